"""The commands that turn flights into training data (`cavenav dataset`); registered on
the command line by `cavenav.cli`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from cavenav.cli.episode_flags import (
    MODEL,
    VLM,
    DetailOpt,
    EnergyPromptOpt,
    HistoryOpt,
    ImageFormatOpt,
    ImageSizeOpt,
    JpegQualityOpt,
    MapImageOpt,
    PromptFileOpt,
    StructuredOpt,
)
from cavenav.cli.output import console

__all__ = ["dataset", "finetune"]

ReplyOpt = Annotated[
    str,
    typer.Option(
        help="full: reasoning, then the dictionary; brief: the dictionary; terse: the "
        "dictionary, justified by the choice's reason alone"
    ),
]


def dataset(
    sources: Annotated[
        list[Path], typer.Argument(help="sweep folders (cavenav eval) and run folders")
    ],
    out: Annotated[Path, typer.Option(help="the dataset folder to write (new or empty)")],
    labels: Annotated[
        str,
        typer.Option(
            help="recorded: the flying pilot's own replies; teacher: those of the teacher "
            "that flew in its shadow (--teacher; DAgger)"
        ),
    ] = "recorded",
    episodes: Annotated[
        str | None,
        typer.Option(
            help="successful or all (default: successful for recorded labels, all for a teacher's)"
        ),
    ] = None,
    drop_shielded: Annotated[
        bool, typer.Option(help="leave out the steps whose action the safety shield replaced")
    ] = True,
    validation: Annotated[
        float, typer.Option(help="share of the caves held out for validation (split by cave)")
    ] = 0.1,
    reply: ReplyOpt = "full",
    shard_rows: Annotated[int, typer.Option(help="rows in a Parquet shard")] = 1000,
    allow_mixed: Annotated[
        bool, typer.Option(help="accept sources flown with different settings or prompts")
    ] = False,
    detail: DetailOpt = None,
    history: HistoryOpt = MODEL.history,
    prompt_file: PromptFileOpt = None,
    structured: StructuredOpt = MODEL.structured,
    map_image: MapImageOpt = MODEL.map_image,
    energy_prompt: EnergyPromptOpt = MODEL.energy_prompt,
    image_format: ImageFormatOpt = MODEL.image_format,
    jpeg_quality: JpegQualityOpt = MODEL.jpeg_quality,
    image_size: ImageSizeOpt = None,
) -> None:
    """Make a Hugging Face dataset of flights: one row a decision, its request as the VLM
    pilot sends it and the reply it should give."""
    vlm = VLM.value(locals())  # the options that shape the requests a dataset holds
    from cavenav.training.dataset import DatasetOptions, export_dataset

    options = DatasetOptions(
        labels=labels,
        episodes=episodes,
        drop_shielded=drop_shielded,
        validation=validation,
        reply=reply,
        shard_rows=shard_rows,
        allow_mixed=allow_mixed,
        vlm=vlm,
    )
    columns = (TextColumn("rows"), BarColumn(), MofNCompleteColumn())
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task("rows", total=None)
        done = export_dataset(sources, out, options, lambda n: bar.advance(task, n))
    rows, caves = done.rows, done.card["caves"]
    console.print(
        f"{rows['train']:,} train and {rows['validation']:,} validation rows from "
        f"{done.episodes} episodes ({caves['train']} + {caves['validation']} caves), "
        f"{done.decisions_per_s:,.0f} decisions/s"
    )
    console.print(f"dataset: {done.out}")


def finetune(
    dataset: Annotated[Path, typer.Argument(help="a dataset folder (cavenav dataset)")],
    out: Annotated[Path, typer.Option(help="the model folder to write (a stopped run resumes)")],
    base: Annotated[
        Path | None,
        typer.Option(help="a local image-text-to-text model folder to start from"),
    ] = None,
    new: Annotated[
        str | None,
        typer.Option(help="build a fresh model instead: small (SmolVLM's architecture, 2.5 M)"),
    ] = None,
    prompt_file: Annotated[
        Path | None,
        typer.Option(help="a system prompt of the model's own; it flies with it from then on"),
    ] = None,
    epochs: Annotated[float, typer.Option(min=0.0, help="passes over the training rows")] = 1.0,
    max_steps: Annotated[
        int | None, typer.Option(min=1, help="optimiser steps (instead of --epochs)")
    ] = None,
    batch_size: Annotated[int, typer.Option(min=1, help="rows an optimiser step")] = 8,
    learning_rate: Annotated[
        float | None, typer.Option(help="default: 1e-3 fresh, 2e-4 LoRA, 5e-5 otherwise")
    ] = None,
    lora: Annotated[
        bool | None,
        typer.Option(help="train LoRA adapters (default: for bases over 50 M parameters)"),
    ] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    validation_rows: Annotated[
        int, typer.Option(min=0, help="validation rows whose actions are scored at the end")
    ] = 64,
    seed: Annotated[int, typer.Option(min=0, help="a fresh model's weights, the shuffling")] = 0,
) -> None:
    """Fine-tune a vision-language pilot on a dataset of flights (the train extra)."""
    from cavenav.training.finetune import FinetuneOptions
    from cavenav.training.finetune import finetune as train

    options = FinetuneOptions(
        base=base,
        new=new,
        prompt_file=prompt_file,
        epochs=epochs,
        max_steps=max_steps,
        batch_size=batch_size,
        learning_rate=learning_rate,
        lora=lora,
        device=device,
        validation_rows=validation_rows,
        seed=seed,
    )
    done = train(dataset, out, options)
    scores = done.validation
    chose = (
        f"; validation: {scores['parsed']:.0%} parse, {scores['action']:.0%} whole actions, "
        f"{scores['parts']:.0%} all four parts, {scores['median_ms']} ms a decision"
        if scores
        else ""
    )
    console.print(f"{done.steps} steps, loss {done.first_loss:.3f} -> {done.last_loss:.3f}{chose}")
    console.print(f"model: {done.out}")

"""Fine-tuning a vision-language pilot on a `cavenav dataset`: `cavenav finetune`.

transformers' `Trainer` runs the training (CPU or CUDA, checkpoints, resume, its progress
bar); this module only says what a sample is and what is written:

- A sample is a row's request, turned into the model's chat exactly as the transformers
  backend turns a request in flight (`cavenav.pilots.backends.local_chat`), then the
  target reply after the generation prompt. The loss counts the reply's tokens only.
- The base is any local image-text-to-text folder (SmolVLM, Idefics3, Qwen2.5-VL, ...),
  trained whole when small and through LoRA adapters (PEFT) when large, merged back at
  the end so that the folder loads and serves as a plain model; or a fresh small model
  built here (`--new small`, `cavenav.training.small_vlm`).
- A model may learn with a prompt of its own (`--prompt-file`), shorter than the
  packaged one: every row's system prompt is replaced by it. The model folder keeps the
  prompt and the image settings it learned with (cavenav_pilot.json, cavenav_prompt.md),
  and the VLM pilot flies it with them (`VLMOptions.for_model`): the model and its
  prompt never part.

OUT/
  model weights (safetensors), config, processor: what the transformers backend and
      `transformers serve` load
  cavenav_pilot.json, cavenav_prompt.md   how the model must be asked
  training/loss.csv, training/loss.png    the loss per logged step (and validation)
  training/validation.json                action accuracy on validation rows, latency
  README.md                               the model card, written last
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from cavenav.core.errors import ActionError, ConfigError, DependencyError, RecordingError
from cavenav.core.files import save_figure
from cavenav.episode.run_folder import write_atomic, write_json
from cavenav.motion.actions import parse_action
from cavenav.pilots.backends import TransformersBackend, TransformersConfig, local_chat
from cavenav.pilots.factory import PILOT_SETTINGS, PROMPT_FILE, VLMOptions
from cavenav.pilots.prompt import PromptConfig, render_system
from cavenav.pilots.reply import parse_reply
from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.depth import DEPTH_RANGE_M
from cavenav.training.dataset import request_messages
from cavenav.training.small_vlm import SMALL, build_small_vlm

__all__ = ["FinetuneOptions", "Finetuned", "finetune", "score_actions"]

NEW_MODELS = {"small": SMALL}
# The validation rows whose loss is measured after each epoch.
EVAL_ROWS = 256
# A base with more parameters than this is trained through LoRA adapters by default.
LORA_ABOVE = 50_000_000


@dataclass(frozen=True)
class FinetuneOptions:
    """How to train.

    Attributes:
        base: a local image-text-to-text model folder to start from; or
        new: the name of a fresh model to build (`NEW_MODELS`), its tokenizer trained on
            the dataset's text.
        prompt_file: a system-prompt template of the model's own, replacing the rows'.
        epochs: passes over the training rows (``max_steps`` wins when set).
        max_steps: optimiser steps; None: as many as ``epochs`` take.
        batch_size: rows a step.
        learning_rate: None: 1e-3 for a fresh model, 2e-4 through LoRA, 5e-5 otherwise.
        lora: None: LoRA for bases over `LORA_ABOVE` parameters.
        device: "auto" (CUDA when there is one), "cpu" or "cuda".
        validation_rows: validation rows whose actions are scored at the end (0: none).
        save_steps: a checkpoint every this many steps, to resume from.
        seed: the fresh model's weights, the shuffling.
    """

    base: Path | None = None
    new: str | None = None
    prompt_file: Path | None = None
    epochs: float = 1.0
    max_steps: int | None = None
    batch_size: int = 8
    learning_rate: float | None = None
    lora: bool | None = None
    device: str = "auto"
    validation_rows: int = 64
    save_steps: int = 200
    seed: int = 0

    def __post_init__(self) -> None:
        if (self.base is None) == (self.new is None):
            raise ConfigError("give --base MODEL_DIR or --new small, not both and not neither")
        if self.new is not None and self.new not in NEW_MODELS:
            raise ConfigError(f"--new must be one of {', '.join(NEW_MODELS)}, not '{self.new}'")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"--device must be auto, cpu or cuda, not '{self.device}'")
        if self.prompt_file is not None and not Path(self.prompt_file).is_file():
            raise ConfigError(f"--prompt-file {self.prompt_file}: no such file")


@dataclass(frozen=True)
class Finetuned:
    """What training produced: the model folder, the steps, the losses and the scores."""

    out: Path
    steps: int
    first_loss: float
    last_loss: float
    validation: dict[str, Any]
    seconds: float


def _torch() -> Any:  # noqa: ANN401 - the module
    try:
        import torch
        import transformers  # noqa: F401
    except ImportError as exc:
        raise DependencyError(
            f"cavenav finetune needs torch and transformers ({exc}); install with: "
            "pip install 'cavenav[train]'"
        ) from None
    return torch


def _device(asked: str, torch: Any) -> str:  # noqa: ANN401
    if asked == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: this machine has no CUDA device; use --device cpu")
    if asked == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return asked


def _dataset(folder: Path, cache: Path) -> tuple[Any, dict[str, Any]]:  # noqa: ANN401
    """The dataset's splits (images as bytes) and its cavenav_dataset.json.

    datasets converts the shards into its own cache, which it keys by the files' names,
    sizes and times, not by their folder: two datasets exported alike would share one
    entry, and a model could train on the other's rows. The cache here is the training
    run's own (``cache``).
    """
    import datasets

    about = Path(folder) / "cavenav_dataset.json"
    if not about.is_file():
        raise ConfigError(f"{folder} is not a cavenav dataset (no cavenav_dataset.json)")
    card = json.loads(about.read_text(encoding="utf-8"))
    files = {split: [str(Path(folder) / name) for name in names]
             for split, names in card["files"].items() if names}  # fmt: skip
    splits = datasets.load_dataset("parquet", data_files=files, cache_dir=str(cache))
    raw = datasets.List(datasets.Image(decode=False))
    return {name: split.cast_column("images", raw) for name, split in splits.items()}, card


def _check_base(base: Path) -> None:
    """Refuse a folder that is not an image-text-to-text model, before loading weights."""
    from transformers import AutoConfig
    from transformers.models.auto.modeling_auto import MODEL_FOR_IMAGE_TEXT_TO_TEXT_MAPPING_NAMES

    if not (Path(base) / "config.json").is_file():
        raise ConfigError(f"--base {base}: no model folder (config.json) there")
    try:
        kind = AutoConfig.from_pretrained(base).model_type
    except (OSError, ValueError) as exc:
        raise ConfigError(f"--base {base}: cannot read its config ({exc})") from None
    if kind not in MODEL_FOR_IMAGE_TEXT_TO_TEXT_MAPPING_NAMES:
        raise ConfigError(
            f"--base {base} is a '{kind}' model, not an image-text-to-text one (SmolVLM, "
            "Idefics3, Qwen2.5-VL, ...)"
        )


def _texts(split: Any) -> Any:  # noqa: ANN401 - an iterator of str
    """Every text a fresh tokenizer should know: prompts and replies."""
    for row in split.select_columns(["messages", "reply"]):
        for message in row["messages"]:
            for part in message["content"]:
                if part["text"]:
                    yield part["text"]
        yield row["reply"]


class _System:
    """The system prompt a model learns and flies with: the rows' own, or ``prompt_file``
    rendered with the dataset's depth range and field of view."""

    def __init__(self, prompt_file: Path | None, card: Mapping[str, Any]):
        self.text: str | None = None
        if prompt_file is not None:
            sensors = card["settings"].get("sensors") or {}
            history = card["prompt"].get("history", PromptConfig.history)
            config = PromptConfig(history=history, system_file=prompt_file)
            low, high = DEPTH_RANGE_M
            depth = (sensors.get("depth_min_m", low), sensors.get("depth_max_m", high))
            hfov = CameraIntrinsics(**sensors["camera"]).hfov_deg if "camera" in sensors else None
            self.text = render_system(config, depth, hfov)

    def messages(self, row: Mapping[str, Any]) -> list[dict[str, Any]]:
        messages = request_messages(row)
        if self.text is not None and messages and messages[0]["role"] == "system":
            messages[0] = {"role": "system", "content": self.text}
        return messages


class _Collator:
    """Rows to a batch: the processor's inputs for request + reply, labels on the reply."""

    def __init__(self, processor: Any, system: _System):  # noqa: ANN401
        self.processor, self.system = processor, system
        self.tokenizer = processor.tokenizer
        self.tokenizer.padding_side = "right"
        self.end = self.tokenizer.eos_token or ""

    def __call__(self, rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
        texts, images, replies = [], [], []
        for row in rows:
            chat, pictures = local_chat(self.system.messages(row))
            prompt = self.processor.apply_chat_template(chat, add_generation_prompt=True)
            reply = " " + row["reply"] + self.end  # a space: the reply's first token stands alone
            texts.append(prompt + reply)
            images.append(pictures)
            replies.append(self.tokenizer(reply, add_special_tokens=False)["input_ids"])
        batch = self.processor(text=texts, images=images, padding=True, return_tensors="pt")
        labels = batch["input_ids"].clone()
        labels[batch["attention_mask"] == 0] = -100
        for i, reply in enumerate(replies):
            end = int(batch["attention_mask"][i].sum())
            if labels[i, end - len(reply) : end].tolist() != reply:
                raise ConfigError("the tokenizer joins the reply to its prompt: cannot mask it")
            labels[i, : end - len(reply)] = -100
        batch["labels"] = labels
        return dict(batch)


def _model(options: FinetuneOptions, out: Path, train: Any, device: str) -> tuple[Any, Any, bool]:  # noqa: ANN401
    """(processor, model, whether LoRA adapters train it), the base loaded or built."""
    from transformers import AutoModelForImageTextToText, AutoProcessor

    base = options.base
    if base is None:
        base = out / "base"  # built once: a resumed run starts from the same weights
        if not (base / "config.json").is_file():
            build_small_vlm(base, _texts(train), NEW_MODELS[str(options.new)], options.seed)
    processor = AutoProcessor.from_pretrained(base)
    model = AutoModelForImageTextToText.from_pretrained(base).to(device)  # type: ignore[arg-type]
    size = sum(p.numel() for p in model.parameters())
    lora = options.lora if options.lora is not None else size > LORA_ABOVE
    if lora:
        from peft import LoraConfig, get_peft_model

        adapters = LoraConfig(r=16, lora_alpha=32, lora_dropout=0.05,
                              target_modules=["q_proj", "k_proj", "v_proj", "o_proj"])  # fmt: skip
        model = get_peft_model(model, adapters)
    return processor, model, lora


def _last_checkpoint(folder: Path) -> Path | None:
    """The newest whole checkpoint (its trainer state written last, so a checkpoint cut
    short by a full disk or a kill has none); the ones cut short are removed."""
    whole = None
    for path in sorted(folder.glob("checkpoint-*"), key=lambda p: int(p.name.split("-")[1])):
        if (path / "trainer_state.json").is_file():
            whole = path
        else:
            shutil.rmtree(path, ignore_errors=True)
    return whole


def finetune(dataset: Path, out: Path, options: FinetuneOptions) -> Finetuned:
    """Train on ``dataset`` into ``out`` (resuming a run stopped there).

    Raises:
        DependencyError: torch or transformers missing.
        ConfigError: a bad base, dataset or device.
        RecordingError: ``out`` cannot be written (a full disk).
    """
    torch = _torch()
    device = _device(options.device, torch)
    if options.base is not None:
        _check_base(options.base)
    if not (Path(dataset) / "cavenav_dataset.json").is_file():
        raise ConfigError(f"{dataset} is not a cavenav dataset (no cavenav_dataset.json)")
    out = Path(out)
    if (out / "README.md").is_file():
        raise ConfigError(f"{out} holds a finished model; give another --out")
    started = time.perf_counter()
    try:
        out.mkdir(parents=True, exist_ok=True)
        splits, card = _dataset(Path(dataset), out / "cache")
        if "train" not in splits:
            raise ConfigError(f"{dataset} has no train split")
        processor, model, lora = _model(options, out, splits["train"], device)
        system = _System(options.prompt_file, card)
        trainer = _trainer(model, processor, system, splits, options, out, device, lora)
        resume = _last_checkpoint(out / "checkpoints")
        trainer.train(resume_from_checkpoint=str(resume) if resume else None)
        if lora:
            model = model.merge_and_unload()
        _save(model, processor, out, system, card, options)
    except OSError as exc:
        raise RecordingError.cannot_write(out, exc) from None
    history = trainer.state.log_history
    losses = [entry["loss"] for entry in history if "loss" in entry]
    validation = score_actions(out, splits.get("validation"), options.validation_rows, card, device)
    result = Finetuned(out, trainer.state.global_step, losses[0] if losses else math.nan,
                       losses[-1] if losses else math.nan, validation,
                       time.perf_counter() - started)  # fmt: skip
    _write_records(out, history, result, dataset, card, options, lora)
    for scaffolding in ("checkpoints", "base", "cache"):  # what a resumed run needed
        shutil.rmtree(out / scaffolding, ignore_errors=True)
    return result


def _trainer(
    model: Any, processor: Any, system: _System, splits: Mapping[str, Any],  # noqa: ANN401
    options: FinetuneOptions, out: Path, device: str, lora: bool,
) -> Any:  # fmt: skip  # noqa: ANN401 - a transformers Trainer
    from transformers import Trainer, TrainingArguments

    rate = options.learning_rate or (1e-3 if options.new else 2e-4 if lora else 5e-5)
    arguments = TrainingArguments(
        output_dir=str(out / "checkpoints"),
        per_device_train_batch_size=options.batch_size,
        per_device_eval_batch_size=options.batch_size,
        num_train_epochs=options.epochs,
        max_steps=options.max_steps or -1,
        learning_rate=rate,
        # A fresh model's rate climbs from 0 over its first 5% of steps, the usual warm-up
        # of a transformer trained from scratch (weights already trained need none).
        warmup_steps=0.05 if options.new else 0,
        logging_steps=1 if (options.max_steps or 0) and options.max_steps <= 50 else 10,
        save_strategy="steps",
        save_steps=options.save_steps,
        save_total_limit=1,
        eval_strategy="epoch" if "validation" in splits else "no",
        report_to="none",
        remove_unused_columns=False,
        use_cpu=device == "cpu",
        seed=options.seed,
        dataloader_num_workers=0,
    )
    return Trainer(
        model=model,
        args=arguments,
        train_dataset=splits["train"],
        eval_dataset=_spread(splits.get("validation"), EVAL_ROWS),
        data_collator=_Collator(processor, system),
    )


def _spread(rows: Any, count: int) -> Any:  # noqa: ANN401 - a datasets.Dataset or None
    """``count`` rows evenly spaced over ``rows``: rows come cave by cave, episode by
    episode, so the first 64 would all be one cave's (and its start)."""
    if rows is None:
        return None
    step = max(1, len(rows) // max(count, 1))
    return rows.select(range(0, len(rows), step)[:count])


def _save(
    model: Any, processor: Any, out: Path, system: _System,  # noqa: ANN401
    card: Mapping[str, Any], options: FinetuneOptions,
) -> None:  # fmt: skip
    """The model, its processor and how it must be asked, into ``out`` through a partial
    folder: a model file in ``out`` is whole."""
    partial = out / ".partial-model"
    shutil.rmtree(partial, ignore_errors=True)
    model.save_pretrained(partial)
    processor.save_pretrained(partial)
    for path in partial.iterdir():
        os.replace(path, out / path.name)
    partial.rmdir()
    prompt = dict(card.get("prompt") or {})
    if system.text is not None:
        write_atomic(out / PROMPT_FILE, Path(str(options.prompt_file)).read_text(encoding="utf-8"))
        prompt["prompt_file"] = PROMPT_FILE
    write_json(out / PILOT_SETTINGS, {"prompt": prompt, "reply": card.get("reply")})


def score_actions(
    model_dir: Path,
    rows: Any,
    limit: int,
    card: Mapping[str, Any],
    device: str = "cpu",  # noqa: ANN401
) -> dict[str, Any]:
    """How often the model, asked as the pilot asks it, gives the row's action: over
    ``limit`` rows spread evenly over ``rows``, the share whose first reply parses, whose
    whole action string matches, whose four parts all match and whose each part matches
    (forward, strafe and yaw exactly; the vertical move within 0.1 m, being continuous:
    "ascend 0.16 m" for "ascend 0.15 m" fails the whole string but not the parts); and
    the median milliseconds a decision took.

    Args:
        card: the rows' dataset's cavenav_dataset.json (its camera renders the model's
            own prompt, as each observation's camera does in flight).
    """
    if rows is None or limit <= 0 or len(rows) == 0:
        return {}
    model_dir = Path(model_dir)
    options = VLMOptions(model=str(model_dir), backend="transformers").for_model()
    chosen = _spread(rows, limit)
    backend = TransformersBackend(TransformersConfig(str(model_dir), device=device))
    # A reply twice as long as the longest target is wrong however it ends: stop there.
    longest = max(backend.count_tokens(row["reply"]) for row in chosen)
    budget = min(options.max_tokens, 2 * longest + 8)
    backend.config = replace(backend.config, max_new_tokens=budget)
    system = _System(Path(options.prompt_file) if options.prompt_file else None, card)
    counts = dict.fromkeys(("parsed", "action", "parts", "forward", "right", "up", "yaw_deg"), 0)
    latencies = []
    for row in chosen:
        completion = backend.complete(system.messages(row))
        latencies.append(completion.latency_s)
        try:
            got = parse_reply(completion.text)
        except ActionError:
            continue
        want = parse_action(row["action"])
        matched = {part: getattr(got.action, part) == getattr(want, part)
                   for part in ("forward", "right", "yaw_deg")}  # fmt: skip
        matched["up"] = abs(got.action.up - want.up) <= 0.1
        counts["parsed"] += 1
        counts["action"] += got.action == want
        counts["parts"] += all(matched.values())
        for part, same in matched.items():
            counts[part] += same
    latencies.sort()
    scored = {key: round(value / len(chosen), 4) for key, value in counts.items()}
    return {
        "rows": len(chosen),
        **scored,
        "median_ms": round(1e3 * latencies[len(latencies) // 2], 1),
    }


def _write_records(
    out: Path, history: list[dict[str, Any]], result: Finetuned, dataset: Path,
    card: Mapping[str, Any], options: FinetuneOptions, lora: bool,
) -> None:  # fmt: skip
    """training/ (loss.csv, loss.png, validation.json, dataset.json), then the card."""
    from cavenav.training.card import model_card

    folder = out / "training"
    folder.mkdir(exist_ok=True)
    with open(folder / "loss.csv", "w", newline="", encoding="utf-8") as file:
        rows = csv.writer(file)
        rows.writerow(["step", "epoch", "loss", "validation_loss"])
        for entry in history:
            if "loss" in entry or "eval_loss" in entry:
                rows.writerow([entry.get("step"), entry.get("epoch"), entry.get("loss", ""),
                               entry.get("eval_loss", "")])  # fmt: skip
    _plot_loss(history, folder / "loss.png")
    write_json(folder / "validation.json", result.validation)
    write_json(folder / "dataset.json", card)
    about = {
        **{k: str(v) if isinstance(v, Path) else v for k, v in asdict(options).items()},
        "lora": lora,
        "dataset": str(dataset),
        "steps": result.steps,
        "first_loss": result.first_loss,
        "last_loss": result.last_loss,
        "train_s": round(result.seconds, 1),
    }
    write_atomic(out / "README.md", model_card(about, card, result.validation))


def _plot_loss(history: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6, 3.5), dpi=110)
    train = [(e["step"], e["loss"]) for e in history if "loss" in e]
    held = [(e["step"], e["eval_loss"]) for e in history if "eval_loss" in e]
    if train:
        axes.plot(*zip(*train, strict=True), label="training")
    if held:
        axes.plot(*zip(*held, strict=True), "o-", label="validation")
    axes.set(xlabel="optimiser step", ylabel="loss (reply tokens)", yscale="log")
    axes.legend()
    axes.grid(alpha=0.3)
    figure.tight_layout()
    save_figure(figure, path)
    plt.close(figure)

"""Fine-tuning a pilot on flights (`cavenav finetune`): the loss falls, the folder flies
as the pilot flies it, asked as it learned, and bad input is refused before anything."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("datasets")

from cavenav.episode.loop import EpisodeConfig, run_episode  # noqa: E402
from cavenav.errors import ConfigError  # noqa: E402
from cavenav.pilots.factory import PilotSpec, VLMOptions  # noqa: E402
from cavenav.pilots.geometric import GeometricPilot  # noqa: E402
from cavenav.training.dataset import DatasetOptions, export_dataset  # noqa: E402
from cavenav.training.finetune import FinetuneOptions, finetune  # noqa: E402
from cavenav.world.scenarios import load_scenario  # noqa: E402

from .conftest import cavenav  # noqa: E402
from .tiny_vlm import build_tiny_idefics3  # noqa: E402

SMALL_PROMPT = Path(__file__).parents[1] / "src" / "cavenav" / "pilots" / "prompts" / "small.md"


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dataset of two short geometric flights in two caves, images at 64x48."""
    root = tmp_path_factory.mktemp("flights")
    config = EpisodeConfig(max_steps=4, save_frames=False, plots=False)
    runs = [root / f"S1-{seed}" for seed in (0, 1)]
    for seed, run_dir in zip((0, 1), runs, strict=True):
        run_episode(load_scenario("S1", seed), GeometricPilot(), config, run_dir)
    options = DatasetOptions(episodes="all", reply="brief", validation=0.5,
                             vlm=VLMOptions(image_size="64x48"))  # fmt: skip
    export_dataset(runs, root / "data", options)
    return root / "data"


@pytest.mark.slow
def test_a_few_training_steps_lower_the_loss(flights: Path, tmp_path: Path) -> None:
    base = build_tiny_idefics3(tmp_path / "tiny")
    out = tmp_path / "model"
    options = FinetuneOptions(base=base, prompt_file=SMALL_PROMPT, max_steps=12, batch_size=4,
                              learning_rate=1e-2, validation_rows=2, device="cpu")  # fmt: skip
    done = finetune(flights, out, options)
    assert done.steps == 12 and done.last_loss < 0.7 * done.first_loss
    losses = (out / "training" / "loss.csv").read_text().splitlines()
    assert losses[0] == "step,epoch,loss,validation_loss" and len(losses) >= 13
    assert (out / "training" / "loss.png").stat().st_size > 0
    # Scored as the pilot flies it: the transformers backend, greedy, on held-out rows.
    assert done.validation["rows"] == 2 and done.validation["median_ms"] > 0
    card = (out / "README.md").read_text()
    assert "pipeline_tag: image-text-to-text" in card and "12 optimiser steps" in card
    assert not (out / "checkpoints").exists()  # scaffolding for a resumed run, gone


@pytest.mark.slow
def test_a_fresh_small_model_keeps_its_prompt_and_flies_with_it(
    flights: Path, tmp_path: Path
) -> None:
    out = tmp_path / "small"
    options = FinetuneOptions(new="small", prompt_file=SMALL_PROMPT, max_steps=2,
                              batch_size=2, validation_rows=0, device="cpu")  # fmt: skip
    finetune(flights, out, options)
    kept = json.loads((out / "cavenav_pilot.json").read_text())["prompt"]
    assert kept["prompt_file"] == "cavenav_prompt.md" and kept["image_size"] == "64x48"
    assert (out / "cavenav_prompt.md").read_text() == SMALL_PROMPT.read_text()
    flown = VLMOptions(model=str(out), backend="transformers", image_size="640x480").for_model()
    assert flown.prompt_file == str(out / "cavenav_prompt.md") and flown.image_size == "64x48"
    assert not (out / "base").exists()
    # It flies as a VLM pilot, its own prompt first in every request.
    pilot = PilotSpec("vlm", flown).build()
    assert pilot.prompt.system_file == out / "cavenav_prompt.md"  # type: ignore[attr-defined]


def test_bad_input_is_refused_before_anything_is_written(flights: Path, tmp_path: Path) -> None:
    text_only = tmp_path / "text-only"
    text_only.mkdir()
    (text_only / "config.json").write_text(json.dumps({"model_type": "llama"}))
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match="not an image-text-to-text one"):
        finetune(flights, out, FinetuneOptions(base=text_only, device="cpu"))
    with pytest.raises(ConfigError, match="not both and not neither"):
        FinetuneOptions()
    with pytest.raises(ConfigError, match="not a cavenav dataset"):
        finetune(tmp_path, out, FinetuneOptions(new="small", device="cpu"))
    assert not out.exists()


@pytest.mark.slow
def test_cuda_asked_of_a_machine_without_it_is_one_line_and_exit_2(
    flights: Path, tmp_path: Path
) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    done = cavenav("finetune", str(flights), "--new", "small", "--device", "cuda",
                   "--out", str(tmp_path / "out"))  # fmt: skip
    assert done.returncode == 2 and "no CUDA device" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()

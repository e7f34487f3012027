"""Fine-tuning a pilot on flights (`cavenav finetune`): the loss falls, the folder flies
as the pilot flies it, asked as it learned, the same locally and through Hugging Face's
own OpenAI-compatible server (`transformers serve`, on 127.0.0.1), and bad input is
refused before anything."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("datasets")

import pyarrow as pa  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

from cavenav.core.errors import ConfigError  # noqa: E402
from cavenav.episode.loop import run_episode  # noqa: E402
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.factory import PilotSpec, VLMOptions  # noqa: E402
from cavenav.pilots.geometric import GeometricPilot  # noqa: E402
from cavenav.training.dataset import DatasetOptions, export_dataset  # noqa: E402
from cavenav.training.finetune import FinetuneOptions, finetune  # noqa: E402
from cavenav.world.scenarios import load_scenario  # noqa: E402
from tests.conftest import cavenav  # noqa: E402
from tests.tiny_vlm import build_tiny_idefics3  # noqa: E402

SMALL_PROMPT = Path(__file__).parents[2] / "src" / "cavenav" / "pilots" / "prompts" / "small.md"


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
def test_a_few_training_steps_lower_the_loss(holding_model: Path) -> None:
    losses = (holding_model / "training" / "loss.csv").read_text().splitlines()
    assert losses[0] == "step,epoch,loss,validation_loss" and len(losses) >= 31
    steps = [line.split(",") for line in losses[1:] if line.split(",")[2]]
    assert len(steps) == 30 and float(steps[-1][2]) < 0.3 * float(steps[0][2])
    assert (holding_model / "training" / "loss.png").stat().st_size > 0
    # Scored as the pilot flies it: the transformers backend, greedy, on held-out rows.
    scores = json.loads((holding_model / "training" / "validation.json").read_text())
    assert scores["rows"] == 2 and scores["parsed"] == 1.0 and scores["median_ms"] > 0
    card = (holding_model / "README.md").read_text()
    assert "pipeline_tag: image-text-to-text" in card and "30 optimiser steps" in card
    assert "| first reply parses | 100.0% |" in card
    assert not (holding_model / "checkpoints").exists()  # a resumed run's scaffolding, gone
    assert not (holding_model / "cache").exists()
    with pytest.raises(ConfigError, match="holds a finished model"):
        finetune(holding_model.parent / "data", holding_model, FinetuneOptions(new="small"))


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


@pytest.mark.slow
def test_lora_adapters_are_merged_into_a_plain_model(flights: Path, tmp_path: Path) -> None:
    from transformers import AutoModelForImageTextToText

    base = build_tiny_idefics3(tmp_path / "tiny")
    out = tmp_path / "lora"
    options = FinetuneOptions(base=base, prompt_file=SMALL_PROMPT, lora=True, max_steps=2,
                              batch_size=2, validation_rows=0, device="cpu")  # fmt: skip
    finetune(flights, out, options)
    assert not list(out.glob("adapter_*"))  # merged: no adapters to load apart
    model = AutoModelForImageTextToText.from_pretrained(out)
    assert not any("lora" in name for name, _ in model.named_parameters())
    assert "LoRA adapters, merged" in (out / "README.md").read_text()


# What the model learns to answer, whatever it sees: one token of its own, so that a few
# steps teach the tiny model to say it.
REPLY = '{"hold": "no way on"}'


@pytest.fixture(scope="module")
def holding_model(flights: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny model, trained on the flights' requests to answer `REPLY` to each."""
    from transformers import AutoModelForImageTextToText, AutoProcessor

    root = tmp_path_factory.mktemp("holding")
    base = build_tiny_idefics3(root / "tiny")
    processor = AutoProcessor.from_pretrained(base)
    processor.tokenizer.add_tokens([REPLY])
    model = AutoModelForImageTextToText.from_pretrained(base)
    model.resize_token_embeddings(len(processor.tokenizer))
    model.save_pretrained(base)
    processor.save_pretrained(base)
    shutil.copytree(flights, root / "data")
    for shard in (root / "data" / "data").glob("*.parquet"):  # every reply the same
        table = pq.read_table(shard)
        replies = pa.array([REPLY] * table.num_rows)
        pq.write_table(table.set_column(table.schema.get_field_index("reply"), "reply", replies),
                       shard)  # fmt: skip
    training = FinetuneOptions(base=base, prompt_file=SMALL_PROMPT, max_steps=30, batch_size=2,
                               learning_rate=5e-2, validation_rows=2, device="cpu")  # fmt: skip
    finetune(root / "data", root / "model", training)
    return root / "model"


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def served(holding_model: Path) -> Iterator[str]:
    """`transformers serve` with the model, on 127.0.0.1; its base URL."""
    pytest.importorskip("fastapi")  # transformers' [serving] extra: the test extra has it
    port = _free_port()
    command = [str(Path(sys.executable).parent / "transformers"), "serve", str(holding_model),
               "--host", "127.0.0.1", "--port", str(port), "--device", "cpu"]  # fmt: skip
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    server = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2)
                break
            except OSError:
                if server.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(server.stderr.read().decode()[-2000:]) from None
                time.sleep(0.25)
        yield f"http://127.0.0.1:{port}/v1"
    finally:
        server.terminate()
        server.wait(timeout=30)


@pytest.mark.slow
def test_a_trained_model_flies_alike_locally_and_through_transformers_serve(
    holding_model: Path, served: str, tmp_path: Path
) -> None:
    ways = {
        "local": VLMOptions(model=str(holding_model), backend="transformers"),
        "served": VLMOptions(model=str(holding_model), base_url=served),
    }
    flown = {}
    for way, options in ways.items():
        greedy = VLMOptions(**{**options.__dict__, "temperature": 0.0, "max_tokens": 8})
        pilot = PilotSpec("vlm", greedy.for_model()).build()
        config = EpisodeConfig(max_steps=3, save_frames=False, plots=False)
        result = run_episode(load_scenario("S1"), pilot, config, tmp_path / way)
        exchanges = [json.loads(line) for line in (tmp_path / way / "exchanges.jsonl").open()]
        flown[way] = (result, exchanges)
    (local, asked_here), (served_result, asked_there) = flown["local"], flown["served"]
    assert [s["action"] for s in local.steps] == [s["action"] for s in served_result.steps]
    assert [s["action"] for s in local.steps] == ["hold"] * 3  # what it learned to say
    assert [e["reply"].strip() for e in asked_here] == [e["reply"].strip() for e in asked_there]
    # The same prompt reached the model both ways, its own system prompt and images.
    assert [e["prompt_tokens"] for e in asked_here] == [e["prompt_tokens"] for e in asked_there]
    assert asked_here[0]["messages"][0]["content"].startswith("You pilot an underwater robot")
    # The report's latency per decision is measured both ways.
    for result in (local, served_result):
        assert result.summary["usage"]["mean_latency_s"] > 0

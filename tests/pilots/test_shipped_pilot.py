"""The small VLM pilot shipped in the repository (`models/cavenav-pilot-small`): a fresh
clone flies a model that reads the frames, with no download, asked as it learned."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import cavenav

MODEL = Path(__file__).parents[2] / "models" / "cavenav-pilot-small"


def test_the_shipped_model_is_small_and_keeps_its_prompt_and_card() -> None:
    size = sum(file.stat().st_size for file in MODEL.rglob("*") if file.is_file())
    assert size <= 25 * 2**20
    for name in ("model.safetensors", "config.json", "tokenizer.json", "chat_template.jinja",
                 "cavenav_prompt.md", "cavenav_pilot.json", "training/loss.png"):  # fmt: skip
        assert (MODEL / name).is_file(), name
    asked = json.loads((MODEL / "cavenav_pilot.json").read_text())
    assert asked["prompt"]["prompt_file"] == "cavenav_prompt.md"
    card = (MODEL / "README.md").read_text()
    assert "pipeline_tag: image-text-to-text" in card
    assert "examples/train_small_pilot.sh" in card  # how to make it again


@pytest.mark.slow
def test_a_fresh_clone_flies_the_shipped_model(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    done = cavenav("run", "S1", "--pilot", "vlm", "--backend", "transformers", "--model",
                   str(MODEL), "--temperature", "0", "--steps", "3", "--no-frames",
                   "--out", str(tmp_path))  # fmt: skip
    assert done.returncode == 0, done.stderr
    (run,) = tmp_path.iterdir()
    exchanges = [json.loads(line) for line in (run / "exchanges.jsonl").read_text().splitlines()]
    assert len(exchanges) == 3 and all(e["rejected"] is None for e in exchanges)
    system = exchanges[0]["messages"][0]["content"]
    assert system.startswith("You pilot an underwater robot")  # its own short prompt
    steps = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
    assert [s["vlm"]["requeries"] for s in steps] == [0, 0, 0]

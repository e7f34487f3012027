"""The dataset card: the README.md of a `cavenav dataset` folder, from its
cavenav_dataset.json. Its YAML header is what datasets reads (the splits' files); the
rest is what a reader asks first: how many rows from which caves and pilots, how the
replies were made, and the prompt a model trained on them must fly with."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["dataset_card", "model_card"]

# The Hub's tags of both cards, closing their YAML header.
_TAGS = """tags:
- robotics
- underwater
- navigation
- cavenav
---"""


def dataset_card(data: Mapping[str, Any]) -> str:
    """The README.md of a dataset: the YAML header datasets reads, then the facts."""
    configs = "\n".join(
        f"  - split: {split}\n    path: data/{split}-*" for split, n in data["rows"].items() if n
    )
    sources = "\n".join(
        f"| `{s['path']}` | {s['kind']} | {s['pilot'].get('label')} | {s['episodes']} |"
        for s in data["sources"]
    )
    facts = "\n".join(f"| {name} | {value} |" for name, value in _facts(data))
    return f"""---
configs:
- config_name: default
  data_files:
{configs}
task_categories:
- image-text-to-text
{_TAGS}
# cavenav flight decisions

Each row is one decision of a pilot flying an underwater vehicle through a simulated
flooded cave (cavenav {data["cavenav_version"]}, scenario set {data["scenario_set"]}): the
request a vision-language pilot is sent at that step (system prompt, the earlier
observations with the actions taken after them, the current colour and depth images and
the echo-sounder ranges) and the reply it should give.

| | |
| --- | --- |
{facts}

## Sources

| folder | kind | pilot | episodes used |
| --- | --- | --- | --- |
{sources}

## Use

```python
import datasets
from cavenav.training.dataset import request_messages

rows = datasets.load_dataset("PATH/TO/THIS/FOLDER")
row = rows["train"].cast_column("images", datasets.List(datasets.Image(decode=False)))[0]
messages = request_messages(row)  # the OpenAI request, byte for byte as the pilot sends it
```

`cavenav finetune PATH/TO/THIS/FOLDER --base MODEL_DIR --out DIR` trains on it. A model
trained on these rows must fly with the prompt settings above; `cavenav_dataset.json`
holds them and the rest of this card as data.
"""


_LABEL_WORDS = {
    "recorded": "the replies the flying pilot gave",
    "teacher": "the replies of a teacher flying in the pilot's shadow (DAgger)",
}


def _skipped(counts: Mapping[str, int]) -> str:
    left = [f"{n} {why}" for why, n in counts.items() if n]
    return "left out: " + ", ".join(left) if left else "none left out"


def _facts(data: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The card's table: what a reader asks first."""
    rows, caves = data["rows"], data["caves"]
    camera = (data["settings"].get("sensors") or {}).get("camera") or {}
    kept = "successful only" if data["successful_only"] else "all"
    shielded = "dropped" if data["drop_shielded"] else "kept"
    return [
        ("rows", f"train {rows['train']:,}, validation {rows['validation']:,}"),
        ("caves", f"train {caves['train']}, validation {caves['validation']} "
                  "(split by cave, never by step)"),
        ("episodes", f"{data['episodes']} ({_skipped(data['skipped_episodes'])})"),
        ("scenarios", ", ".join(data["scenarios"])),
        ("pilots", ", ".join(data["pilots"])),
        ("labels", f"{data['labels']}: {_LABEL_WORDS[data['labels']]}"),
        ("replies", data["reply"]),
        ("episodes kept", f"{kept}; steps the shield replaced {shielded}"),
        ("camera", f"{camera.get('width')}x{camera.get('height')}"),
        ("prompt", ", ".join(f"{k} = {v}" for k, v in data["prompt"].items() if v is not None)),
    ]  # fmt: skip


def model_card(
    about: Mapping[str, Any], dataset: Mapping[str, Any], validation: Mapping[str, Any]
) -> str:
    """The README.md of a `cavenav finetune` model folder: what it is, what it learned
    from, how well it chose the validation rows' actions, and how to fly it."""
    base = f"`{about['base']}`" if about.get("base") else f"a fresh {about['new']} model"
    scores = (
        "\n".join(
            f"| {name} | {validation[key]:.1%} |" for key, name in _SCORES if key in validation
        )
        or "| (no validation rows) | |"
    )
    latency = validation.get("median_ms")
    prompt = ", ".join(
        f"{k} = {Path(v).name if k == 'prompt_file' else v}"  # the name, not this machine's path
        for k, v in dataset.get("prompt", {}).items()
        if v is not None
    )
    return f"""---
library_name: transformers
pipeline_tag: image-text-to-text
{_TAGS}
# A cavenav pilot

A vision-language model that pilots an underwater vehicle through a flooded cave, one
move at a time, from a forward colour image, a depth image and two echo-sounder ranges
(the cavenav method). Trained with `cavenav finetune` from {base}
({"LoRA adapters, merged" if about["lora"] else "all weights"}) on `{about["dataset"]}`:
{dataset["rows"]["train"]:,} decisions of {", ".join(dataset.get("pilots", []))} over
{", ".join(dataset.get("scenarios", []))} ({dataset["labels"]} labels, {dataset["reply"]}
replies), {about["steps"]} optimiser steps in {about["train_s"]} s, loss
{about["first_loss"]:.3f} to {about["last_loss"]:.3f} (`training/loss.png`).

## How it chose the validation caves' actions

{validation.get("rows", 0)} validation decisions, asked exactly as the pilot asks it in
flight, greedy decoding; median {latency if latency is not None else "-"} ms a decision:

| | share |
| --- | --- |
{scores}

These are agreements with the teacher on held-out caves, not flights: fly it
(`cavenav eval`) for success rates.

## Fly it

```bash
cavenav run S1 --pilot vlm --backend transformers --model PATH/TO/THIS/FOLDER --temperature 0
```

It must be asked as it learned ({prompt}): `cavenav_pilot.json` holds these settings
and the VLM pilot takes them from the folder by itself
{"(with its own system prompt, `cavenav_prompt.md`)" if about.get("prompt_file") else ""}.
"""


_SCORES = (
    ("parsed", "first reply parses"),
    ("action", "whole action string"),
    ("parts", "all four parts (ascend/descend within 0.1 m)"),
    ("forward", "forward/back"),
    ("right", "strafe"),
    ("up", "ascend/descend (within 0.1 m)"),
    ("yaw_deg", "turn"),
)

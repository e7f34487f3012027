"""The local transformers backend, on a tiny random model the test builds itself."""

from __future__ import annotations

import base64
import io
import json
import threading
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("transformers")

from cavenav.core.errors import ConfigError  # noqa: E402
from cavenav.episode.loop import run_episode  # noqa: E402
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.backends import TransformersBackend, TransformersConfig  # noqa: E402
from cavenav.pilots.prompt import PromptConfig, render_system  # noqa: E402
from cavenav.pilots.vlm import EncodedObservation, VLMPilot, build_messages, png_data_url  # noqa: E402
from cavenav.world.scenarios import load_scenario  # noqa: E402
from tests.tiny_vlm import build_tiny_idefics3  # noqa: E402


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_tiny_idefics3(tmp_path_factory.mktemp("tiny-idefics3"))


def greedy_reference(model_dir: Path, messages: list[dict], max_new_tokens: int):
    """What transformers itself generates greedily for ``messages``, the backend left out:
    (the processor, the prompt's token ids, the generated token ids)."""
    import torch
    from PIL import Image
    from transformers import AutoModelForImageTextToText, AutoProcessor

    processor = AutoProcessor.from_pretrained(model_dir)
    model = AutoModelForImageTextToText.from_pretrained(model_dir).eval()
    chat, images = [], []
    for message in messages:  # OpenAI-format parts -> the chat template's parts
        content = message["content"]
        if isinstance(content, str):
            content = [{"type": "text", "text": content}]
        parts = []
        for part in content:
            if part["type"] == "text":
                parts.append({"type": "text", "text": part["text"]})
            else:
                data = base64.b64decode(part["image_url"]["url"].split(",", 1)[1])
                images.append(Image.open(io.BytesIO(data)).convert("RGB"))
                parts.append({"type": "image"})
        chat.append({"role": message["role"], "content": parts})
    prompt = processor.apply_chat_template(chat, add_generation_prompt=True)
    inputs = processor(text=prompt, images=images, return_tensors="pt")
    with torch.inference_mode():
        out = model.generate(**inputs, max_new_tokens=max_new_tokens, do_sample=False)
    prompt_ids = inputs["input_ids"][0]
    return processor, prompt_ids, out[0, len(prompt_ids) :]


@pytest.mark.slow
def test_the_tiny_model_answers_through_the_real_backend(tiny_model: Path) -> None:
    backend = TransformersBackend(
        TransformersConfig(str(tiny_model), device="cpu", max_new_tokens=12)
    )
    image = png_data_url(np.zeros((480, 640, 3), np.uint8))
    depth = png_data_url(np.zeros((480, 640), np.uint8))
    system = render_system(PromptConfig())
    messages = build_messages(system, EncodedObservation(image, depth, 2.0, 2.0), [])
    completion = backend.complete(messages)
    assert completion.model == str(tiny_model)
    # Greedy decoding (temperature 0) answers the same request the same way.
    assert backend.complete(messages).text == completion.text
    processor, prompt_ids, new_ids = greedy_reference(tiny_model, messages, 12)
    # The tokens counted are the tokens the model read (system prompt, text and both
    # images) and the tokens it wrote: the whole budget, as this seeded model never stops.
    assert completion.prompt_tokens == len(prompt_ids)
    assert (prompt_ids == processor.image_token_id).sum() == 2 * 4  # 4 tokens per image
    assert len(new_ids) == completion.completion_tokens == 12
    assert completion.text == processor.decode(new_ids, skip_special_tokens=True)


def test_a_small_model_decides_on_one_thread_of_the_thread_that_asks(tiny_model: Path) -> None:
    import torch

    backend = TransformersBackend(
        TransformersConfig(str(tiny_model), device="cpu", max_new_tokens=2)
    )
    image = png_data_url(np.zeros((48, 64, 3), np.uint8))
    messages = build_messages("fly", EncodedObservation(image, image, 2.0, 2.0), [])
    threads = []

    def episode() -> None:  # as a sweep flies it: on a thread of its own
        backend.complete(messages)
        threads.append(torch.get_num_threads())

    before = torch.get_num_threads()
    flying = threading.Thread(target=episode)
    flying.start()
    flying.join()
    assert threads == [1]  # a parallel region costs a small model more than it saves
    assert torch.get_num_threads() == before  # the asking thread's setting only


@pytest.mark.slow
def test_its_garbage_ends_the_episode_as_pilot_failure(tiny_model: Path, tmp_path: Path) -> None:
    backend = TransformersBackend(
        TransformersConfig(str(tiny_model), device="cpu", max_new_tokens=16)
    )
    run_dir = tmp_path / "run"
    result = run_episode(
        load_scenario("S4"), VLMPilot(backend), EpisodeConfig(plots=False), run_dir
    )
    assert result.termination == "pilot_failure"
    assert "no usable reply after 4 attempts" in result.summary["failure"]
    exchanges = [
        json.loads(line) for line in (run_dir / "exchanges.jsonl").read_text().splitlines()
    ]
    assert len(exchanges) == 4 and all(e["rejected"] for e in exchanges)
    assert all(e["completion_tokens"] == 16 for e in exchanges)
    assert json.loads((run_dir / "summary.json").read_text())["usage"]["requeries"] == 3


def test_a_missing_model_folder_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot load the model"):
        TransformersBackend(TransformersConfig(str(tmp_path / "nothing-here"), device="cpu"))

"""The VLM path end to end, against a real HTTP server on 127.0.0.1 (tests/vlm_server.py)."""

from __future__ import annotations

import base64
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import BackendAuthError, ConfigError
from cavenav.core.types import Usage
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.actions import parse_action, to_twist
from cavenav.pilots import request_images
from cavenav.pilots.backends import CachedBackend, OpenAIBackend, OpenAIConfig
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.pilots.prompt import PromptConfig
from cavenav.pilots.replay import ReplayPilot, recorded_noise_seed
from cavenav.pilots.request_images import ImageEncoding
from cavenav.pilots.vlm import VLMPilot
from cavenav.world.scenarios import load_scenario
from tests.cli.test_cli import printed_summary
from tests.conftest import synthetic_observation, wide
from tests.vlm_server import FakeVLM

QUICK = dict(timeout_s=0.8, max_retries=3, backoff_s=0.01, backoff_cap_s=0.2)


@pytest.fixture
def server():
    with FakeVLM() as fake:
        yield fake


def pilot_for(server: FakeVLM, **overrides) -> VLMPilot:
    config = OpenAIConfig(model="fake-vlm", base_url=server.base_url, **{**QUICK, **overrides})
    return VLMPilot(OpenAIBackend(config), price_per_mtok=(0.5, 1.5))


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.slow
@pytest.mark.parametrize("cave", ["S4", "S1"])
def test_a_vlm_episode_reaches_the_exit(server: FakeVLM, cave: str, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    config = EpisodeConfig(save_frames=False, plots=False)
    result = run_episode(load_scenario(cave), pilot_for(server), config, run_dir)
    assert result.termination == "exit" and result.summary["collisions"] == 0
    usage = result.summary["usage"]
    assert usage["model_steps"] == result.summary["steps"]
    steps = read_jsonl(run_dir / "steps.jsonl")
    assert all(s["vlm"]["requeries"] == 0 for s in steps)
    exchanges = read_jsonl(run_dir / "exchanges.jsonl")
    assert len(exchanges) == len(steps)
    assert "step by step" in exchanges[0]["reply"]  # the reasoning is kept
    # The fake server bills a token per 4 characters of its reply: each whole reply is kept
    # with the count the server reported, and the totals and the cost add them up.
    assert all(e["completion_tokens"] == len(e["reply"]) // 4 for e in exchanges)
    prompt = sum(e["prompt_tokens"] for e in exchanges)
    completion = sum(e["completion_tokens"] for e in exchanges)
    assert usage["prompt_tokens"] == prompt > 0 and usage["completion_tokens"] == completion
    cost = (0.5 * prompt + 1.5 * completion) / 1e6  # at the $0.5 and $1.5 per million given
    assert usage["cost_usd"] == pytest.approx(cost, abs=1e-6)  # kept to a millionth of a $


def test_requests_put_the_system_prompt_first_and_carry_history(server: FakeVLM) -> None:
    result = run_episode(
        load_scenario("S4"),
        pilot_for(server),
        EpisodeConfig(max_steps=4, save_frames=False, plots=False),
    )
    first, fourth = server.requests[0], server.requests[3]
    assert first["messages"][0]["role"] == "system"
    assert first["messages"][0]["content"] == fourth["messages"][0]["content"]  # cacheable prefix

    def images(request: dict) -> list[str]:
        return [
            p["image_url"]["url"]
            for p in request["messages"][1]["content"]
            if p["type"] == "image_url"
        ]

    assert len(images(first)) == 2 and len(images(fourth)) == 6  # K = 2 earlier observations
    assert all(url.startswith("data:image/png;base64,") for url in images(fourth))
    texts = [p["text"] for p in fourth["messages"][1]["content"] if p["type"] == "text"]
    taken = [t.removeprefix("Action taken after it: ") for t in texts if t.startswith("Action ")]
    assert taken == [result.steps[1]["action"], result.steps[2]["action"]]  # oldest first


def test_faults_are_requeried_or_retried_and_recorded(server: FakeVLM, tmp_path: Path) -> None:
    server.faults.extend(["garbage", "429", "two_keys", "500", "out_of_set", "slow"])
    server.slow_s = 1.2
    run_dir = tmp_path / "run"
    config = EpisodeConfig(max_steps=3, save_frames=False, plots=False)
    result = run_episode(load_scenario("S4"), pilot_for(server), config, run_dir)
    assert result.termination == "budget"  # every fault was recovered from
    exchanges = read_jsonl(run_dir / "exchanges.jsonl")
    rejected = [e["rejected"] for e in exchanges if e["rejected"]]
    assert any("no final dictionary" in r for r in rejected)
    assert any("2 key-value pairs" in r for r in rejected)
    assert any("not admissible" in r for r in rejected)
    errors = [err for e in exchanges for err in e["transport_errors"]]
    assert any("HTTP 429" in err for err in errors)
    assert any("HTTP 500" in err for err in errors)
    assert any("timeout" in err for err in errors)
    assert result.summary["usage"]["requeries"] == 3
    assert result.summary["usage"]["transport_retries"] == 3  # the 429, the 500, the timeout
    # The model is told what was wrong when re-queried.
    repair = [
        r
        for r in server.requests
        if r["messages"][-1]["role"] == "user" and isinstance(r["messages"][-1]["content"], str)
    ]
    assert any("could not be used" in r["messages"][-1]["content"] for r in repair)


@pytest.mark.parametrize("fault", ["garbage", "out_of_set", "500", "429"])
def test_persistent_faults_end_cleanly_as_pilot_failure(
    server: FakeVLM, fault: str, tmp_path: Path
) -> None:
    server.persistent_fault = fault
    run_dir = tmp_path / "run"
    result = run_episode(
        load_scenario("S4"), pilot_for(server, max_retries=1), EpisodeConfig(plots=False), run_dir
    )
    assert result.termination == "pilot_failure"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["termination"] == "pilot_failure"
    assert summary["steps"] == 1 and summary["failure"]
    assert len(read_jsonl(run_dir / "steps.jsonl")) == 1
    if fault in ("garbage", "out_of_set"):
        assert len(read_jsonl(run_dir / "exchanges.jsonl")) == 4  # 1 + 3 re-queries


def test_a_refused_key_is_a_one_line_error_at_start() -> None:
    with FakeVLM(required_key="right") as server:
        os.environ["CAVENAV_TEST_KEY"] = "wrong"
        try:
            with pytest.raises(BackendAuthError, match="refused the API key"):
                pilot_for(server, api_key_env="CAVENAV_TEST_KEY")
            os.environ["CAVENAV_TEST_KEY"] = "right"
            pilot_for(server, api_key_env="CAVENAV_TEST_KEY")
        finally:
            del os.environ["CAVENAV_TEST_KEY"]


def test_the_key_never_reaches_the_run_folder(tmp_path: Path) -> None:
    with FakeVLM(required_key="sk-secret-123") as server:
        os.environ["CAVENAV_TEST_KEY"] = "sk-secret-123"
        try:
            pilot = pilot_for(server, api_key_env="CAVENAV_TEST_KEY")
            run_episode(
                load_scenario("S4"), pilot, EpisodeConfig(max_steps=2, plots=False), tmp_path / "r"
            )
        finally:
            del os.environ["CAVENAV_TEST_KEY"]
    for path in (tmp_path / "r").rglob("*"):
        if path.is_file():
            assert b"sk-secret-123" not in path.read_bytes(), path


@pytest.mark.slow
def test_replay_reproduces_a_recorded_episode(server: FakeVLM, tmp_path: Path) -> None:
    config = EpisodeConfig(save_frames=False, plots=False)
    original = run_episode(load_scenario("S4"), pilot_for(server), config, tmp_path / "a")
    n_requests = len(server.requests)
    replay = run_episode(load_scenario("S4"), ReplayPilot(tmp_path / "a"), config, tmp_path / "b")
    assert len(server.requests) == n_requests  # no model involved
    assert replay.poses == original.poses
    assert replay.summary["termination"] == original.summary["termination"]


def test_the_reply_cache_makes_a_rerun_free(server: FakeVLM, tmp_path: Path) -> None:
    config = EpisodeConfig(max_steps=5, save_frames=False, plots=False)
    backend = OpenAIBackend(OpenAIConfig(model="fake-vlm", base_url=server.base_url, **QUICK))
    first = run_episode(
        load_scenario("S4"), VLMPilot(CachedBackend(backend, tmp_path / "cache")), config
    )
    n_requests = len(server.requests)
    again = run_episode(
        load_scenario("S4"), VLMPilot(CachedBackend(backend, tmp_path / "cache")), config
    )
    assert len(server.requests) == n_requests
    assert again.poses == first.poses
    assert all(s["vlm"]["cached"] for s in again.steps)


def test_each_image_is_encoded_once_however_often_it_is_sent_or_recorded(
    server: FakeVLM, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    encoded, encode = [], request_images._encode

    def counted(image: np.ndarray, how: ImageEncoding) -> str:
        encoded.append(image.ndim)
        return encode(image, how)

    monkeypatch.setattr(request_images, "_encode", counted)
    config = EpisodeConfig(max_steps=4, save_frames=False, plots=False)
    run_episode(load_scenario("S4"), pilot_for(server), config, tmp_path / "run")
    # Four steps of colour and depth, each sent again twice as history and named in
    # steps.jsonl, encoded once each.
    assert encoded == [3, 2] * 4
    steps = read_jsonl(tmp_path / "run" / "steps.jsonl")
    assert all(set(s["model_images"]) == {"rgb", "depth_png"} for s in steps)


def test_the_default_images_are_the_pngs_reply_caches_know_and_jpeg_and_a_size_are_settings(
    server: FakeVLM, tmp_path: Path
) -> None:
    image = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    png = io.BytesIO()
    Image.fromarray(image).save(png, format="PNG", compress_level=1)  # what caches were keyed by
    assert request_images.data_url(image) == (
        "data:image/png;base64," + base64.b64encode(png.getvalue()).decode("ascii")
    )

    config = OpenAIConfig(model="fake-vlm", base_url=server.base_url, **QUICK)
    smaller = ImageEncoding("jpeg", 80, (320, 240))
    pilot = VLMPilot(OpenAIBackend(config), images=smaller)
    episode = EpisodeConfig(max_steps=2, save_frames=False, plots=False)
    run_episode(load_scenario("S4"), pilot, episode, tmp_path / "run")
    urls = [p["image_url"]["url"] for p in server.requests[1]["messages"][1]["content"]
            if p["type"] == "image_url"]  # fmt: skip
    assert [u.split(";")[0] for u in urls] == ["data:image/jpeg", "data:image/png"] * 2
    for url in urls:
        with Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))) as sent:
            assert sent.size == (320, 240)
    recorded = read_jsonl(tmp_path / "run" / "steps.jsonl")[1]["model_images"]
    assert recorded["rgb"].endswith(".jpg") and recorded["depth_png"].endswith(".png")
    with pytest.raises(ConfigError, match="--jpeg-quality must lie in 1-100"):
        ImageEncoding("jpeg", 0)
    with pytest.raises(ConfigError, match="--image-size: 'big' is not a resolution"):
        PilotSpec("vlm", VLMOptions(model="m", image_size="big"))


def test_structured_mode_sends_a_fixed_key_schema(server: FakeVLM) -> None:
    config = OpenAIConfig(model="fake-vlm", base_url=server.base_url, **QUICK)
    pilot = VLMPilot(OpenAIBackend(config), PromptConfig(structured=True))
    run_episode(
        load_scenario("S4"), pilot, EpisodeConfig(max_steps=1, save_frames=False, plots=False)
    )
    schema = server.requests[0]["response_format"]["json_schema"]["schema"]
    assert schema["required"] == ["situation", "constraints", "action", "justification"]


def test_map_image_sends_the_pilots_own_map_and_explains_it(server: FakeVLM) -> None:
    config = OpenAIConfig(model="fake-vlm", base_url=server.base_url, **QUICK)
    pilot = VLMPilot(OpenAIBackend(config), PromptConfig(map_image=True, history=0))
    run_episode(
        load_scenario("S4"), pilot, EpisodeConfig(max_steps=3, save_frames=False, plots=False)
    )
    assert "# Your map" in server.requests[0]["messages"][0]["content"]
    content = server.requests[2]["messages"][1]["content"]
    images = [p for p in content if p["type"] == "image_url"]
    texts = [p["text"] for p in content if p["type"] == "text"]
    assert len(images) == 3  # colour, depth, then the map
    assert any(t.startswith("Your map (heading up). Flown ") for t in texts)
    # Without the flag, neither the picture nor the paragraph.
    run_episode(
        load_scenario("S4"),
        VLMPilot(OpenAIBackend(config), PromptConfig(history=0)),
        EpisodeConfig(max_steps=1, save_frames=False, plots=False),
    )
    plain = server.requests[-1]
    assert "# Your map" not in plain["messages"][0]["content"]
    assert sum(p["type"] == "image_url" for p in plain["messages"][1]["content"]) == 2


def test_energy_aware_prompting_tells_the_model_what_its_battery_has_left(
    server: FakeVLM,
) -> None:
    config = OpenAIConfig(model="fake-vlm", base_url=server.base_url, **QUICK)
    pilot = VLMPilot(OpenAIBackend(config), PromptConfig(energy=True, history=0))
    flown = EpisodeConfig(max_steps=3, save_frames=False, plots=False, battery_wh=2.0)
    result = run_episode(load_scenario("S4"), pilot, flown)
    assert "# Your battery" in server.requests[0]["messages"][0]["content"]
    told = [
        [text for part in request["messages"][1]["content"]
         if (text := part.get("text", "")).startswith("Battery: ")]
        for request in server.requests[-3:]
    ]  # fmt: skip
    assert told[0] == ["Battery: 2.00 Wh left."]
    spent = result.steps[0]["energy_wh"] + result.steps[1]["energy_wh"]
    assert told[2] == [f"Battery: {2.0 - spent:.2f} Wh left."]


@pytest.mark.parametrize(
    ("summary", "noise_seed"),
    [
        ({"noise_seed": 4, "config": {"seed": 4}}, 4),
        ({"config": {"seed": 2}}, 2),  # recorded before the summary named the noise's seed
        ({}, 0),  # recorded before the configuration was: the noise was always seed 0
    ],
)
def test_a_replay_draws_the_noise_its_recording_drew(
    tmp_path: Path, summary: dict, noise_seed: int
) -> None:
    (tmp_path / "summary.json").write_text(json.dumps({"scenario": "S1", "seed": 3, **summary}))
    assert recorded_noise_seed(tmp_path) == noise_seed
    (tmp_path / "summary.json").write_text(json.dumps({"noise_seed": "4"}))
    with pytest.raises(ConfigError, match="field 'noise_seed' is not a whole number"):
        recorded_noise_seed(tmp_path)


@pytest.mark.slow
def test_cli_runs_the_vlm_pilot_and_replays_it(server: FakeVLM, tmp_path: Path) -> None:
    base = [
        sys.executable,
        "-m",
        "cavenav.cli",
        "run",
        "S4",
        "--steps",
        "3",
        "--no-frames",
        "--out",
        str(tmp_path),
    ]
    done = subprocess.run(
        [
            *base,
            "--pilot",
            "vlm",
            "--base-url",
            server.base_url,
            "--model",
            "fake-vlm",
            "--price",
            "0.5,1.5",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=wide(),
    )
    assert done.returncode == 0, done.stderr
    (run_dir,) = tmp_path.iterdir()
    usage = json.loads((run_dir / "summary.json").read_text())["usage"]
    shown = printed_summary(done.stdout)
    assert shown["prompt tokens"] == str(usage["prompt_tokens"])
    assert shown["completion tokens"] == str(usage["completion_tokens"])
    assert shown["cost"] == f"${usage['cost_usd']:.4f}"
    n_requests = len(server.requests)
    done = subprocess.run(
        [*base, "--pilot", "replay", "--from", str(run_dir)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert len(server.requests) == n_requests  # the replay asks no model
    (replay_dir,) = [folder for folder in tmp_path.iterdir() if folder != run_dir]

    def flight(folder: Path) -> list[tuple[str, dict]]:
        return [(step["action"], step["pose"]) for step in read_jsonl(folder / "steps.jsonl")]

    assert flight(replay_dir) == flight(run_dir)


def test_ask_answers_one_photograph(server: FakeVLM, tmp_path: Path) -> None:
    photo = tmp_path / "frame.png"
    Image.fromarray(np.full((480, 640, 3), 40, np.uint8)).save(photo)
    depth = tmp_path / "depth.png"
    Image.fromarray(np.full((480, 640), 200, np.uint8)).save(depth)
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "cavenav.cli",
            "ask",
            str(photo),
            "--depth",
            str(depth),
            "--top",
            "3.0",
            "--bottom",
            "1.0",
            "--base-url",
            server.base_url,
            "--model",
            "fake-vlm",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env=wide(),
    )
    assert done.returncode == 0, done.stderr
    assert "step by step" in done.stdout  # the reasoning is shown
    (action_line,) = [x for x in done.stdout.splitlines() if x.startswith("action:")]
    action = parse_action(action_line.removeprefix("action:"))
    assert action.up == pytest.approx(1.0)  # 3 m above, 1 m below: rise 1 m to the middle
    (twist_line,) = [x for x in done.stdout.splitlines() if x.startswith("twist:")]
    assert twist_line.split(None, 1)[1] == str(to_twist(action))


def test_model_time_is_the_servers_not_the_time_a_request_waited_here(
    server: FakeVLM, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With many episodes in flight a request waits in this process (building it, a free
    core) before the server sees it: the model's time leaves that out, the latency not."""
    import openai._base_client as base

    build = base.SyncAPIClient._build_request

    def crowded(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        time.sleep(0.4)  # as a request waits behind others here
        return build(self, *args, **kwargs)

    monkeypatch.setattr(base.SyncAPIClient, "_build_request", crowded)
    server.persistent_fault, server.slow_s = "slow", 0.3  # the server takes 0.3 s
    decision = pilot_for(server, timeout_s=5.0).decide(synthetic_observation(8.0))
    assert decision.usage is not None and decision.usage.latency_s >= 0.7
    assert 0.3 <= decision.usage.model_s < 0.55
    assert decision.exchanges[0]["model_s"] == pytest.approx(decision.usage.model_s, abs=1e-4)


def test_a_steps_model_times_are_summed_and_an_episodes_given_as_percentiles() -> None:
    steps = [Usage(model_s=t) for t in (0.1, 0.2, 0.3, 0.4)] + [Usage(cached=True, model_s=None)]
    total = Usage.total(steps)
    assert total["model_p50_s"] == pytest.approx(0.25)
    assert total["model_p95_s"] == pytest.approx(0.385)
    assert Usage.total([Usage(cached=True)])["model_p50_s"] is None


def test_a_sonar_and_a_stereo_camera_are_sent_and_explained(server: FakeVLM) -> None:
    config = EpisodeConfig(
        max_steps=2, save_frames=False, plots=False, sonar="ping360", depth_source="stereo"
    )
    run_episode(load_scenario("S4"), pilot_for(server), config)
    first, second = server.requests[0], server.requests[1]
    system = first["messages"][0]["content"]
    assert "# Your sonar" in system and "scanning imaging sonar (a Ping360)" in system
    assert "20 m away" in system and "12.5 degrees above or below" in system
    assert "# Your depth camera" in system and "Treat black as unknown" in system
    parts = second["messages"][1]["content"]
    images = [p for p in parts if p["type"] == "image_url"]
    assert len(images) == 5  # the earlier colour and depth, then colour, depth and sonar
    assert any("Colour, then depth, then sonar:" in p.get("text", "") for p in parts)


def test_without_the_instruments_the_prompt_is_the_papers(server: FakeVLM) -> None:
    run_episode(
        load_scenario("S4"),
        pilot_for(server),
        EpisodeConfig(max_steps=1, plots=False, save_frames=False),
    )
    system = server.requests[0]["messages"][0]["content"]
    assert "# Your sonar" not in system and "# Your depth camera" not in system

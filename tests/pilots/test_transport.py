"""The OpenAI backend against bad input and faults: deadlines, retries as the SDK makes
them, bodies that are no reply, a server that is no OpenAI server at start, a key refused
mid-run, and what the run folder keeps.

Transport faults are played by a real HTTP server on 127.0.0.1 (tests/vlm_server.py);
the retry policy by `httpx2.MockTransport` handlers with the sleep recorded, not slept.
"""

from __future__ import annotations

import email.utils
import json
import time
from collections.abc import Callable
from pathlib import Path

import httpx2
import numpy as np
import pytest

from cavenav.core.errors import (
    BackendError,
    BackendTimeout,
    BackendUnavailable,
    PilotFailure,
    RateLimited,
)
from cavenav.core.types import Observation
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.backends import REPLY_CHARS, OpenAIBackend, OpenAIConfig
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.pilots.vlm import VLMPilot
from cavenav.world.scenarios import load_scenario
from tests.conftest import cavenav
from tests.vlm_server import PROXY_PAGE, FakeVLM

MESSAGES = [{"role": "user", "content": "Which way?"}]
FAST = dict(backoff_s=0.01, backoff_cap_s=0.05)  # retries against the real server


@pytest.fixture
def server():
    with FakeVLM() as fake:
        yield fake


def real_backend(server: FakeVLM, **config) -> OpenAIBackend:
    return OpenAIBackend(OpenAIConfig(model="fake-vlm", base_url=server.base_url, **config))


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


# --------------------------------------------------------------------------- deadlines


@pytest.mark.slow
def test_a_reply_dripped_byte_by_byte_is_cut_off_at_the_attempt_timeout(
    server: FakeVLM,
) -> None:
    server.persistent_fault = "drip"  # a byte every 2 s: no single read ever times out
    backend = real_backend(server, timeout_s=3.0, max_retries=0)
    start = time.monotonic()
    with pytest.raises(BackendTimeout, match="gave up after 1 attempt ") as caught:
        backend.complete(MESSAGES)
    elapsed = time.monotonic() - start
    assert 3.0 <= elapsed < 3.0 + 2.5  # the timeout, plus at most one byte's wait
    assert caught.value.errors == ("timeout after 3 s",)


@pytest.mark.slow
def test_the_deadline_bounds_the_whole_call_retries_included(server: FakeVLM) -> None:
    server.persistent_fault = "drip"
    backend = real_backend(server, timeout_s=3.0, max_retries=2, deadline_s=5.0, **FAST)
    start = time.monotonic()
    with pytest.raises(BackendTimeout, match="deadline of 5 s reached after 2 attempts"):
        backend.complete(MESSAGES)
    assert time.monotonic() - start < 7.0
    assert len(server.requests) == 2  # the third attempt had no time left


def test_the_deadline_option_reaches_the_backend() -> None:
    options = VLMOptions(model="m", base_url="http://model.test/v1", timeout=2.0, deadline=7.0)
    pilot = PilotSpec("vlm", options).build(check=False)
    config = pilot.backend.config  # type: ignore[attr-defined]
    assert (config.timeout_s, config.deadline_s, config.budget_s) == (2.0, 7.0, 7.0)


class FakeTime:
    """A clock that moves only when the backend sleeps."""

    def __init__(self) -> None:
        self.now = 100.0
        self.slept: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


def chat_reply(text: str = '{"forward 1 m": "open water"}') -> httpx2.Response:
    return httpx2.Response(
        200,
        json={
            "id": "chatcmpl-1",
            "object": "chat.completion",
            "created": 0,
            "model": "mock",
            "choices": [
                {
                    "index": 0,
                    "finish_reason": "stop",
                    "message": {"role": "assistant", "content": text},
                }
            ],
            "usage": {"prompt_tokens": 7, "completion_tokens": 5, "total_tokens": 12},
        },
    )


def http_error(status: int, **headers: str) -> httpx2.Response:
    headers = {k.replace("_", "-"): v for k, v in headers.items()}
    return httpx2.Response(status, headers=headers, json={"error": {"message": f"no ({status})"}})


class Script:
    """Answers each request with the next response (the last one repeats); keeps requests.

    Each answer is a fresh copy of its response: a response body can be read only once.
    """

    def __init__(self, *responses: httpx2.Response):
        self.responses = list(responses)
        self.requests: list[httpx2.Request] = []

    def __call__(self, request: httpx2.Request) -> httpx2.Response:
        self.requests.append(request)
        model = self.responses.pop(0) if len(self.responses) > 1 else self.responses[0]
        return httpx2.Response(model.status_code, headers=model.headers, content=model.read())


def mock_backend(
    script: Script, sleep: Callable[[float], None], clock: Callable[[], float] = time.monotonic,
    **config,
) -> OpenAIBackend:  # fmt: skip
    return OpenAIBackend(
        OpenAIConfig(model="mock", base_url="http://model.test/v1", **config),
        transport=httpx2.MockTransport(script),
        sleep=sleep,
        clock=clock,
    )


def test_every_phase_of_an_attempt_waits_at_most_the_time_left() -> None:
    fake = FakeTime()
    script = Script(http_error(500, retry_after="3"), chat_reply())
    backend = mock_backend(script, fake.sleep, fake.clock, timeout_s=3.0, deadline_s=5.0)
    backend.complete(MESSAGES)
    first, second = (r.extensions["timeout"] for r in script.requests)
    assert first == {"connect": 3.0, "read": 3.0, "write": 3.0, "pool": 3.0}
    assert second == {"connect": 2.0, "read": 2.0, "write": 2.0, "pool": 2.0}  # 5 - 3 slept


def test_a_wait_that_would_pass_the_deadline_is_not_taken() -> None:
    sleeps: list[float] = []
    script = Script(http_error(429, retry_after="10"))
    backend = mock_backend(script, sleeps.append, timeout_s=3.0, deadline_s=5.0)
    with pytest.raises(BackendTimeout, match="deadline of 5 s reached after 1 attempt "):
        backend.complete(MESSAGES)
    assert sleeps == [] and len(script.requests) == 1


def test_without_a_deadline_the_call_may_take_every_attempts_timeout() -> None:
    fake = FakeTime()
    script = Script(http_error(500), http_error(500), chat_reply())
    backend = mock_backend(
        script, fake.sleep, fake.clock, timeout_s=2.0, max_retries=2, backoff_s=2.0
    )
    backend.complete(MESSAGES)
    # 3 x 2 s in all: the waits (1.5-2 s, then 3-4 s) leave the third attempt under 2 s.
    left = 6.0 - sum(fake.slept)
    assert 0 < left < 2.0
    assert script.requests[2].extensions["timeout"]["read"] == pytest.approx(left)


# --------------------------------------------------------------------------- retries


def test_retry_after_in_seconds_is_waited_exactly() -> None:
    sleeps: list[float] = []
    script = Script(http_error(429, retry_after="3"), chat_reply())
    completion = mock_backend(script, sleeps.append).complete(MESSAGES)
    assert sleeps == [3.0]
    assert completion.retries == 1 and completion.errors[0].startswith("HTTP 429")
    assert completion.text == '{"forward 1 m": "open water"}'


def test_retry_after_as_an_http_date_is_waited_until_then() -> None:
    sleeps: list[float] = []
    when = email.utils.formatdate(time.time() + 5, usegmt=True)  # whole seconds
    script = Script(http_error(503, retry_after=when), chat_reply())
    mock_backend(script, sleeps.append).complete(MESSAGES)
    assert len(sleeps) == 1 and 3.9 < sleeps[0] <= 5.0


def test_retry_after_ms_is_preferred_to_retry_after() -> None:
    sleeps: list[float] = []
    script = Script(http_error(429, retry_after_ms="250", retry_after="3"), chat_reply())
    mock_backend(script, sleeps.append).complete(MESSAGES)
    assert sleeps == [0.25]


@pytest.mark.parametrize("asked", ["-5", "0", "soon", "nan"])
def test_an_unusable_retry_after_falls_back_to_backoff(asked: str) -> None:
    sleeps: list[float] = []
    script = Script(http_error(429, retry_after=asked), chat_reply())
    mock_backend(script, sleeps.append, backoff_s=2.0).complete(MESSAGES)
    assert len(sleeps) == 1 and 1.5 <= sleeps[0] <= 2.0


def test_a_server_asking_for_minutes_is_not_retried() -> None:
    sleeps: list[float] = []
    script = Script(http_error(429, retry_after="600"), chat_reply())
    with pytest.raises(RateLimited, match="HTTP 429"):
        mock_backend(script, sleeps.append).complete(MESSAGES)
    assert sleeps == [] and len(script.requests) == 1


def test_x_should_retry_false_forbids_retrying_a_503() -> None:
    sleeps: list[float] = []
    script = Script(http_error(503, x_should_retry="false"), chat_reply())
    with pytest.raises(BackendUnavailable, match="HTTP 503"):
        mock_backend(script, sleeps.append).complete(MESSAGES)
    assert sleeps == [] and len(script.requests) == 1


def test_x_should_retry_true_retries_even_a_400() -> None:
    sleeps: list[float] = []
    script = Script(http_error(400, x_should_retry="true"), chat_reply())
    completion = mock_backend(script, sleeps.append).complete(MESSAGES)
    assert len(script.requests) == 2 and completion.retries == 1


def test_a_400_is_not_retried() -> None:
    script = Script(http_error(400), chat_reply())
    with pytest.raises(BackendError, match="HTTP 400") as caught:
        mock_backend(script, lambda s: None).complete(MESSAGES)
    assert type(caught.value) is BackendError and len(script.requests) == 1
    assert len(caught.value.errors) == 1 and "no (400)" in caught.value.reply


def test_backoff_doubles_up_to_the_cap_less_a_random_quarter() -> None:
    firsts = set()
    for _ in range(20):
        sleeps: list[float] = []
        script = Script(http_error(500), chat_reply())
        script.responses[1:1] = [http_error(500) for _ in range(4)]
        backend = mock_backend(script, sleeps.append, max_retries=5, backoff_s=1.0,
                               backoff_cap_s=5.0)  # fmt: skip
        completion = backend.complete(MESSAGES)
        assert completion.retries == 5 and len(completion.errors) == 5
        for slept, base in zip(sleeps, [1.0, 2.0, 4.0, 5.0, 5.0], strict=True):
            assert 0.75 * base <= slept <= base
        firsts.add(sleeps[0])
    assert len(firsts) > 1  # jittered, not a fixed sequence


# --------------------------------------------------------------------------- bad bodies


@pytest.mark.parametrize("content_type", ["text/html", "application/json"])
def test_a_page_instead_of_a_reply_is_retried_then_a_clean_error(content_type: str) -> None:
    sleeps: list[float] = []
    page = httpx2.Response(200, headers={"content-type": content_type}, text=PROXY_PAGE)
    script = Script(page)
    with pytest.raises(BackendUnavailable, match="gave up after 3 attempts") as caught:
        mock_backend(script, sleeps.append, max_retries=2).complete(MESSAGES)
    assert "<!DOCTYPE html><html><head><title>Service" in str(caught.value)  # quoted
    assert len(sleeps) == 2 and len(caught.value.errors) == 3
    assert caught.value.reply == PROXY_PAGE[:REPLY_CHARS]


def test_a_proxy_page_ends_the_episode_with_the_page_recorded(
    server: FakeVLM, tmp_path: Path
) -> None:
    server.persistent_fault = "html"
    pilot = VLMPilot(real_backend(server, max_retries=1, **FAST))
    run_dir = tmp_path / "run"
    run_episode(load_scenario("S4"), pilot, EpisodeConfig(plots=False), run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["termination"] == "pilot_failure"
    assert summary["failure_cause"] == "backend" and "<!DOCTYPE html>" in summary["failure"]
    (exchange,) = read_jsonl(run_dir / "exchanges.jsonl")
    assert exchange["reply"] == PROXY_PAGE[:REPLY_CHARS]
    assert "gave up after 2 attempts" in exchange["rejected"]
    assert exchange["transport_retries"] == 1 and len(exchange["transport_errors"]) == 2


# --------------------------------------------------------------------------- at start

NO_MODEL_LISTS = {
    "a proxy's page": ("text/html", PROXY_PAGE),
    "a JSON list": ("application/json", '[{"id": "fake-vlm"}]'),
    "an object without data": ("application/json", "{}"),
    "data that is no list": ("application/json", '{"data": "fake-vlm"}'),
    "an empty body": ("application/json", ""),
    "plain text": ("text/plain", "It works!"),
}


@pytest.mark.parametrize("answer", NO_MODEL_LISTS.values(), ids=NO_MODEL_LISTS.keys())
def test_a_server_whose_model_list_is_no_list_is_refused_at_start(
    server: FakeVLM, answer: tuple[str, str]
) -> None:
    server.models_answer = answer
    with pytest.raises(BackendUnavailable, match=r"is no OpenAI-compatible server") as caught:
        real_backend(server).check()
    message = str(caught.value)
    assert f"GET /models answered HTTP 200 ({answer[0]}) with " in message
    assert "check --base-url" in message and caught.value.exit_status == 2
    assert server.requests == []  # refused before the first chat request


def test_a_model_list_is_accepted_at_start(server: FakeVLM) -> None:
    server.models_answer = ("application/json", '{"object": "list", "data": []}')
    real_backend(server).check()


def test_the_command_line_refuses_a_page_at_start_in_one_line_with_no_run_folder(
    server: FakeVLM, tmp_path: Path
) -> None:
    server.models_answer = ("text/html", PROXY_PAGE)
    done = cavenav(
        "run", "S1", "--pilot", "vlm", "--base-url", server.base_url, "--model", "fake",
        "--out", str(tmp_path / "runs"),
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith(f"error: {server.base_url} is no OpenAI-compatible server")
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


# --------------------------------------------------------------------------- failures


def test_a_key_refused_mid_run_ends_the_episode_as_an_auth_failure(
    server: FakeVLM, tmp_path: Path
) -> None:
    server.faults.extend([None, "401"])  # the first step flies, then the key is revoked
    pilot = VLMPilot(real_backend(server, **FAST))
    run_dir = tmp_path / "run"
    run_episode(load_scenario("S4"), pilot, EpisodeConfig(plots=False), run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "finished" and summary["termination"] == "pilot_failure"
    assert summary["failure_cause"] == "auth" and summary["steps"] == 2
    assert "API key from $OPENAI_API_KEY was refused (HTTP 401)" in summary["failure"]
    failed = read_jsonl(run_dir / "exchanges.jsonl")[-1]
    assert failed["step"] == 1 and failed["messages"][0]["role"] == "system"
    assert failed["transport_errors"] == ["the API key from $OPENAI_API_KEY was refused (HTTP 401)"]
    assert failed["transport_retries"] == 0 and "invalid api key" in failed["reply"]
    assert len(server.requests) == 2  # a refused key is not retried


def test_a_backend_that_gives_up_leaves_its_request_in_the_run_folder(
    server: FakeVLM, tmp_path: Path
) -> None:
    server.persistent_fault = "500"
    pilot = VLMPilot(real_backend(server, max_retries=2, **FAST), price_per_mtok=(0.5, 1.5))
    run_dir = tmp_path / "run"
    run_episode(load_scenario("S4"), pilot, EpisodeConfig(plots=False), run_dir)
    (exchange,) = read_jsonl(run_dir / "exchanges.jsonl")
    assert "gave up after 3 attempts (HTTP 500" in exchange["rejected"]
    assert exchange["transport_retries"] == 2
    assert [e[:8] for e in exchange["transport_errors"]] == ["HTTP 500"] * 3
    assert "fault 500" in exchange["reply"] and exchange["messages"][0]["role"] == "system"
    (step,) = read_jsonl(run_dir / "steps.jsonl")
    assert step["vlm"]["transport_retries"] == 2  # counted like any other step's


def small_observation() -> Observation:
    depth = np.full((48, 64), 120, np.uint8)
    return Observation(
        np.full((48, 64, 3), 40, np.uint8), depth.astype(np.float32), depth, 2.0, 1.0,
        depth_range=(0.0, 20.0), hfov_deg=53.13,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("fault", "cause"), [("401", "auth"), ("500", "backend"), ("garbage", "reply")]
)
def test_a_pilot_failure_says_what_failed(server: FakeVLM, fault: str, cause: str) -> None:
    server.persistent_fault = fault
    pilot = VLMPilot(real_backend(server, max_retries=1, **FAST), max_requeries=1)
    with pytest.raises(PilotFailure) as caught:
        pilot.decide(small_observation())
    assert caught.value.cause == cause
    assert len(caught.value.exchanges) == (2 if fault == "garbage" else 1)  # 1 + 1 re-query

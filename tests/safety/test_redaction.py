"""API keys never leak: whatever a server echoes back (an error body, a proxy's page, a
model's reply), the key and any Authorization header value are redacted from the run
folder, the summary and everything a command prints (docs/guides/faults.md).

The servers are real (tests/vlm_server.py on 127.0.0.1), the commands run as a user runs
them, and the check is on bytes: every file of the run folder, stdout and stderr.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import BackendUnavailable
from cavenav.core.redaction import Redactor
from cavenav.pilots.backends import OpenAIBackend, OpenAIConfig
from tests.conftest import cavenav, wide
from tests.vlm_server import FakeVLM

KEY = "sk-test-4f9c2b7e1d8a4c6f9e3b5a7d1c2e8f40"


class SteadyVLM(FakeVLM):
    """The fake server answering one admissible action to whatever it is asked (its usual
    answer reads a depth image, which a plain question lacks)."""

    def answer(self, body: dict) -> str:
        return 'Open water ahead.\n{"forward 1 m": "open water"}'


def command(*args: str) -> subprocess.CompletedProcess[str]:
    """The command line in a fresh process, with ``KEY`` as the user's API key."""
    return cavenav(*args, env={**wide(), "OPENAI_API_KEY": KEY})


def files_holding(folder: Path, secret: str) -> list[str]:
    """Every file under ``folder`` whose bytes contain ``secret``."""
    return [
        str(path.relative_to(folder))
        for path in sorted(folder.rglob("*"))
        if path.is_file() and secret.encode() in path.read_bytes()
    ]


# --------------------------------------------------------------------------- the redactor


def test_the_key_and_authorization_values_are_redacted_wherever_they_appear() -> None:
    redact = Redactor((KEY,))
    text = (
        f"Incorrect API key provided: {KEY}. headers: {{'Authorization': 'Bearer abc.def-123'}}"
        f" authorization: Basic dXNlcjpwYXNz; x-api-key={KEY}"
    )
    cleaned = redact(text)
    assert KEY not in cleaned and "abc.def-123" not in cleaned and "dXNlcjpwYXNz" not in cleaned
    assert cleaned.startswith("Incorrect API key provided: [redacted]. headers:")
    assert "Bearer [redacted]" in cleaned and "Basic [redacted]" in cleaned
    assert redact(cleaned) == cleaned  # the run folder redacts what backends redacted


@pytest.mark.parametrize(
    "text",
    [
        'I will go ahead.\n{"forward 1 m": "the bearer of good news: open water"}',
        "Basic strategy: keep right of the pillar.",
        "basic obstacle avoidance first, then the bearer of the passage: north",
        "passage authorization: granted by the open water ahead",
        "Authorization: none needed; basic 2024 plan",
    ],
)
def test_a_models_prose_is_kept_word_for_word(text: str) -> None:
    assert Redactor((KEY,))(text) == text


@pytest.mark.parametrize(
    ("text", "credential"),
    [
        ("send Bearer sk-proj-abc123def456 now", "sk-proj-abc123def456"),
        ("Basic dXNlcjpwYXNz", "dXNlcjpwYXNz"),  # user:pass
        ("authorization=tok3n12345", "tok3n12345"),
        ('{"authorization": "granted-by-no-one"}', "granted-by-no-one"),  # quoted: a header
    ],
)
def test_a_credential_of_another_service_is_redacted_by_its_form(
    text: str, credential: str
) -> None:
    cleaned = Redactor((KEY,))(text)
    assert credential not in cleaned and "[redacted]" in cleaned


def test_a_placeholder_key_of_a_local_server_is_not_treated_as_a_secret() -> None:
    # vLLM's "EMPTY" or Ollama's "ollama": redacting them would mangle every reply.
    redact = Redactor(("EMPTY", "ollama", ""))
    assert redact("EMPTY ollama replies") == "EMPTY ollama replies"


def test_records_are_redacted_through_and_through() -> None:
    redact = Redactor((KEY,))
    record = {"reply": KEY, "errors": [f"HTTP 500: {KEY}"], "n": 3, "nested": {"t": (KEY,)}}
    assert redact.scrub(record) == {
        "reply": "[redacted]",
        "errors": ["HTTP 500: [redacted]"],
        "n": 3,
        "nested": {"t": ("[redacted]",)},
    }


# --------------------------------------------------------------------------- the backend


@pytest.mark.parametrize("fault", ["echo_key_500", "echo_key_html"])
def test_an_error_from_a_server_echoing_the_key_carries_no_key(
    fault: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OPENAI_API_KEY", KEY)
    with FakeVLM() as server:
        server.persistent_fault = fault
        backend = OpenAIBackend(
            OpenAIConfig(model="fake-vlm", base_url=server.base_url, max_retries=1,
                         backoff_s=0.01, backoff_cap_s=0.02)
        )  # fmt: skip
        with pytest.raises(BackendUnavailable) as caught:
            backend.complete([{"role": "user", "content": "Which way?"}])
    error = caught.value
    for text in (str(error), *error.errors, error.reply):
        assert KEY not in text, text
    assert "[redacted]" in error.reply


def test_a_reply_echoing_the_key_is_handed_out_without_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OPENAI_API_KEY", KEY)
    with SteadyVLM() as server:
        server.faults.append("echo_key_reply")
        backend = OpenAIBackend(OpenAIConfig(model="fake-vlm", base_url=server.base_url))
        completion = backend.complete([{"role": "user", "content": "Which way?"}])
    assert KEY not in completion.text
    assert completion.text.startswith("My key is [redacted]; Bearer [redacted].")


# --------------------------------------------------------------------------- commands


@pytest.mark.slow
def test_a_run_against_a_server_echoing_the_key_keeps_it_out_of_every_file_and_output(
    tmp_path: Path,
) -> None:
    with FakeVLM(required_key=KEY) as server:
        # Step 0 flies on a reply that quotes the key; step 1 gets a page quoting the
        # Authorization header, then (retried) an error body quoting the key, and fails.
        server.faults.extend(["echo_key_reply", "echo_key_html", "echo_key_500"])
        done = command(
            "run", "S1", "--pilot", "vlm", "--base-url", server.base_url, "--model", "fake",
            "--retries", "1", "--no-frames", "--resolution", "64x48", "--out", str(tmp_path),
        )  # fmt: skip
    assert done.returncode == 1, done.stderr
    (run_dir,) = tmp_path.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["termination"] == "pilot_failure" and summary["failure_cause"] == "backend"
    assert summary["steps"] == 2  # the echoed reply was flown, then the server failed
    assert files_holding(run_dir, KEY) == []
    assert KEY not in done.stdout and KEY not in done.stderr
    assert "Incorrect API key provided: [redacted]" in summary["failure"]
    assert "Incorrect API key provided: [redacted]" in done.stdout  # shown, not taken as markup
    exchanges = (run_dir / "exchanges.jsonl").read_text()
    assert "My key is [redacted]; Bearer [redacted]." in exchanges
    assert "Authorization: Bearer [redacted]" in exchanges


@pytest.mark.parametrize("fault", ["echo_key_reply", "echo_key_500"])
def test_ask_against_a_server_echoing_the_key_prints_no_key(fault: str, tmp_path: Path) -> None:
    photo = tmp_path / "frame.png"
    Image.fromarray(np.full((48, 64, 3), 40, np.uint8)).save(photo)
    with SteadyVLM(required_key=KEY) as server:
        server.persistent_fault = fault
        done = command(
            "ask", str(photo), "--top", "1.5", "--bottom", "2",
            "--base-url", server.base_url, "--model", "fake", "--retries", "0",
        )  # fmt: skip
    assert KEY not in done.stdout and KEY not in done.stderr
    assert "Traceback" not in done.stderr
    if fault == "echo_key_reply":
        assert done.returncode == 0 and "My key is [redacted]" in done.stdout
    else:
        assert done.returncode == 1 and "[redacted]" in done.stderr

"""Model backends: one `complete(messages)` call over any OpenAI-compatible endpoint or a
local transformers model, with bounded retries, token accounting and an optional cache.

Messages use the OpenAI chat format with images as PNG data URLs, so one request
recorded in a run folder means the same thing to every backend. What a backend hands out
(replies, errors, the bodies they carry) never holds an API key, whatever the server
echoed: each public method is `redacting` (`cavenav.core.redaction`).
"""

from __future__ import annotations

import base64
import email.utils
import hashlib
import io
import json
import math
import os
import random
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import httpx2

from cavenav.core.errors import (
    BackendAuthError,
    BackendError,
    BackendTimeout,
    BackendUnavailable,
    ConfigError,
    DependencyError,
    RateLimited,
)
from cavenav.core.files import write_then_rename
from cavenav.core.redaction import redacting, register
from cavenav.pilots.endpoints import OpenAIConfig, TransformersConfig

if TYPE_CHECKING:
    import openai

__all__ = [
    "Backend",
    "CachedBackend",
    "Completion",
    "OpenAIBackend",
    "OpenAIConfig",  # declared in cavenav.pilots.endpoints; imported from here too
    "TransformersBackend",
    "TransformersConfig",
    "local_chat",
    "request_hash",
]

Message = dict[str, Any]


@dataclass(frozen=True)
class Completion:
    """One model answer with its accounting.

    Attributes:
        text: the raw reply, reasoning included.
        prompt_tokens, completion_tokens: as reported by the server (or counted locally).
        latency_s: wall time of the successful request, from the call to the parsed reply.
        model_s: the part of it the model server took: from the built request going on
            the wire (httpx's request hook) to its parsed reply, leaving out the time
            spent in this process before, building the request (encoding its images) or
            waiting for a core to do it, which grows with the episodes in flight; the
            generation time for a local model; None where not measured.
        retries: transport retries before it (timeouts, 408/409/429/5xx, refused, a
            body that was no reply).
        errors: one line per failed attempt, for the record.
        cached: served from the reply cache, no model call.
    """

    text: str
    prompt_tokens: int = 0
    completion_tokens: int = 0
    latency_s: float = 0.0
    retries: int = 0
    errors: tuple[str, ...] = ()
    cached: bool = False
    model: str = ""
    model_s: float | None = None


class Backend(Protocol):
    name: str
    model: str

    def check(self) -> None:
        """Fail fast (at start, not at step 40) on a bad key or an unreachable model."""

    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion: ...


def request_hash(model: str, messages: list[Message], params: dict[str, Any]) -> str:
    """A stable hash of everything that determines a reply (images included, by content)."""
    blob = json.dumps({"model": model, "messages": messages, "params": params}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


# --------------------------------------------------------------------------- OpenAI


# As the openai SDK (`_base_client.py`, `MAX_RETRY_AFTER_DELAY`): a server that asks for a
# longer wait than this means "not soon", and the request is not retried at all.
MAX_RETRY_AFTER_S = 120.0
# Of a body that is no reply (a proxy's error page), what the run folder keeps: enough
# to read the page's message, not a whole site.
REPLY_CHARS = 2000


def _retry_after(headers: Mapping[str, str], now: float) -> float | None:
    """The wait a server asked for, in seconds, as the SDK reads it: retry-after-ms, else
    retry-after as seconds or as an HTTP date (measured from ``now``, a `time.time()`).
    None when it named none, or nothing finite."""
    for name, scale in (("retry-after-ms", 1e-3), ("retry-after", 1.0)):
        try:
            value = float(headers[name]) * scale
        except (KeyError, ValueError):
            continue
        return value if math.isfinite(value) else None
    date = email.utils.parsedate_tz(headers.get("retry-after", ""))
    if date is None:
        return None
    try:
        return email.utils.mktime_tz(date) - now
    except (OverflowError, ValueError):
        return None


def _should_retry(status: int, headers: Mapping[str, str], asked: float | None) -> bool:
    """Whether an HTTP error is worth another attempt, as the SDK's `_should_retry`
    decides: never after a wait too long to honour, then as the server's x-should-retry
    says, else for 408, 409, 429 and 5xx."""
    if asked is not None and asked > MAX_RETRY_AFTER_S:
        return False
    flag = headers.get("x-should-retry")
    if flag in ("true", "false"):
        return flag == "true"
    return status in (408, 409, 429) or status >= 500


def _backoff(retry: int, asked: float | None, first_s: float, cap_s: float) -> float:
    """Seconds to wait before retry number ``retry`` (0 for the first).

    The server's retry-after when it is a usable wait (0 < asked <= MAX_RETRY_AFTER_S),
    else ``min(first_s * 2**retry, cap_s)`` less 0-25 % at random, so that clients
    refused together do not all come back together (the SDK's
    `_calculate_retry_timeout`, with our first wait and cap).
    """
    if asked is not None and 0 < asked <= MAX_RETRY_AFTER_S:
        return asked
    # 2**32 passes any cap; the bound keeps the power finite for absurd retry counts.
    return min(first_s * 2.0 ** min(retry, 32), cap_s) * (1 - 0.25 * random.random())


def _time_left(deadline: float, clock: Callable[[], float]) -> float:
    """Seconds until ``deadline``; past it, the `httpx2.ReadTimeout` the SDK reports as
    `openai.APITimeoutError`, so that a cut-off attempt is a timeout like any other."""
    left = deadline - clock()
    if left <= 0:
        raise httpx2.ReadTimeout("the attempt's deadline has passed")
    return left


class _DeadlineStream(httpx2.SyncByteStream):
    """A response body that ends at a deadline however steadily it trickles in: the read
    timeout bounds each wait for bytes, so one byte every few seconds never trips it."""

    def __init__(self, inner: httpx2.SyncByteStream, deadline: float, clock: Callable[[], float]):
        self._inner, self._deadline, self._clock = inner, deadline, clock

    def __iter__(self) -> Iterator[bytes]:
        for chunk in self._inner:
            _time_left(self._deadline, self._clock)
            yield chunk

    def close(self) -> None:
        self._inner.close()


@dataclass(frozen=True)
class _Failed:
    """One failed attempt: its line for the record, whether to try again, what to raise
    if not, the wait the server asked for and the body it sent (if any)."""

    error: type[BackendError]
    line: str
    retry: bool
    asked_s: float | None = None
    reply: str = ""


def _status_failure(exc: openai.APIStatusError, key_env: str) -> _Failed:
    """What an HTTP error means: a refused key is not retried (it will not change);
    the rest are retried as the SDK would."""
    status, headers, body = exc.status_code, exc.response.headers, exc.response.text
    if status in (401, 403):
        line = f"the API key from ${key_env} was refused (HTTP {status})"
        return _Failed(BackendAuthError, line, retry=False, reply=body)
    asked = _retry_after(headers, time.time())
    error: type[BackendError] = BackendError
    if status == 429:
        error = RateLimited
    elif status in (408, 409) or status >= 500:
        error = BackendUnavailable
    line = f"HTTP {status}: {_short(exc)}"
    return _Failed(error, line, _should_retry(status, headers, asked), asked, body)


class OpenAIBackend:
    """Chat completions through the official `openai` SDK.

    Retries are made here, not in the SDK, so that each is counted and recorded; the
    SDK's HTTP client is built here too, so that an attempt's deadline reaches every
    phase of the request (see `_cap_timeouts` and `_bound_body`). One gap is left: the
    status line and headers are read under one read timeout (the time left when the
    request starts) per socket read, so only a server trickling its *body* is cut off
    mid-way; headers trickled byte by byte would be bounded per read alone.
    """

    name = "openai"

    def __init__(
        self,
        config: OpenAIConfig,
        transport: httpx2.BaseTransport | None = None,
        sleep: Callable[[float], None] = time.sleep,
        clock: Callable[[], float] = time.monotonic,
    ):
        """
        Args:
            config: the endpoint and its limits.
            transport: how requests leave (default: the network, proxies from the
                environment included); tests pass an `httpx2.MockTransport`.
            sleep: the waits between retries (seconds), injectable so that tests need
                not wait.
            clock: the time deadlines are kept against (seconds, monotonic), injectable
                likewise.
        """
        import openai

        self.config = config
        self.model = config.model
        key = os.environ.get(config.api_key_env, "")
        if not key and config.base_url is None:
            raise BackendAuthError(
                f"no API key: set the environment variable {config.api_key_env} "
                "(or point --base-url at a local server)"
            )
        register(key)  # a server may echo it back: redacted from all we hand out
        if not all(" " <= char <= "~" for char in key):  # what an HTTP header may hold
            raise BackendAuthError(
                f"the API key in {config.api_key_env} is not a valid HTTP header value: it "
                "holds a line break, a control or a non-ASCII character (set it again)"
            )
        self._openai = openai
        self._sleep, self._clock = sleep, clock
        # The deadline of the attempt this thread is making: sweeps share one backend
        # between threads, and the HTTP hooks run in the thread that sends.
        self._attempt_deadline = threading.local()
        self._sent = threading.local()  # when this thread's request went on the wire
        hooks: dict[str, list[Callable[..., Any]]] = {
            "request": [self._cap_timeouts, self._mark_sent],
            "response": [self._bound_body],
        }
        # Local servers (vLLM, Ollama, llama.cpp) accept any key; the SDK needs one.
        self._client = openai.OpenAI(
            api_key=key or "EMPTY",
            base_url=config.base_url,
            timeout=config.timeout_s,
            max_retries=0,  # retried here, so that every retry is counted and recorded
            http_client=openai.DefaultHttpxClient(transport=transport, event_hooks=hooks),
        )

    @property
    def params(self) -> dict[str, Any]:
        return {"temperature": self.config.temperature, "max_tokens": self.config.max_tokens}

    @contextmanager
    def _until(self, deadline: float) -> Iterator[None]:
        """Bound every request this thread sends meanwhile by ``deadline`` (clock time)."""
        self._attempt_deadline.at = deadline
        try:
            yield
        finally:
            self._attempt_deadline.at = None

    def _cap_timeouts(self, request: httpx2.Request) -> None:
        """Request hook: no phase (connect, write, pool, each read) may wait past the
        attempt's deadline."""
        deadline = getattr(self._attempt_deadline, "at", None)
        if deadline is None:
            return
        left = _time_left(deadline, self._clock)
        request.extensions["timeout"] = {
            phase: left if limit is None else min(limit, left)
            for phase, limit in request.extensions["timeout"].items()
        }

    def _mark_sent(self, request: httpx2.Request) -> None:
        """Request hook: the request is built and about to be sent (`Completion.model_s`
        counts from here)."""
        self._sent.at = self._clock()

    def _bound_body(self, response: httpx2.Response) -> None:
        """Response hook: the body, read next, stops at the attempt's deadline."""
        deadline = getattr(self._attempt_deadline, "at", None)
        if deadline is not None:
            assert isinstance(response.stream, httpx2.SyncByteStream)  # a sync client
            response.stream = _DeadlineStream(response.stream, deadline, self._clock)

    @redacting
    def check(self) -> None:
        """Ask for the model list: a refused key, an unreachable server or one that is
        no OpenAI server (a page, an empty or foreign body) is refused before the first
        step. A server without /models, or failing now, is left to the first request."""
        openai = self._openai
        try:
            with self._until(self._clock() + self.config.budget_s):
                raw = self._client.with_options(max_retries=1).models.with_raw_response.list()
        except (openai.AuthenticationError, openai.PermissionDeniedError) as exc:
            raise BackendAuthError(
                f"{self._where()} refused the API key from ${self.config.api_key_env} "
                f"({exc.status_code})"
            ) from None
        except openai.NotFoundError:
            pass  # some servers have no /models; the first request will tell
        except openai.APIConnectionError as exc:
            raise BackendUnavailable(f"cannot reach {self._where()}: {exc}") from None
        except openai.APIStatusError:
            pass
        else:
            problem = _not_a_model_list(raw.http_response)
            if problem:
                raise BackendUnavailable(
                    f"{self._where()} is no OpenAI-compatible server, or not up: GET /models "
                    f"answered {problem}; check --base-url (a local server's ends in /v1)"
                )

    def _where(self) -> str:
        return self.config.base_url or "api.openai.com"

    @redacting
    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion:
        """One reply, retried within the call's deadline.

        Raises:
            BackendError: or a subclass saying why, carrying each attempt's error and
                the last body received, when no attempt gave a reply.
        """
        cfg = self.config
        extra: dict[str, Any] = {}
        if json_schema is not None:
            extra["response_format"] = {
                "type": "json_schema",
                "json_schema": {"name": "pilot_reply", "schema": json_schema, "strict": True},
            }
        deadline = self._clock() + cfg.budget_s
        errors: list[str] = []
        while True:
            outcome = self._attempt(messages, extra, min(self._clock() + cfg.timeout_s, deadline))
            if isinstance(outcome, Completion):
                return replace(outcome, retries=len(errors), errors=tuple(errors))
            errors.append(outcome.line)
            attempts = f"{len(errors)} attempt{'s' if len(errors) > 1 else ''}"
            wait = _backoff(len(errors) - 1, outcome.asked_s, cfg.backoff_s, cfg.backoff_cap_s)
            error = outcome.error
            if not outcome.retry:
                reason = outcome.line
            elif len(errors) > cfg.max_retries:
                reason = f"gave up after {attempts} ({outcome.line})"
            elif self._clock() + wait >= deadline:
                error = BackendTimeout
                reason = f"deadline of {cfg.budget_s:g} s reached after {attempts} ({outcome.line})"
            else:
                self._sleep(wait)
                continue
            raise error(
                f"{self._where()}: {reason}",
                errors=tuple(errors),
                reply=outcome.reply[:REPLY_CHARS],
            )

    def _attempt(
        self, messages: list[Message], extra: dict[str, Any], deadline: float
    ) -> Completion | _Failed:
        """One request that must end by ``deadline`` (clock time)."""
        openai, cfg = self._openai, self.config
        start = self._clock()
        try:
            with self._until(deadline):
                raw = self._client.chat.completions.with_raw_response.create(
                    model=cfg.model,
                    messages=messages,  # type: ignore[arg-type]  # plain dicts, OpenAI format
                    **self.params,
                    **extra,
                )
        except openai.APITimeoutError:
            return _Failed(BackendTimeout, f"timeout after {deadline - start:.3g} s", retry=True)
        except openai.APIConnectionError as exc:
            return _Failed(BackendUnavailable, f"connection failed: {exc}", retry=True)
        except openai.APIStatusError as exc:
            return _status_failure(exc, cfg.api_key_env)
        body = raw.http_response.text
        try:
            # A str for a body that is not JSON; a ValueError when it claims to be.
            parsed: Any = raw.parse()
        except ValueError:
            parsed = None
        if not isinstance(parsed, openai.types.chat.ChatCompletion) or parsed.choices is None:
            line = f"HTTP {raw.status_code} but no chat completion: {body[:100]!r}"
            return _Failed(BackendUnavailable, line, retry=True, reply=body)
        choice = parsed.choices[0] if parsed.choices else None
        usage = parsed.usage
        sent = getattr(self._sent, "at", None)
        return Completion(
            text=(choice.message.content or "") if choice else "",
            prompt_tokens=int(getattr(usage, "prompt_tokens", 0) or 0),
            completion_tokens=int(getattr(usage, "completion_tokens", 0) or 0),
            latency_s=self._clock() - start,
            model=parsed.model or cfg.model,
            model_s=None if sent is None or sent < start else self._clock() - sent,
        )


def _short(exc: Exception) -> str:
    return str(exc).splitlines()[0][:200]


def _not_a_model_list(response: httpx2.Response) -> str:
    """What is wrong with a successful answer to GET /models, in words ("" if nothing):
    an OpenAI-compatible server answers a JSON object whose "data" is a list."""
    try:
        listing: Any = response.json()
    except ValueError:  # not JSON: a page, plain text, nothing
        listing = None
    if isinstance(listing, dict) and isinstance(listing.get("data"), list):
        return ""
    kind = response.headers.get("content-type", "no content type").split(";")[0]
    body = response.text.strip()
    quoted = repr(body[:100]) if body else "an empty body"
    return f"HTTP {response.status_code} ({kind}) with {quoted}"


# --------------------------------------------------------------------------- cache


class CachedBackend:
    """Serves a reply from disk when exactly the same request was answered before.

    The key is the hash of model, parameters and messages (images by content), so a sweep
    can be re-run for free and a changed prompt or image misses the cache.
    """

    def __init__(self, inner: Any, directory: str | Path):
        self.inner = inner
        self.name = f"cached-{inner.name}"
        self.model = inner.model
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def check(self) -> None:
        self.inner.check()

    @redacting  # a reply cached before keys were redacted is served without its key
    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion:
        params = {**getattr(self.inner, "params", {}), "schema": json_schema}
        path = self.directory / f"{request_hash(self.model, messages, params)}.json"
        if path.is_file():
            stored = json.loads(path.read_text())
            stored["errors"] = tuple(stored.get("errors", ()))
            return Completion(
                **{**stored, "cached": True, "latency_s": 0.0, "retries": 0, "model_s": None}
            )
        completion = self.inner.complete(messages, json_schema)
        write_then_rename(path, lambda tmp: tmp.write_text(json.dumps(asdict(completion))))
        return completion


# --------------------------------------------------------------------------- transformers


def local_chat(
    messages: list[Message], image: Callable[[Mapping[str, Any]], Any] | None = None
) -> tuple[list[dict[str, Any]], list[Any]]:
    """OpenAI messages as a local model's processor takes them: (the chat, each content a
    list of text and image parts, for its chat template; the images, in order). Training
    data (`cavenav.training.dataset`) and fine-tuning read requests through this too, so a
    model learns from exactly what it is shown in flight.

    Args:
        image: what an image part becomes in the list of images; by default its picture,
            an RGB Pillow image.
    """
    chat, images = [], []
    for message in messages:
        content = message["content"]
        if isinstance(content, str):
            chat.append({"role": message["role"], "content": [{"type": "text", "text": content}]})
            continue
        parts: list[dict[str, Any]] = []
        for part in content:
            if part["type"] == "text":
                parts.append({"type": "text", "text": part["text"]})
            else:
                images.append((image or _picture)(part))
                parts.append({"type": "image"})
        chat.append({"role": message["role"], "content": parts})
    return chat, images


def _picture(part: Mapping[str, Any]) -> Any:  # noqa: ANN401 - a Pillow image
    from PIL import Image

    data = base64.b64decode(part["image_url"]["url"].split(",", 1)[1])
    return Image.open(io.BytesIO(data)).convert("RGB")


# A model this small decides on one CPU thread: its matrices are too small to share out,
# and an OpenMP parallel region entered from any thread but the main one (a sweep flies
# its episodes on threads) costs about 80 us to start. Measured on 2 cores with a
# 2.5 M-parameter Idefics3 (`finetune --new small`): 65 ms a decision on the main thread
# with 2 threads, 210 ms on a sweep's thread with 2, 62-66 ms on either with 1.
ONE_THREAD_BELOW = 10_000_000


class TransformersBackend:
    """`AutoProcessor` + `AutoModelForImageTextToText`, chat template with images."""

    name = "transformers"

    def __init__(self, config: TransformersConfig):
        try:
            import torch
            from transformers import AutoModelForImageTextToText, AutoProcessor
        except ImportError as exc:
            raise DependencyError(
                f"the transformers backend needs torch and transformers ({exc}); install with: "
                "pip install 'cavenav[transformers]'"
            ) from None
        self.config = config
        self.model = config.model
        self._torch = torch
        device = config.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        dtype = {
            "auto": "auto",
            "float32": torch.float32,
            "bfloat16": torch.bfloat16,
            "float16": torch.float16,
        }.get(config.dtype)
        if dtype is None:
            raise ConfigError(
                f"unknown dtype '{config.dtype}'; use auto, float32, bfloat16 or float16"
            )
        try:
            self._processor: Any = AutoProcessor.from_pretrained(config.model)
            model: Any = AutoModelForImageTextToText.from_pretrained(config.model, dtype=dtype)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot load the model '{config.model}': {_short(exc)}") from None
        self._model: Any = model.to(device).eval()
        self.device = device
        size = sum(parameter.numel() for parameter in model.parameters())
        self._one_thread = device == "cpu" and size < ONE_THREAD_BELOW

    @property
    def params(self) -> dict[str, Any]:
        return {
            "max_new_tokens": self.config.max_new_tokens,
            "temperature": self.config.temperature,
        }

    def check(self) -> None:
        """Loading already proved the model usable."""

    def count_tokens(self, text: str) -> int:
        """How many tokens ``text`` is to this model's tokenizer."""
        return len(self._processor.tokenizer(text, add_special_tokens=False)["input_ids"])

    @redacting
    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion:
        torch, called = self._torch, time.perf_counter()
        chat, images = local_chat(messages)
        prompt = self._processor.apply_chat_template(chat, add_generation_prompt=True)
        inputs = self._processor(text=prompt, images=images or None, return_tensors="pt").to(
            self.device
        )
        if self._one_thread:
            torch.set_num_threads(1)  # in this thread only: see ONE_THREAD_BELOW
        start = time.perf_counter()
        sample = self.config.temperature > 0
        with torch.inference_mode():
            out = self._model.generate(
                **inputs,
                max_new_tokens=self.config.max_new_tokens,
                do_sample=sample,
                **({"temperature": self.config.temperature} if sample else {}),
            )
        new = out[0, inputs["input_ids"].shape[1] :]
        text = self._processor.decode(new, skip_special_tokens=True)
        done = time.perf_counter()
        return Completion(
            text=text,
            prompt_tokens=int(inputs["input_ids"].shape[1]),
            completion_tokens=int(new.shape[0]),
            latency_s=done - called,  # the processor too
            model=self.config.model,
            model_s=done - start,  # the generation
        )

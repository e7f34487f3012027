"""Model backends: one `complete(messages)` call over any OpenAI-compatible endpoint or a
local transformers model, with bounded retries, token accounting and an optional cache.

Messages use the OpenAI chat format with images as PNG data URLs, so one request
recorded in a run folder means the same thing to every backend.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import math
import os
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

from cavenav.errors import (
    BackendAuthError,
    BackendError,
    BackendTimeout,
    BackendUnavailable,
    ConfigError,
    DependencyError,
    RateLimited,
)

__all__ = [
    "Backend",
    "CachedBackend",
    "Completion",
    "OpenAIBackend",
    "TransformersBackend",
    "request_hash",
]

Message = dict[str, Any]


@dataclass(frozen=True)
class Completion:
    """One model answer with its accounting.

    Attributes:
        text: the raw reply, reasoning included.
        prompt_tokens, completion_tokens: as reported by the server (or counted locally).
        latency_s: wall time of the successful request.
        retries: transport retries before it (timeouts, 408/409/429/5xx, refused).
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


@dataclass(frozen=True)
class OpenAIConfig:
    """Settings of an OpenAI-compatible endpoint (OpenAI, vLLM, SGLang, Ollama, llama.cpp).

    Attributes:
        base_url: e.g. http://localhost:8000/v1; None means api.openai.com.
        model: model name as the server knows it.
        api_key_env: environment variable holding the key; the key itself is never stored.
        timeout_s: per request.
        max_retries: transport retries per request (timeout, refused, 408/409/429/5xx),
            with exponential backoff that honours retry-after.
        temperature, max_tokens, detail: sampling and image settings sent with each request.
        backoff_s, backoff_cap_s: first and largest wait between retries.
    """

    model: str
    base_url: str | None = None
    api_key_env: str = "OPENAI_API_KEY"
    timeout_s: float = 60.0
    max_retries: int = 4
    temperature: float = 0.2
    max_tokens: int = 1024
    detail: str = "auto"
    backoff_s: float = 1.0
    backoff_cap_s: float = 30.0


_RETRY_STATUS = {408, 409, 429}


class OpenAIBackend:
    """Chat completions through the official `openai` SDK."""

    name = "openai"

    def __init__(self, config: OpenAIConfig, http_client: Any = None):
        import openai

        self.config = config
        self.model = config.model
        key = os.environ.get(config.api_key_env, "")
        if not key and config.base_url is None:
            raise BackendAuthError(
                f"no API key: set the environment variable {config.api_key_env} "
                "(or point --base-url at a local server)"
            )
        self._openai = openai
        # Local servers (vLLM, Ollama, llama.cpp) accept any key; the SDK needs one.
        self._client = openai.OpenAI(
            api_key=key or "EMPTY",
            base_url=config.base_url,
            timeout=config.timeout_s,
            max_retries=0,  # retried here, so that every retry is counted and recorded
            http_client=http_client,
        )

    @property
    def params(self) -> dict[str, Any]:
        return {"temperature": self.config.temperature, "max_tokens": self.config.max_tokens}

    def check(self) -> None:
        openai = self._openai
        try:
            self._client.with_options(max_retries=1).models.list()
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

    def _where(self) -> str:
        return self.config.base_url or "api.openai.com"

    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion:
        openai, cfg = self._openai, self.config
        extra: dict[str, Any] = {}
        if json_schema is not None:
            extra["response_format"] = {
                "type": "json_schema",
                "json_schema": {"name": "pilot_reply", "schema": json_schema, "strict": True},
            }
        errors: list[str] = []
        for attempt in range(cfg.max_retries + 1):
            start = time.perf_counter()
            wait: float | None = None
            try:
                response = self._client.chat.completions.create(
                    model=cfg.model,
                    messages=messages,  # type: ignore[arg-type]  # plain dicts, OpenAI format
                    **self.params,
                    **extra,
                )
            except (openai.AuthenticationError, openai.PermissionDeniedError) as exc:
                raise BackendAuthError(
                    f"{self._where()} refused the API key ({exc.status_code})"
                ) from None
            except openai.APITimeoutError:
                errors.append(f"timeout after {cfg.timeout_s:g} s")
                final: type[BackendError] = BackendTimeout
            except openai.APIConnectionError as exc:
                errors.append(f"connection failed: {exc}")
                final = BackendUnavailable
            except openai.APIStatusError as exc:
                status = exc.status_code
                if status not in _RETRY_STATUS and status < 500:
                    raise BackendError(
                        f"{self._where()} answered {status}: {_short(exc)}"
                    ) from None
                errors.append(f"HTTP {status}: {_short(exc)}")
                final = RateLimited if status == 429 else BackendUnavailable
                wait = _retry_after(exc.response.headers)
            else:
                choice = response.choices[0] if response.choices else None
                text = (choice.message.content or "") if choice else ""
                usage = response.usage
                return Completion(
                    text=text,
                    prompt_tokens=int(getattr(usage, "prompt_tokens", 0) or 0),
                    completion_tokens=int(getattr(usage, "completion_tokens", 0) or 0),
                    latency_s=time.perf_counter() - start,
                    retries=attempt,
                    errors=tuple(errors),
                    model=response.model or cfg.model,
                )
            if attempt < cfg.max_retries:
                backoff = cfg.backoff_s * 2**attempt * (1 + 0.1 * random.random())
                time.sleep(min(wait if wait is not None else backoff, cfg.backoff_cap_s))
        raise final(f"{self._where()}: gave up after {cfg.max_retries + 1} attempts ({errors[-1]})")


def _short(exc: Exception) -> str:
    return str(exc).splitlines()[0][:200]


def _retry_after(headers: Any) -> float | None:
    """Seconds from a retry-after(-ms) header, if the server sent one."""
    try:
        if headers.get("retry-after-ms"):
            return float(headers["retry-after-ms"]) / 1000.0
        if headers.get("retry-after"):
            value = float(headers["retry-after"])
            return value if math.isfinite(value) and value >= 0 else None
    except (TypeError, ValueError):
        return None
    return None


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

    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion:
        params = {**getattr(self.inner, "params", {}), "schema": json_schema}
        path = self.directory / f"{request_hash(self.model, messages, params)}.json"
        if path.is_file():
            stored = json.loads(path.read_text())
            stored["errors"] = tuple(stored.get("errors", ()))
            return Completion(**{**stored, "cached": True, "latency_s": 0.0, "retries": 0})
        completion = self.inner.complete(messages, json_schema)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(asdict(completion)))
        tmp.replace(path)
        return completion


# --------------------------------------------------------------------------- transformers


@dataclass(frozen=True)
class TransformersConfig:
    """A local vision-language model loaded with transformers.

    Attributes:
        model: a local folder (or a hub name when the machine can reach the hub).
        device: "auto" picks CUDA when available, else CPU; or "cpu", "cuda", "cuda:1".
        dtype: "auto", "float32", "bfloat16" or "float16".
        max_new_tokens: generation budget per reply.
        temperature: 0 means greedy decoding.
    """

    model: str
    device: str = "auto"
    dtype: str = "auto"
    max_new_tokens: int = 512
    temperature: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)


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

    @property
    def params(self) -> dict[str, Any]:
        return {
            "max_new_tokens": self.config.max_new_tokens,
            "temperature": self.config.temperature,
        }

    def check(self) -> None:
        """Loading already proved the model usable."""

    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion:
        from PIL import Image

        torch = self._torch
        chat, images = [], []
        for message in messages:
            content = message["content"]
            if isinstance(content, str):
                chat.append(
                    {"role": message["role"], "content": [{"type": "text", "text": content}]}
                )
                continue
            parts = []
            for part in content:
                if part["type"] == "text":
                    parts.append({"type": "text", "text": part["text"]})
                else:
                    data = part["image_url"]["url"].split(",", 1)[1]
                    images.append(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))
                    parts.append({"type": "image"})
            chat.append({"role": message["role"], "content": parts})
        prompt = self._processor.apply_chat_template(chat, add_generation_prompt=True)
        inputs = self._processor(text=prompt, images=images or None, return_tensors="pt").to(
            self.device
        )
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
        return Completion(
            text=text,
            prompt_tokens=int(inputs["input_ids"].shape[1]),
            completion_tokens=int(new.shape[0]),
            latency_s=time.perf_counter() - start,
            model=self.config.model,
        )

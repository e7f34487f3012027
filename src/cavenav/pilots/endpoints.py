"""How to reach a model: the settings of an OpenAI-compatible endpoint and of a local
transformers model, as plain values.

Kept apart from `cavenav.pilots.backends`, which talks to the models, so that the command
line and `cavenav.pilots.factory.VLMOptions` read these defaults without loading an HTTP
client at every start.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["OpenAIConfig", "TransformersConfig"]


@dataclass(frozen=True)
class OpenAIConfig:
    """Settings of an OpenAI-compatible endpoint (OpenAI, vLLM, SGLang, Ollama, llama.cpp).

    Attributes:
        base_url: e.g. http://localhost:8000/v1; None means api.openai.com.
        model: model name as the server knows it.
        api_key_env: environment variable holding the key; the key itself is never stored.
        timeout_s: the whole of one attempt (connect, send, wait, read every byte), not
            each socket read: a server trickling a byte a second is cut off all the same.
        deadline_s: the whole of one `complete()` call, retries and waits included; None
            means ``timeout_s * (max_retries + 1)``. A retry whose wait would pass it is
            not made.
        max_retries: transport retries per request (timeout, refused, 408/409/429/5xx,
            a body that is no reply, or what the server's x-should-retry says).
        temperature, max_tokens, detail: sampling and image settings sent with each request.
        backoff_s, backoff_cap_s: first and largest wait between retries when the server
            names none (retry-after): doubling from the first, less 0-25 % at random.
    """

    model: str
    base_url: str | None = None
    api_key_env: str = "OPENAI_API_KEY"
    timeout_s: float = 60.0
    deadline_s: float | None = None
    max_retries: int = 4
    temperature: float = 0.2
    max_tokens: int = 1024
    detail: str = "auto"
    backoff_s: float = 1.0
    backoff_cap_s: float = 30.0

    @property
    def budget_s(self) -> float:
        """Seconds one `complete()` call may take: `deadline_s`, or every attempt's timeout."""
        return (
            self.deadline_s
            if self.deadline_s is not None
            else self.timeout_s * (self.max_retries + 1)
        )


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

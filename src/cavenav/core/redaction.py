"""Credentials never reach a record or a screen, whoever echoes them back.

A careless server can quote the API key it was sent (OpenAI's own "Incorrect API key
provided: ..."), a proxy's error page can print the request's headers, and a model can
repeat what it was told. So every backend registers the key it sends (`register`) and
hands out nothing it has not passed through `redact`: replies, each attempt's error line,
error bodies, the errors it raises (`redacting`). The run folder's writer and the command
line's error line pass what they write through `redact` again, a last guard for text that
reached them another way (a reply cache written before, a wrapper of a backend).

Redacted are the registered keys wherever they appear, and the value of anything that
looks like an Authorization header (``Authorization: ...``, ``Bearer ...``, ``Basic ...``),
whoever's it is. This module is a leaf: it imports nothing of cavenav but the errors.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import functools
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ParamSpec, TypeVar

from cavenav.core.errors import CavenavError

__all__ = ["REDACTED", "Redactor", "redact", "redacting", "register"]

REDACTED = "[redacted]"
# Shorter "keys" are the placeholders local servers accept ("EMPTY" for vLLM, "ollama"):
# no secret, and taking every "EMPTY" out of a reply would only garble it.
MIN_SECRET_CHARS = 8

# The value of an Authorization header however it is quoted (a header line, a dict's repr,
# JSON, a query string), and a Bearer or Basic credential on its own. Records are mostly
# prose (a model's reasoning: "basic strategy: keep right", "authorization: granted"), so a
# value is taken for a credential only when its form says so: after the header's name with
# a scheme or a quote before it, or when it looks like one (`_looks_like_credential`). The
# value is token characters (a trailing full stop is the sentence's); one already redacted
# is matched as it is, so that redacting twice gives what redacting once gave.
_CREDENTIAL = re.compile(
    r"(?i)(?:"
    r"(?P<header>\b(?:proxy-)?authorization\b[\"']?\s*[:=]\s*)(?P<quote>[\"']?)"
    r"(?P<scheme>(?:bearer|basic|token|digest)\s+)?"
    r"|(?P<lone>\b(?:bearer|basic)\s+))"
    r"(?P<value>\[redacted\]|[\w\-.~+/=:%]*[\w\-~+/=%])"
)


def _looks_like_credential(value: str) -> bool:
    """Whether ``value`` reads as a token rather than a word: 8 or more characters with
    letters and digits (API keys, JWTs), or Base64 of "user:password" (RFC 7617)."""
    if len(value) >= 8 and any(c.isdigit() for c in value) and any(c.isalpha() for c in value):
        return True
    try:
        decoded = base64.b64decode(value, validate=True).decode("utf-8")
    except (binascii.Error, UnicodeDecodeError, ValueError):
        return False
    return ":" in decoded and decoded.isprintable()


def _redacted(match: re.Match[str]) -> str:
    """The match with its value redacted where it is a credential, else as it was."""
    value = match["value"]
    told = match["header"] is not None and bool(match["quote"] or match["scheme"])
    if value == REDACTED or not (told or _looks_like_credential(value)):
        return match[0]
    return match[0][: match.start("value") - match.start()] + REDACTED


@dataclass(frozen=True)
class Redactor:
    """Takes ``secrets`` and Authorization values out of text and of records.

    Attributes:
        secrets: the exact strings to take out (API keys); those shorter than
            `MIN_SECRET_CHARS` are placeholders and kept.
    """

    secrets: tuple[str, ...] = ()

    def __call__(self, text: str) -> str:
        """``text`` with every credential replaced by `REDACTED`."""
        text = _CREDENTIAL.sub(_redacted, text)
        for secret in self.secrets:
            if len(secret) >= MIN_SECRET_CHARS:
                text = text.replace(secret, REDACTED)
        return text

    def scrub(self, value: Any) -> Any:  # noqa: ANN401 - any record
        """``value`` with every string in it redacted: dicts (keys too), lists, tuples and
        dataclasses are rebuilt, anything else (numbers, None, arrays) returned as is."""
        if isinstance(value, str):
            return self(value)
        if isinstance(value, dict):
            return {self.scrub(k): self.scrub(v) for k, v in value.items()}
        if type(value) in (list, tuple):
            return type(value)(self.scrub(v) for v in value)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            fields = [f.name for f in dataclasses.fields(value) if f.init]
            return dataclasses.replace(
                value, **{name: self.scrub(getattr(value, name)) for name in fields}
            )
        return value


# The keys this process sends: backends of a sweep's threads register theirs concurrently.
_lock = threading.Lock()
_current = Redactor()


def register(secret: str) -> None:
    """Redact ``secret`` from now on, in this process, wherever `redact` is used."""
    global _current
    if len(secret) < MIN_SECRET_CHARS:
        return
    with _lock:
        if secret not in _current.secrets:
            _current = Redactor((*_current.secrets, secret))


def redact(value: Any) -> Any:  # noqa: ANN401 - any record
    """``value`` (a string or a record) with every registered key and Authorization value
    taken out (see `Redactor.scrub`)."""
    return _current.scrub(value)


P = ParamSpec("P")
R = TypeVar("R")


def redacting(method: Callable[P, R]) -> Callable[P, R]:
    """A backend method whose result, and whatever `CavenavError` it raises (message and
    attributes: each attempt's error line, the body received), are redacted: so that no
    path through the method can hand a key out."""

    @functools.wraps(method)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return redact(method(*args, **kwargs))
        except CavenavError as exc:
            exc.args = redact(exc.args)
            for name, value in vars(exc).items():
                setattr(exc, name, redact(value))
            raise

    return wrapper

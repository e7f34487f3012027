"""Reading a model's reply: find the final one-pair dictionary and parse its action.

Real models write reasoning before the answer, fence it in a code block, use single
quotes (a Python dict), or add prose after it. The final answer is the last dictionary in
the text that reads as JSON or as a Python literal; it must hold exactly one pair
``{action: justification}`` (or, in structured mode, the keys ``situation``,
``constraints``, ``action``, ``justification``).
"""

from __future__ import annotations

import ast
import json
from dataclasses import dataclass

from cavenav.core.errors import ActionError
from cavenav.core.types import Action
from cavenav.motion.actions import DEFAULT_SPACE, ActionSpace, parse_action

__all__ = ["MAX_REQUERIES", "ParsedReply", "final_answer", "parse_reply"]

# SPEC's N: the re-queries after unusable replies before the pilot gives up and the
# episode ends as a pilot failure.
MAX_REQUERIES = 3

STRUCTURED_KEYS = ("situation", "constraints", "action", "justification")


@dataclass(frozen=True)
class ParsedReply:
    action: Action
    action_text: str
    justification: str


def _dict_candidates(text: str, offset: int = 0) -> tuple[list[tuple[int, str]], int]:
    """Every balanced ``{...}`` span of ``text[offset:]``, outermost only, in order of
    appearance, each with where it starts; and where a brace still open at the end was
    opened (-1 if none)."""
    spans, depth, start, quote, escaped = [], 0, -1, "", False
    for i in range(offset, len(text)):
        ch = text[i]
        if quote:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == quote:
                quote = ""
            continue
        if ch in "\"'" and depth > 0:
            quote = ch
        elif ch == "{":
            if depth == 0:
                start = i
            depth += 1
        elif ch == "}" and depth > 0:
            depth -= 1
            if depth == 0:
                spans.append((start, text[start : i + 1]))
    return spans, start if depth > 0 else -1


def _load(candidate: str) -> object:
    try:
        return json.loads(candidate)
    except (json.JSONDecodeError, ValueError):
        pass
    try:
        return ast.literal_eval(candidate)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        return None


def _final_dict(text: str, passes: int = 64) -> dict | None:
    """The last ``{...}`` span of ``text`` that loads as a dictionary.

    A brace in the reasoning must not swallow the answer after it. One never closed ("I
    considered {going left") is read as prose: the text after it is scanned again. One
    with an apostrophe after it ("{going left, but it's narrow") can pair with the
    answer's own quotes and braces into a span that does not load: the text past that
    span's brace is scanned again. The passes are bounded, so a reply of a thousand
    braces is refused quickly instead of exhausting the stack.
    """
    answer, offset = None, 0
    for _ in range(passes):
        spans, still_open = _dict_candidates(text, offset)
        if spans and not isinstance(_load(spans[-1][1]), dict):
            # The last span does not load: look inside it, before any brace left open
            # after it ("{a, {answer}} then {maybe").
            still_open = spans[-1][0]
        for _, span in reversed(spans):
            loaded = _load(span)
            if isinstance(loaded, dict):
                answer = loaded
                break
        if still_open < 0:
            break
        offset = still_open + 1
    return answer


def final_answer(text: str) -> tuple[object, str]:
    """The final one-pair dictionary of a reply as (key, justification), the key as
    written (the action string, or a pilot design's choice, `cavenav.pilots.designs`).

    Raises:
        ActionError: with a reason that can be sent back to the model.
    """
    if not isinstance(text, str) or not text.strip():
        raise ActionError("the reply is empty")
    answer = _final_dict(text[-20000:])
    if answer is None:
        raise ActionError(
            'no final dictionary found; end the reply with {"<action>": "<justification>"}'
        )
    if set(answer) >= {"action", "justification"}:
        return answer["action"], str(answer["justification"]).strip()
    if len(answer) != 1:
        raise ActionError(
            f"the final dictionary has {len(answer)} key-value pairs; give exactly one, "
            'as {"<action>": "<justification>"}'
        )
    ((key, justification),) = answer.items()
    return key, str(justification).strip()


def parse_reply(text: str, space: ActionSpace = DEFAULT_SPACE) -> ParsedReply:
    """Extract and validate the final answer of a reply.

    Raises:
        ActionError: with a reason that can be sent back to the model.
    """
    action_text, justification = final_answer(text)
    if not isinstance(action_text, str):
        raise ActionError("the dictionary's key must be the action string")
    action = parse_action(action_text, space)
    return ParsedReply(action, action_text.strip(), justification)

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

from cavenav.actions import DEFAULT_SPACE, ActionSpace, parse_action
from cavenav.errors import ActionError
from cavenav.types import Action

__all__ = ["ParsedReply", "parse_reply"]

STRUCTURED_KEYS = ("situation", "constraints", "action", "justification")


@dataclass(frozen=True)
class ParsedReply:
    action: Action
    action_text: str
    justification: str


def _dict_candidates(text: str) -> list[str]:
    """Every balanced ``{...}`` span, outermost only, in order of appearance; a brace
    that is never closed is read as prose."""
    spans, depth, start, quote, escaped = [], 0, -1, "", False
    for i, ch in enumerate(text):
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
                spans.append(text[start : i + 1])
    if depth > 0:
        # A brace (or a quote) left open in the reasoning ("I considered {going left")
        # would swallow the answer after it: look again past the brace that opened it.
        spans += _dict_candidates(text[start + 1 :])
    return spans


def _load(candidate: str) -> object:
    try:
        return json.loads(candidate)
    except (json.JSONDecodeError, ValueError):
        pass
    try:
        return ast.literal_eval(candidate)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        return None


def parse_reply(text: str, space: ActionSpace = DEFAULT_SPACE) -> ParsedReply:
    """Extract and validate the final answer of a reply.

    Raises:
        ActionError: with a reason that can be sent back to the model.
    """
    if not isinstance(text, str) or not text.strip():
        raise ActionError("the reply is empty")
    answer = None
    for candidate in reversed(_dict_candidates(text[-20000:])):
        loaded = _load(candidate)
        if isinstance(loaded, dict):
            answer = loaded
            break
    if answer is None:
        raise ActionError(
            'no final dictionary found; end the reply with {"<action>": "<justification>"}'
        )
    if set(answer) >= {"action", "justification"}:
        action_text, justification = answer["action"], answer["justification"]
    elif len(answer) != 1:
        raise ActionError(
            f"the final dictionary has {len(answer)} key-value pairs; give exactly one, "
            'as {"<action>": "<justification>"}'
        )
    else:
        ((action_text, justification),) = answer.items()
    if not isinstance(action_text, str):
        raise ActionError("the dictionary's key must be the action string")
    action = parse_action(action_text, space)
    return ParsedReply(action, action_text.strip(), str(justification).strip())

"""The prompt (SPEC section 3) and the reading of replies (SPEC section 4)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from cavenav.core.errors import ActionError, ConfigError
from cavenav.core.types import Action, Rules
from cavenav.motion.actions import DEFAULT_SPACE, ActionSpace, parse_action
from cavenav.pilots.prompt import PromptConfig, render_repair, render_system
from cavenav.pilots.reply import parse_reply
from tests.motion.test_actions import inadmissible_actions, worded_actions


def test_the_prompt_has_the_four_parts_and_the_reply_format() -> None:
    text = render_system(PromptConfig())
    for heading in (
        "# 1. Mission",
        "# 2. What you receive",
        "# 3. Strategy",
        "# 4. Think step by step",
    ):
        assert heading in text
    for phrase in (
        "Collision avoidance comes before progress",
        "2 m from walls",
        "0.1-0.2 m",
        "within 1.5 m",
        "Do not reverse",
        "(a) Situation",
        "(b) Active constraints",
        "(c) Action selection",
        "exactly one key-value pair",
    ):
        assert phrase in text


def test_every_number_in_the_prompt_comes_from_the_configuration() -> None:
    space = ActionSpace(
        forward_m=(0.0, 0.25, 0.75), yaw_deg=(0.0, 12.0), vertical_range_m=(0.2, 1.5)
    )
    rules = Rules(standoff_m=3.0, no_forward_within_m=2.5, slow_forward_m=(0.1, 0.3))
    text = render_system(
        PromptConfig(space=space, rules=rules), depth_range=(0.5, 30.0), hfov_deg=70
    )
    assert "0.25, 0.75 m" in text and "12 degrees" in text and "from 0.2 to 1.5 m" in text
    assert "3 m from walls" in text and "within 2.5 m" in text and "at most 0.1-0.3 m" in text
    assert "30 m or more" in text and "0.5 + g / 255" in text and "70.0 degrees wide" in text
    assert "90" not in text.split("# The action")[1]  # the default yaw set is gone


def test_history_zero_is_explained() -> None:
    assert "No earlier observations" in render_system(PromptConfig(history=0))


def test_a_user_prompt_file_is_rendered_with_the_same_fields(tmp_path: Path) -> None:
    path = tmp_path / "mine.md"
    path.write_text('Keep {standoff_m} m away; turns: {yaw_deg}. Reply {{"a": "b"}}')
    text = render_system(PromptConfig(system_file=path))
    assert text.startswith("Keep 2 m away; turns: 5, 10, 15, 20, 30, 45, 90, 180.")
    path.write_text("Use {no_such_field}")
    with pytest.raises(ConfigError, match="no_such_field"):
        render_system(PromptConfig(system_file=path))


def test_the_repair_message_tells_the_model_what_was_wrong() -> None:
    text = render_repair(PromptConfig(), "forward 0.3 m is not admissible")
    assert "forward 0.3 m is not admissible" in text and "0.1, 0.2, 0.5, 1 m" in text


@pytest.mark.parametrize(
    "reply",
    [
        'Reasoning...\n{"forward 0.5 m, turn left 15 deg": "open ahead"}',
        "(a) ok (b) ok (c) ok\n```json\n"
        '{"turn left 15 degrees, forward 0.5 meters": "open ahead"}\n```',
        "Final answer: {'Forward 0.5m, yaw left 15°': 'open ahead'} I will reassess.",
        '```python\n{"ahead 0.5 m + rotate left 15 deg": "open ahead"}\n```\nDone.',
        'Earlier I thought {"hold": "x"} but now: '
        '{"forward 0.5 m and turn left 15 deg": "open ahead"}',
        "I considered {going left, but it's narrow there.\n"
        '{"forward 0.5 m, turn left 15 deg": "open ahead"}',
        '{"situation": "s", "constraints": "c", "action": "forward 0.5 m, turn left 15 deg", '
        '"justification": "open ahead"}',
        # The open brace's apostrophe pairs with the answer's, and the brace in the
        # answer's string closes the span: the answer must not be swallowed.
        "I considered {going left, but it's narrow there.\n"
        '{"situation": "it\'s \'narrow\'", "constraints": "wall }", '
        '"action": "forward 0.5 m, turn left 15 deg", "justification": "open ahead"}',
    ],
)
def test_replies_as_models_write_them(reply: str) -> None:
    parsed = parse_reply(reply)
    assert parsed.action == Action(forward=0.5, yaw_deg=15.0)
    assert parsed.justification == "open ahead"


@pytest.mark.parametrize(
    ("reply", "reason"),
    [
        ("I would go forward a little.", "no final dictionary"),
        ('{"forward 0.5 m": "a", "turn left 10 deg": "b"}', "2 key-value pairs"),
        ('{"forward 0.3 m": "gap"}', "not admissible"),
        ("{}", "0 key-value pairs"),
        ("", "empty"),
        ('{"turn left": "no magnitude"}', "no magnitude"),
        ("{x " * 2000, "no final dictionary"),  # braces never closed: refused, not a crash
    ],
)
def test_unusable_replies_are_rejected_with_a_reason(reply: str, reason: str) -> None:
    with pytest.raises(ActionError, match=reason):
        parse_reply(reply)


def assert_accepted_replies_are_sound(reply: str) -> None:
    """Parse ``reply``; if it is accepted, the action must be admissible and be the one
    its own action text reads as, and the justification must be trimmed text."""
    try:
        parsed = parse_reply(reply)
    except ActionError:
        event("refused")
        return  # refused with a reason: fine
    event("accepted")
    assert DEFAULT_SPACE.is_valid(parsed.action)
    assert parse_action(parsed.action_text) == parsed.action
    assert parsed.action_text == parsed.action_text.strip()
    assert parsed.justification == parsed.justification.strip()


# ------------------------------------------------------------------ replies, built
# Property tests build a reply the way models write one (reasoning, then the answer as
# JSON or a Python literal, fenced or bare, one pair or the structured keys, then prose)
# around an action built from the admissible sets, so that each check runs on every
# accepted example.

# Prose before the answer: any text with no dictionary of its own (braces left open
# included), and what models write.
reasoning = st.one_of(
    st.sampled_from(
        [
            "",
            "(a) Situation: the passage bends left.\n(b) Constraints: wall 1.2 m right.\n"
            "(c) Action:\n",
            "Final answer: ",
            "I considered {going left, but it's narrow there.\n",
            'Earlier I thought {"hold": "x"} but now: ',
        ]
    ),
    st.text(max_size=200).filter(lambda t: "}" not in t),
)
afterword = st.one_of(
    st.sampled_from(["", "\nI will reassess after this step.", " Done.", "\n\n"]),
    st.text(max_size=200).filter(lambda t: "{" not in t),
)
justifications = st.one_of(
    st.sampled_from(["open ahead", "  wall close on the right  ", "it's 'narrow'", ""]),
    st.text(max_size=40),
)
_WRITERS = [
    json.dumps,
    lambda d: json.dumps(d, indent=2, ensure_ascii=False),
    repr,
    lambda d: "```json\n" + json.dumps(d, indent=2) + "\n```",
    lambda d: "```python\n" + repr(d) + "\n```",
    lambda d: "```\n" + json.dumps(d) + "\n```",
]


class Reply(NamedTuple):
    """A built reply, in its three parts, and what its answer holds."""

    before: str  # reasoning
    answer: str  # the final dictionary as written: JSON or a Python literal, maybe fenced
    after: str  # afterword
    action_text: str
    justification: str

    @property
    def text(self) -> str:
        return self.before + self.answer + self.after


@st.composite
def replies(draw: st.DrawFn, action_texts: st.SearchStrategy[str]) -> Reply:
    """A reply around an action text drawn from ``action_texts``."""
    action_text = draw(st.sampled_from(["", " ", "\n"])) + draw(action_texts)
    justification = draw(justifications)
    if draw(st.booleans()):
        answer = {action_text: justification}
    else:  # structured mode
        answer = {
            "situation": draw(justifications),
            "constraints": draw(justifications),
            "action": action_text,
            "justification": justification,
        }
    written = draw(st.sampled_from(_WRITERS))(answer)
    return Reply(draw(reasoning), written, draw(afterword), action_text, justification)


admissible_replies = worded_actions.flatmap(
    lambda built: st.tuples(st.just(built[0]), replies(st.just(built[1])))
)


@given(admissible_replies)
def test_the_final_answer_is_found_after_any_reasoning_and_before_any_afterword(
    built: tuple[Action, Reply],
) -> None:
    action, reply = built
    parsed = parse_reply(reply.text)
    assert parsed.action == action  # signs and magnitudes as built
    assert parsed.action_text == reply.action_text.strip()
    assert parsed.justification == reply.justification.strip()


@given(inadmissible_actions().flatmap(lambda b: st.tuples(st.just(b[0]), replies(st.just(b[1])))))
def test_a_reply_with_an_inadmissible_magnitude_is_refused_naming_the_part(
    built: tuple[str, Reply],
) -> None:
    name, reply = built
    with pytest.raises(ActionError, match=rf"^{name} \S+ (m|deg) is not admissible"):
        parse_reply(reply.text)


def _splice(draw: st.DrawFn, text: str, noise: st.SearchStrategy[str], most: int) -> str:
    """``text`` with up to ``most`` characters from a drawn place replaced by ``noise``."""
    start = draw(st.integers(0, len(text)))
    end = draw(st.integers(start, min(len(text), start + most)))
    return text[:start] + draw(noise) + text[end:]


# Noise that opens no dictionary and no string: prose garbled this way hides no answer.
_plain_noise = st.text(
    st.characters(blacklist_characters="{}\"'\\", blacklist_categories=["Cs"]), max_size=10
)


@st.composite
def garbled(draw: st.DrawFn) -> tuple[Action | None, str]:
    """(action, reply): an admissible reply garbled as a model or a transport might. Half
    the time only its prose is, by text inserted that opens no dictionary or string, and
    the reply must still read as the action built; otherwise a slice anywhere is replaced
    by any text (action None), and the reply may or may not still be readable."""
    action, reply = draw(admissible_replies)
    if draw(st.booleans()):
        if draw(st.booleans()):
            reply = reply._replace(before=_splice(draw, reply.before, _plain_noise, 0))
        else:
            reply = reply._replace(after=_splice(draw, reply.after, _plain_noise, 0))
        return action, reply.text
    return None, _splice(draw, reply.text, st.text(max_size=10), 10)


# Three in four inputs are garbled admissible replies, so that most (measured: 64-83%
# in five runs) are accepted and the checks run; the rest are any text at all. Python's
# literal reader warns of a stray backslash in garbled text, then refuses or reads it.
@pytest.mark.filterwarnings("ignore:invalid escape sequence:DeprecationWarning")
@given(
    st.sampled_from(
        [garbled(), garbled(), garbled(), st.text(max_size=400).map(lambda t: (None, t))]
    ).flatmap(lambda s: s)
)
def test_no_reply_crashes_the_parser_and_what_it_accepts_is_sound(
    built: tuple[Action | None, str],
) -> None:
    action, reply = built
    assert_accepted_replies_are_sound(reply)
    if action is not None:  # only its prose was garbled
        assert parse_reply(reply).action == action


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.text(max_size=20),
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=10), c, max_size=3),
    max_leaves=10,
)


@st.composite
def json_answers(draw: st.DrawFn) -> tuple[Action, object, object]:
    """(action, answer, justification): an admissible action's text as the key of a
    one-pair dictionary or the "action" of the structured keys, whatever JSON value the
    justification and the other keys hold."""
    action, text = draw(worded_actions)
    justification = draw(json_values)
    if draw(st.booleans()):
        return action, {text: justification}, justification
    others = {key: draw(json_values) for key in ("situation", "constraints")}
    return action, {**others, "action": text, "justification": justification}, justification


# Two in three inputs are answers built to be accepted (measured with the rest: 73-89%
# accepted); the rest are any JSON value.
@given(
    st.sampled_from(
        [json_answers(), json_answers(), json_values.map(lambda v: (None, v, None))]
    ).flatmap(lambda s: s)
)
def test_any_json_value_is_read_exactly_or_refused_with_a_reason(
    built: tuple[Action | None, object, object],
) -> None:
    action, value, justification = built
    reply = "answer: " + json.dumps(value)
    if action is None:
        assert_accepted_replies_are_sound(reply)
        return
    parsed = parse_reply(reply)
    event("accepted")
    assert parsed.action == action
    assert parsed.justification == str(justification).strip()


# ------------------------------------------------ braces and quotes around the answer


@pytest.mark.parametrize(
    "reply",
    [
        # A model copying a template's doubled brace: the stray one opens the reply.
        '{{"forward 0.5 m, turn left 15 deg": "open ahead"}',
        'Answer: {{"forward 0.5 m, turn left 15 deg": "open ahead"}',
        # A closing brace in the reasoning closes nothing.
        'The passage bends :} then opens.\n{"forward 0.5 m, turn left 15 deg": "open ahead"}',
        # An escaped quote inside a string does not end it, so its brace stays text.
        '{"forward 0.5 m, turn left 15 deg": "open ahead, \\"past the arch}\\""}',
        # An answer inside an aside is found whatever prose follows it, a brace included.
        'I weigh {a, {"forward 0.5 m, turn left 15 deg": "open ahead"}}',
        'I weigh {a, {"forward 0.5 m, turn left 15 deg": "open ahead"}} then {maybe',
        # Structured mode's two keys alone.
        '{"action": "forward 0.5 m, turn left 15 deg", "justification": "open ahead"}',
    ],
)
def test_the_answer_is_found_past_stray_braces_and_escaped_quotes(reply: str) -> None:
    parsed = parse_reply(reply)
    assert parsed.action == Action(forward=0.5, yaw_deg=15.0)
    assert parsed.action_text == "forward 0.5 m, turn left 15 deg"
    assert parsed.justification.startswith("open ahead")


def test_a_reply_is_read_against_the_action_space_it_is_given() -> None:
    coarse = ActionSpace(forward_m=(0.0, 0.3))
    assert parse_reply('{"forward 0.3 m": "gap"}', coarse).action == Action(forward=0.3)
    with pytest.raises(ActionError, match="not admissible"):
        parse_reply('{"forward 0.5 m": "gap"}', coarse)


@pytest.mark.parametrize(
    ("reply", "message"),
    [
        ("   \n", "the reply is empty"),
        (
            "I would go forward a little.",
            'no final dictionary found; end the reply with {"<action>": "<justification>"}',
        ),
        (
            '{"forward 0.5 m": "a", "turn left 10 deg": "b"}',
            "the final dictionary has 2 key-value pairs; give exactly one, "
            'as {"<action>": "<justification>"}',
        ),
        ("{1: 'forward one metre'}", "the dictionary's key must be the action string"),
        (
            '{"action": 0.5, "justification": "forward"}',
            "the dictionary's key must be the action string",
        ),
    ],
)
def test_an_unusable_reply_is_told_exactly_what_to_fix(reply: str, message: str) -> None:
    with pytest.raises(ActionError) as refused:
        parse_reply(reply)
    assert str(refused.value) == message

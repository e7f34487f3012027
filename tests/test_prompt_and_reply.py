"""The prompt (SPEC section 3) and the reading of replies (SPEC section 4)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cavenav.actions import DEFAULT_SPACE, ActionSpace, format_action, parse_action
from cavenav.errors import ActionError, ConfigError
from cavenav.pilots.prompt import PromptConfig, render_repair, render_system
from cavenav.pilots.reply import parse_reply
from cavenav.types import Action, Rules


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
        return  # rejected with a reason: fine
    assert DEFAULT_SPACE.is_valid(parsed.action)
    assert parse_action(parsed.action_text) == parsed.action
    assert parsed.action_text == parsed.action_text.strip()
    assert parsed.justification == parsed.justification.strip()


@given(st.text(max_size=400))
def test_no_reply_crashes_the_parser(reply: str) -> None:
    assert_accepted_replies_are_sound(reply)


@given(
    st.recursive(
        st.none() | st.booleans() | st.integers() | st.text(max_size=20),
        lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=10), c, max_size=3),
        max_leaves=10,
    )
)
def test_no_json_value_crashes_the_parser(value: object) -> None:
    assert_accepted_replies_are_sound("answer: " + json.dumps(value))


admissible_actions = st.builds(
    Action,
    forward=st.sampled_from([0.0, 0.1, 0.2, 0.5, 1.0, -0.5]),
    right=st.sampled_from([0.0, 0.1, -0.2, 1.0]),
    up=st.sampled_from([0.0, 0.1, -0.35, 2.0]),
    yaw_deg=st.sampled_from([0.0, 5.0, -15.0, 90.0, -180.0]),
)


@given(
    admissible_actions,
    st.text(max_size=40),
    st.text(max_size=200).filter(lambda t: "}" not in t),
    st.text(max_size=200).filter(lambda t: "{" not in t),
    st.sampled_from([json.dumps, repr]),
)
def test_the_final_answer_is_found_after_any_reasoning_and_before_any_afterword(
    action: Action, justification: str, reasoning: str, afterword: str, write
) -> None:
    # Prose without a dictionary of its own (braces left open before the answer included),
    # before and after a JSON or Python-literal answer.
    reply = reasoning + write({format_action(action): justification}) + afterword
    parsed = parse_reply(reply)
    assert parsed.action == action
    assert parsed.action_text == format_action(action)
    assert parsed.justification == justification.strip()

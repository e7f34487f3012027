"""The action language of SPEC section 4."""

from __future__ import annotations

import math
import re
from dataclasses import astuple

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cavenav.actions import DEFAULT_SPACE, format_action, parse_action, to_twist
from cavenav.errors import ActionError
from cavenav.types import Action


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("forward 0.5 m", Action(forward=0.5)),
        ("hold", Action()),
        ("Turn right 30°, move forward 0.2 meters", Action(forward=0.2, yaw_deg=-30)),
        ("yaw left 15 degrees + strafe right 0.1 m", Action(right=0.1, yaw_deg=15)),
        ("ascend 0.35 m and go ahead 1 m", Action(forward=1.0, up=0.35)),
        ("descend 2.0 metres", Action(up=-2.0)),
        ("back 0.1 m", Action(forward=-0.1)),
        ("shift left 20 cm", Action(right=-0.2)),
        ("rotate 90 deg clockwise", Action(yaw_deg=-90)),
        ("df=0.5, dr=-0.2, dz=-0.3, dpsi=15", Action(forward=0.5, right=-0.2, up=-0.3, yaw_deg=15)),
        ("STOP", Action()),
    ],
)
def test_natural_wordings_parse(text: str, expected: Action) -> None:
    assert parse_action(text) == expected


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("forward 0.3 m", "not admissible"),
        ("turn left 12 deg", "not admissible"),
        ("ascend 2.5 m", "not admissible"),
        ("descend 0.05 m", "not admissible"),
        ("left 10", "ambiguous"),
        ("turn left", "no magnitude"),
        ("forward 1 m, forward 0.5 m", "twice"),
        ("fly to the moon 5", "cannot read"),
        ("", "empty"),
        ("turn left 0.5 rad", "degrees"),
        ("forward 15 deg", "degrees only"),
        ("forward -0.5 m", "signed"),
        ("hold, forward 1 m", "holds and moves"),
    ],
)
def test_bad_actions_are_rejected_with_a_reason(text: str, reason: str) -> None:
    with pytest.raises(ActionError, match=reason):
        parse_action(text)


@pytest.mark.parametrize(
    ("action", "refused"),
    [
        (Action(forward=10**400), "forward 100000"),  # beyond a float's range
        (Action(forward=True), "forward True"),  # a flag, though True == 1
        (Action(right="0.5"), "lateral '0.5'"),  # type: ignore[arg-type]
        (Action(up=None), "vertical None"),  # type: ignore[arg-type]
        (Action(yaw_deg=1j), "yaw 1j"),  # type: ignore[arg-type]
    ],
)
def test_validate_refuses_a_part_that_is_no_real_number_naming_it(
    action: Action, refused: str
) -> None:
    with pytest.raises(ActionError, match=f"^{re.escape(refused)}"):
        DEFAULT_SPACE.validate(action)


def test_validate_returns_every_part_as_a_float() -> None:
    validated = DEFAULT_SPACE.validate(Action(1, 0, -1, 15))  # type: ignore[arg-type]
    assert validated == Action(1.0, 0.0, -1.0, 15.0)
    assert [type(v) for v in astuple(validated)] == [float] * 4


def test_magnitudes_are_never_rounded_to_the_set() -> None:
    with pytest.raises(ActionError):
        parse_action("forward 0.49 m")


signs = st.sampled_from([1.0, -1.0])
valid_actions = st.builds(
    lambda f, sf, r, sr, z, sz, y, sy: Action(
        forward=f * sf + 0.0, right=r * sr + 0.0, up=z * sz + 0.0, yaw_deg=y * sy + 0.0
    ),
    st.sampled_from(DEFAULT_SPACE.forward_m),
    signs,
    st.sampled_from(DEFAULT_SPACE.lateral_m),
    signs,
    st.one_of(st.just(0.0), st.floats(0.1, 2.0)),
    signs,
    st.sampled_from(DEFAULT_SPACE.yaw_deg),
    signs,
)


@given(valid_actions)
def test_every_valid_action_formats_and_parses_back_to_itself(action: Action) -> None:
    assert parse_action(format_action(action)) == action


# Text that reads like an action often enough for the parser to accept some of it: motions,
# magnitudes in and out of the admissible sets, units right and wrong, several separators.
_MOTIONS = "forward|back|ahead|turn left|turn right|rotate|strafe left|shift right|ascend|descend"
_clause = st.builds(
    "{} {}{}".format,
    st.sampled_from([*_MOTIONS.split("|"), "up", "left", "hold", "df=", "dpsi ="]),
    st.sampled_from(["0.1", "0.2", "0.3", ".5", "1", "1.0", "2", "2.5", "10", "15", "20", "-0.5"]),
    st.sampled_from([" m", "m", " cm", " deg", "°", " degrees", " metres", " rad", ""]),
)
action_like = st.builds(
    lambda clauses, sep: sep.join(clauses),
    st.lists(_clause, min_size=1, max_size=4),
    st.sampled_from([", ", " and ", " + ", " then ", "; "]),
)


@given(st.one_of(st.text(max_size=200), action_like))
def test_whatever_the_parser_accepts_is_admissible_canonical_and_written_in_the_text(
    text: str,
) -> None:
    try:
        action = parse_action(text)
    except ActionError:
        return  # rejected with a reason: fine
    assert DEFAULT_SPACE.is_valid(action)
    assert parse_action(format_action(action)) == action
    # Never rounded to the set, never invented: each magnitude is a number the text wrote
    # (in metres, or in centimetres divided by 100).
    written = [float(n) for n in re.findall(r"\d+(?:\.\d*)?|\.\d+", text)]
    written += [n / 100 for n in written]
    for value in (action.forward, action.right, action.up, action.yaw_deg):
        if value:
            assert any(abs(abs(value) - n) < 1e-9 for n in written), (value, text)


def test_twist_follows_ros_conventions() -> None:
    # ROS: x forward, y left, z up, angular z counter-clockwise (left).
    twist = to_twist(Action(forward=1.0, right=0.5, up=-0.2, yaw_deg=90.0), dt=2.0)
    assert twist == pytest.approx((0.5, -0.25, -0.1, math.pi / 4))

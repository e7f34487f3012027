"""The action language of SPEC section 4."""

from __future__ import annotations

import math
import re
from dataclasses import astuple, replace

import pytest
from hypothesis import event, example, given
from hypothesis import strategies as st

from cavenav.core.errors import ActionError
from cavenav.core.types import Action
from cavenav.motion.actions import DEFAULT_SPACE, format_action, parse_action, to_twist


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
        (".1 m ahead", Action(forward=0.1)),  # a leading decimal point, not a full stop
        ("d_psi=-15, d_f=1", Action(forward=1.0, yaw_deg=-15)),
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


# ------------------------------------------------------------- actions built, then worded
# Property tests build an action from the admissible sets (SPEC section 4) and write it as
# models do, so that the parser accepts what is generated and each check runs on every
# example; inadmissible magnitudes have strategies of their own, which must be refused.

signs = st.sampled_from([1.0, -1.0])
vertical_m = st.one_of(
    st.floats(0.1, 2.0),  # continuous: any float of the closed interval, its ends included
    st.integers(10, 200).map(lambda cm: cm / 100),  # as models write it: 0.35 m
)
valid_actions = st.builds(
    lambda f, sf, r, sr, z, sz, y, sy: Action(
        forward=f * sf + 0.0, right=r * sr + 0.0, up=z * sz + 0.0, yaw_deg=y * sy + 0.0
    ),
    st.sampled_from(DEFAULT_SPACE.forward_m),
    signs,
    st.sampled_from(DEFAULT_SPACE.lateral_m),
    signs,
    st.one_of(st.just(0.0), vertical_m),
    signs,
    st.sampled_from(DEFAULT_SPACE.yaw_deg),
    signs,
)

# How each motion is worded, for a positive and a negative part; "{}" takes the magnitude.
# SPEC section 5: right is positive dr, up is positive dz, a left turn is positive dpsi.
_WORDINGS = {
    "forward": (
        ["forward {}", "move forward {}", "go ahead {}", "{} ahead", "advance {}", "surge {}"],
        ["back {}", "move backward {}", "reverse {}", "go astern {}", "{} backwards"],
    ),
    "right": (
        ["strafe right {}", "shift right {}", "slide to starboard {}", "{} to the right"],
        ["strafe left {}", "shift left {}", "sway port {}", "strafe {} to the left"],
    ),
    "up": (
        ["ascend {}", "rise {}", "go up {}", "climb {}", "move upward {}"],
        ["descend {}", "sink {}", "dive {}", "go down {}", "drop {}"],
    ),
    "yaw": (
        [
            "turn left {}",
            "yaw left {}",
            "rotate {} counterclockwise",
            "pivot to port {}",
            "turn {} anti-clockwise",
        ],
        ["turn right {}", "yaw right {}", "rotate {} clockwise", "spin starboard {}", "turn {} cw"],
    ),
}
_HOLDS = ["hold", "Hold position", "stop", "hover in place", "stay", "wait"]
_SEPARATORS = [", ", " and ", " then ", "; ", " + ", " & ", ", then ", " while "]
_SIGNED_KEYS = {"forward": "df", "right": "dr", "up": "dz", "yaw": "dpsi"}
_PARTS = {"forward": "forward", "right": "right", "up": "up", "yaw": "yaw_deg"}  # Action's
_REFUSED_AS = {"forward": "forward", "right": "lateral", "up": "vertical", "yaw": "yaw"}


def _number(value: float) -> list[str]:
    """Ways to write ``value``, each reading back to the same float: 0.5, .5, 1, 1.0."""
    text = repr(value)
    ways = [text, text.removesuffix(".0")]
    if text.startswith("0."):
        ways.append(text[1:])
    return ways


@st.composite
def _magnitude(draw: st.DrawFn, part: str, value: float) -> str:
    """``value`` (its absolute value) with a unit as models write it."""
    number = draw(st.sampled_from(_number(abs(value))))
    if part == "yaw":
        return draw(
            st.sampled_from(
                [f"{number} deg", f"{number}°", f"{number} degrees", f"{number}deg", number]
            )
        )
    units = [f"{number} m", f"{number}m", f"{number} meters", f"{number} metres"]
    cm = round(abs(value) * 100)
    if cm / 100 == abs(value):  # 20 cm is exactly 0.2 m; 12.345 cm would not be
        units.append(f"{cm} cm")
    return draw(st.sampled_from(units))


@st.composite
def worded(draw: st.DrawFn, action: Action) -> str:
    """``action`` written as a model might: its non-zero parts in any order, each in one
    of several wordings, joined by any separator, in any case; "hold" when all are 0."""
    parts = {part: getattr(action, attr) for part, attr in _PARTS.items()}
    moves = [(part, value) for part, value in parts.items() if value != 0]
    if not moves:
        return draw(st.sampled_from(_HOLDS))
    moves = draw(st.permutations(moves))
    if draw(st.integers(0, 5)) == 0:  # df=0.5, dpsi=-15: signed keys, as in SPEC section 4
        key = st.sampled_from([": ", "=", " = "])
        clauses = [
            f"{draw(st.sampled_from([_SIGNED_KEYS[p], _SIGNED_KEYS[p].replace('d', 'd_', 1)]))}"
            f"{draw(key)}{repr(v).removesuffix('.0')}"
            for p, v in moves
        ]
    else:
        clauses = [
            draw(st.sampled_from(_WORDINGS[p][0 if v > 0 else 1])).format(draw(_magnitude(p, v)))
            for p, v in moves
        ]
    text = draw(st.sampled_from(_SEPARATORS)).join(clauses)
    case = draw(st.sampled_from([str, str.capitalize, str.upper, str.title]))
    return case(text) + draw(st.sampled_from(["", ".", "!"]))


worded_actions = valid_actions.flatmap(lambda a: st.tuples(st.just(a), worded(a)))


@given(worded_actions)
def test_an_admissible_action_in_any_wording_parses_to_exactly_that_action(
    built: tuple[Action, str],
) -> None:
    action, text = built
    # Signs and magnitudes both: left/right, up/down, back, a left turn positive.
    assert parse_action(text) == action, text


@given(valid_actions)
def test_every_valid_action_formats_and_parses_back_to_itself(action: Action) -> None:
    assert parse_action(format_action(action)) == action


# How far a near miss lies from an admissible magnitude: a loosened check lets it through.
_by = st.one_of(st.sampled_from([1e-6, 1e-4, 1e-3, 0.01]), st.floats(1e-6, 0.05))


def _off_the_set(allowed: tuple[float, ...], top: float) -> st.SearchStrategy[float]:
    """Magnitudes a model might write that are not in ``allowed``: near misses (0.49,
    0.51), values between the steps, and any float up to ``top``."""
    near = st.sampled_from([a for a in allowed if a]).flatmap(
        lambda a: _by.flatmap(lambda d: st.sampled_from([a - d, a + d]))
    )
    return st.one_of(near, st.floats(0.001, top)).filter(
        lambda v: all(abs(v - a) > 1e-7 for a in allowed)
    )


def _off_the_range(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Non-zero magnitudes outside [lo, hi]: just short of ``lo`` or just past ``hi``, and
    farther out."""
    near = _by.flatmap(lambda d: st.sampled_from([lo - d, hi + d]))
    return st.one_of(near, st.floats(0.001, lo - 1e-6), st.floats(hi + 1e-6, 10.0))


_inadmissible_part = st.one_of(
    st.tuples(st.just("forward"), _off_the_set(DEFAULT_SPACE.forward_m, 3.0)),
    st.tuples(st.just("right"), _off_the_set(DEFAULT_SPACE.lateral_m, 3.0)),
    st.tuples(st.just("yaw"), _off_the_set(DEFAULT_SPACE.yaw_deg, 360.0)),
    st.tuples(st.just("up"), _off_the_range(*DEFAULT_SPACE.vertical_range_m)),
)


@st.composite
def inadmissible_actions(draw: st.DrawFn) -> tuple[str, str]:
    """(part name in the refusal, text): an admissible action with one part replaced by a
    magnitude outside its set, worded as models write."""
    part, magnitude = draw(_inadmissible_part)
    attr = _PARTS[part]
    action = replace(draw(valid_actions), **{attr: magnitude * draw(signs)})
    return _REFUSED_AS[part], draw(worded(action))


@given(inadmissible_actions())
@example(("vertical", "descend 0.0999 m"))  # the ends of [0.1, 2] m, whichever the draw
@example(("vertical", "ascend 2.001 m"))
def test_a_magnitude_outside_the_admissible_set_is_refused_naming_the_part(
    built: tuple[str, str],
) -> None:
    name, text = built
    with pytest.raises(ActionError, match=rf"^{name} \S+ (m|deg) is not admissible"):
        parse_action(text)


# Text that reads like an action, near misses included: motions, magnitudes in and out of
# the admissible sets, units right and wrong, several separators.
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


_admissible_text = worded_actions.map(lambda built: built[1])
_near_misses = st.one_of(
    inadmissible_actions().map(lambda built: built[1]), action_like, st.text(max_size=200)
)


# Three in four inputs are admissible actions as models word them, so that most are
# accepted (measured: 60-88% in eight runs) and the checks below run; the rest probe
# the refusals.
@given(
    st.sampled_from([_admissible_text, _admissible_text, _admissible_text, _near_misses]).flatmap(
        lambda s: s
    )
)
def test_whatever_the_parser_accepts_is_admissible_canonical_and_written_in_the_text(
    text: str,
) -> None:
    try:
        action = parse_action(text)
    except ActionError:
        event("refused")
        return  # refused with a reason: fine
    event("accepted")
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


# ----------------------------------------------------- wordings the parser must read
# Each row is a way a model writes a motion that the grammar accepts, with the action it
# must mean: symbols for degrees, spelled-out units on signed keys, markup around a key.


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("30° left", Action(yaw_deg=30)),  # the degree sign alone makes it a turn
        ("15º right", Action(yaw_deg=-15)),  # the masculine ordinal, often typed for °
        ("15 degrees to the left", Action(yaw_deg=15)),
        ("dyaw = 15", Action(yaw_deg=15)),
        ("dpsi = 15 degrees", Action(yaw_deg=15)),
        ("df = 0.5 meters", Action(forward=0.5)),
        ("df=0.5m", Action(forward=0.5)),
        ("`df = 0.5`, (dpsi = -15)", Action(forward=0.5, yaw_deg=-15)),
        ("... df = 0.5", Action(forward=0.5)),  # a leading ellipsis is no decimal point
        ("shift left 20 centimetres", Action(right=-0.2)),
        ("strafe right 0.5", Action(right=0.5)),  # "strafe" says lateral without a unit
        ("turn left 30 deg, forward 1 m", Action(forward=1.0, yaw_deg=30)),
    ],
)
def test_more_wordings_parse(text: str, expected: Action) -> None:
    assert parse_action(text) == expected


def test_a_reply_padded_with_whitespace_is_measured_by_its_words() -> None:
    # Models pad with newlines and indentation; 300 characters of layout are not a long
    # action.
    assert parse_action("forward 0.5 m,\n" + " " * 300 + "\tturn left 15 deg") == Action(
        forward=0.5, yaw_deg=15
    )


def test_an_action_of_300_characters_is_read_and_one_of_301_is_too_long() -> None:
    at_limit = "forward 0.5 m an" + " a" * 142  # filler words, 300 characters in all
    assert len(at_limit) == 300
    assert parse_action(at_limit) == Action(forward=0.5)
    with pytest.raises(ActionError) as refused:
        parse_action(at_limit + "a")
    assert str(refused.value) == ("the action string is too long; give only motions and magnitudes")


def test_a_signed_zero_is_no_motion_not_a_negative_zero() -> None:
    # Records and prompts print the action: "-0.0" would read as a direction.
    action = parse_action("df=-0, dpsi=-0.0")
    assert action == Action()
    assert [math.copysign(1.0, v) for v in astuple(action)] == [1.0] * 4


# ------------------------------------------------------- what the model is told back
# The ActionError's message is shown to the model in the re-query, so its wording is the
# parser's interface: each names the clause as read and the fix.


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (42, "the action must be a string, got int"),
        (" . ", "the action string is empty; name at least one motion or 'hold'"),
        (
            "forward 1 m, forward 0.5 m",
            "the action names the forward component twice ('forward 1 m, forward 0.5 m'); "
            "give each of forward, lateral, vertical and yaw at most once",
        ),
        ("turn left 0.5 radians", "'turn left 0.5 radians': give yaw in degrees, not radians"),
        ("turn left 1 radian", "'turn left 1 radian': give yaw in degrees, not radians"),
        (
            "forward 0.5 m 1",
            "'forward 0.5 m 1' has 2 numbers; give one magnitude per motion",
        ),
        (
            "forward -0.5 m",
            "'forward -0.5 m': give a magnitude with a direction word (e.g. 'descend 0.5 m'), "
            "not a signed number",
        ),
        ("fly to the moon 5", "'fly to the moon 5': cannot read 'fly moon'"),
        ("forward 15 deg", "'forward 15 deg': degrees only make sense for a turn"),
        ("back 15 deg", "'back 15 deg': degrees only make sense for a turn"),
        ("ascend 15 deg", "'ascend 15 deg': degrees only make sense for a turn"),
        ("descend 15 deg", "'descend 15 deg': degrees only make sense for a turn"),
        ("turn left 0.5 m", "'turn left 0.5 m': a turn is measured in degrees, not metres"),
        ("turn left 20 cm", "'turn left 20 cm': a turn is measured in degrees, not metres"),
        ("turn 15 deg", "'turn 15 deg' gives no turn direction"),
        ("turn left right 15 deg", "'turn left right 15 deg' names two opposite turn directions"),
        ("up down 0.5 m", "'up down 0.5 m' names two opposite vertical directions"),
        (
            "forward back 0.5 m",
            "'forward back 0.5 m' names two opposite forward/back directions",
        ),
        (
            "strafe left right 0.2 m",
            "'strafe left right 0.2 m' names two opposite lateral directions",
        ),
        (
            "strafe 0.2 m",
            "'strafe 0.2 m' names no motion (forward, strafe, ascend, turn, hold)",
        ),
    ],
)
def test_a_refusal_tells_the_model_what_to_fix(text: str, message: str) -> None:
    with pytest.raises(ActionError) as refused:
        parse_action(text)  # type: ignore[arg-type]
    assert str(refused.value) == message


@pytest.mark.parametrize(
    "text",
    [
        "ascend forward 0.5 m",
        "descend back 0.5 m",
        "forward strafe left 0.2 m",
        "back right 0.2 m",
        "up strafe 0.2 m",
    ],
)
def test_one_clause_with_two_motions_is_refused_not_read_as_either(text: str) -> None:
    with pytest.raises(ActionError) as refused:
        parse_action(text)
    assert str(refused.value) == f"'{text}' mixes several motions; separate them with commas"


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (
            Action(forward=0.3),
            "forward 0.3 m is not admissible: the magnitude must be one of 0, 0.1, 0.2, 0.5, 1 m",
        ),
        (
            Action(yaw_deg=-12),
            "yaw 12 deg is not admissible: the magnitude must be one of "
            "0, 5, 10, 15, 20, 30, 45, 90, 180 deg",
        ),
        (
            Action(up=-2.5),
            "vertical 2.5 m is not admissible: |dz| must be 0 or lie in [0.1, 2] m",
        ),
        (
            Action(right="0.5"),  # type: ignore[arg-type]
            "lateral '0.5' is not a number of metres: an Action holds four real numbers "
            "within a float's range",
        ),
        (
            Action(yaw_deg=None),  # type: ignore[arg-type]
            "yaw None is not a number of degrees: an Action holds four real numbers "
            "within a float's range",
        ),
    ],
)
def test_validate_names_the_part_and_what_is_admissible(action: Action, message: str) -> None:
    with pytest.raises(ActionError) as refused:
        DEFAULT_SPACE.validate(action)
    assert str(refused.value) == message
    assert not DEFAULT_SPACE.is_valid(action)


# ------------------------------------------------------------- the canonical wording


@pytest.mark.parametrize(
    ("action", "text"),
    [
        (Action(), "hold"),
        (
            Action(forward=0.5, right=0.2, up=0.3, yaw_deg=15),
            "forward 0.5 m, strafe right 0.2 m, ascend 0.3 m, turn left 15 deg",
        ),
        (
            Action(forward=-1.0, right=-0.1, up=-2.0, yaw_deg=-90),
            "back 1 m, strafe left 0.1 m, descend 2 m, turn right 90 deg",
        ),
    ],
)
def test_format_action_writes_the_canonical_lowercase_form(action: Action, text: str) -> None:
    assert format_action(action) == text


def test_a_space_with_fine_turns_formats_and_parses_them_back() -> None:
    fine = replace(DEFAULT_SPACE, yaw_deg=(0.0, 0.5, 1.0, 2.0))
    for yaw in (0.5, 1.0, -0.5, -1.0):
        action = Action(yaw_deg=yaw)
        assert format_action(action) == f"turn {'left' if yaw > 0 else 'right'} {abs(yaw):g} deg"
        assert parse_action(format_action(action), fine) == action


def test_twist_over_one_second_by_default_is_the_action_itself() -> None:
    assert to_twist(Action(forward=0.5, right=0.2, up=-0.3, yaw_deg=180.0)) == pytest.approx(
        (0.5, -0.2, -0.3, math.pi)
    )


@pytest.mark.parametrize("dt", [0.0, -1.0])
def test_twist_refuses_a_step_that_is_not_positive(dt: float) -> None:
    with pytest.raises(ValueError, match=f"^dt must be positive, got {dt}$"):
        to_twist(Action(forward=0.5), dt=dt)

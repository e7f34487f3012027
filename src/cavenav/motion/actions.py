"""The action language of SPEC section 4: parse, validate, format, and map to a twist.

An action string names movement types with magnitudes, e.g.
``"forward 0.5 m, strafe right 0.2 m, ascend 0.3 m, turn left 15 deg"``; one string fixes
all four components of ``a = (df, dr, dz, dpsi)``, and components it does not mention are 0.
``"hold"`` is the zero action. The parser accepts the wording real models use (word order,
case, units spelled out, synonyms) and rejects, with a reason a model can act on, anything
ambiguous or outside the admissible magnitudes: it never rounds 0.3 m to a set value.
"""

from __future__ import annotations

import math
import numbers
import re
import reprlib
from dataclasses import dataclass

import numpy as np

from cavenav.core.errors import ActionError
from cavenav.core.types import Action

__all__ = [
    "TWIST_KEYS",
    "ActionSpace",
    "DEFAULT_SPACE",
    "action_bounds",
    "format_action",
    "parse_action",
    "snap_action",
    "to_twist",
]

_EPS = 1e-9


@dataclass(frozen=True)
class ActionSpace:
    """The admissible magnitudes (SPEC section 4); the prompt and the parser share them.

    Attributes:
        forward_m: admissible |df|, metres.
        lateral_m: admissible |dr|, metres.
        yaw_deg: admissible |dpsi|, degrees.
        vertical_range_m: |dz| is continuous in this closed interval, or exactly 0.
    """

    forward_m: tuple[float, ...] = (0.0, 0.1, 0.2, 0.5, 1.0)
    lateral_m: tuple[float, ...] = (0.0, 0.1, 0.2, 0.5, 1.0)
    yaw_deg: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 90.0, 180.0)
    vertical_range_m: tuple[float, float] = (0.1, 2.0)

    def validate(self, action: Action) -> Action:
        """``action`` with its four parts as floats, or an ActionError naming the offending
        value: a part that is no real number (text, None, a bool, an int beyond a float's
        range) or a magnitude outside the admissible sets."""
        action = Action(
            forward=_real("forward", action.forward, "m"),
            right=_real("lateral", action.right, "m"),
            up=_real("vertical", action.up, "m"),
            yaw_deg=_real("yaw", action.yaw_deg, "deg"),
        )
        _check_in_set("forward", action.forward, self.forward_m, "m")
        _check_in_set("lateral", action.right, self.lateral_m, "m")
        _check_in_set("yaw", action.yaw_deg, self.yaw_deg, "deg")
        lo, hi = self.vertical_range_m
        dz = abs(action.up)
        if not math.isfinite(action.up) or (dz > _EPS and not lo - _EPS <= dz <= hi + _EPS):
            raise ActionError(
                f"vertical {_num(dz)} m is not admissible: |dz| must be 0 or lie in "
                f"[{_num(lo)}, {_num(hi)}] m"
            )
        return action

    def is_valid(self, action: Action) -> bool:
        try:
            self.validate(action)
        except ActionError:
            return False
        return True


DEFAULT_SPACE = ActionSpace()


def _real(name: str, value: object, unit: str) -> float:
    """``value`` as a float if it is a real number; a bool is a flag, not a magnitude,
    though ``True == 1``."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        try:
            return float(value)
        except (TypeError, ValueError, OverflowError):  # 10**400, a Real that refuses
            pass
    words = {"m": "metres", "deg": "degrees"}[unit]
    raise ActionError(
        f"{name} {reprlib.repr(value)} is not a number of {words}: an Action holds four "
        "real numbers within a float's range"
    )


def _check_in_set(name: str, value: float, allowed: tuple[float, ...], unit: str) -> None:
    if math.isfinite(value) and any(abs(abs(value) - a) < _EPS for a in allowed):
        return
    choices = ", ".join(_num(a) for a in allowed)
    raise ActionError(
        f"{name} {_num(abs(value))} {unit} is not admissible: "
        f"the magnitude must be one of {choices} {unit}"
    )


def _num(value: float) -> str:
    """Shortest text that reads back to the same float: 0.5 -> '0.5', 1.0 -> '1'."""
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def format_action(action: Action) -> str:
    """Canonical action string; ``parse_action(format_action(a)) == a`` for valid ``a``."""
    parts = []
    if action.forward:
        word = "forward" if action.forward > 0 else "back"
        parts.append(f"{word} {_num(abs(action.forward))} m")
    if action.right:
        word = "right" if action.right > 0 else "left"
        parts.append(f"strafe {word} {_num(abs(action.right))} m")
    if action.up:
        word = "ascend" if action.up > 0 else "descend"
        parts.append(f"{word} {_num(abs(action.up))} m")
    if action.yaw_deg:
        word = "left" if action.yaw_deg > 0 else "right"
        parts.append(f"turn {word} {_num(abs(action.yaw_deg))} deg")
    return ", ".join(parts) if parts else "hold"


TWIST_KEYS = ("linear_x", "linear_y", "linear_z", "angular_z")  # `to_twist`'s, in order


def to_twist(action: Action, dt: float = 1.0) -> tuple[float, float, float, float]:
    """The command as a ROS Twist would carry it over a step of ``dt`` seconds.

    ROS body frame (REP 103): x forward, y left, z up, angular z counter-clockwise, so a
    rightward ``dr`` becomes a negative ``linear_y`` and a left turn a positive
    ``angular_z`` in rad/s.

    Returns:
        (linear_x, linear_y, linear_z, angular_z)
    """
    if dt <= 0:
        raise ValueError(f"dt must be positive, got {dt}")
    return (
        action.forward / dt,
        -action.right / dt,
        action.up / dt,
        math.radians(action.yaw_deg) / dt,
    )


# ---------------------------------------------------------------------------- parsing

_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"
_CLAUSE_SPLIT = re.compile(r"\s*(?:,|;|\+|&|\band\b|\bthen\b|\bwith\b|\bwhile\b)\s*")

_YAW_WORDS = ("turn", "yaw", "rotate", "rotation", "heading", "pivot", "spin")
_UP_WORDS = ("ascend", "up", "rise", "climb", "raise", "upward", "upwards")
_DOWN_WORDS = ("descend", "down", "sink", "dive", "lower", "downward", "downwards", "drop")
_FORWARD_WORDS = ("forward", "forwards", "ahead", "advance", "fwd", "surge", "straight")
_BACK_WORDS = ("back", "backward", "backwards", "reverse", "astern", "retreat")
_LEFT_WORDS = ("left", "port", "ccw", "counterclockwise", "anticlockwise")
_RIGHT_WORDS = ("right", "starboard", "cw", "clockwise")
_LATERAL_WORDS = ("strafe", "shift", "slide", "lateral", "laterally", "sideways", "sway")
_HOLD_WORDS = ("hold", "stop", "stay", "hover", "wait", "halt", "none", "idle")
_FILLER = {
    "move",
    "go",
    "by",
    "of",
    "the",
    "a",
    "an",
    "to",
    "m",
    "deg",
    "cm",
    "position",
    "slightly",
    "slowly",
    "gently",
    "small",
    "short",
    "step",
    "vehicle",
    "rov",
    "and",
    "degrees",
    "at",
    "for",
    "toward",
    "towards",
    "on",
    "in",
    "place",
    "ly",
    "motion",
}

_SIGNED_KEY = re.compile(
    rf"^(df|dr|dz|dpsi|dyaw|d_psi|d_f|d_r|d_z)\s*[=:]\s*({_NUMBER})\s*(m|deg)?$"
)


def _normalise(text: str) -> str:
    text = text.strip().lower()
    text = text.replace("°", " deg ").replace("º", " deg ")
    text = re.sub(r"counter[- ]clockwise|anti[- ]clockwise", "ccw", text)
    text = re.sub(r"\b(degrees?|degs?)\b", "deg", text)
    text = re.sub(r"\b(meters?|metres?|mtrs?)\b", "m", text)
    text = re.sub(r"\b(centimeters?|centimetres?)\b", "cm", text)
    # "0.5m" -> "0.5 m", "15deg" -> "15 deg"
    text = re.sub(rf"({_NUMBER})(m|cm|deg|rad)\b", r"\1 \2", text)
    # The signed keys d_f, d_r, d_z, d_psi keep their underscore; elsewhere it is emphasis.
    text = re.sub(r"\bd_(f|r|z|psi)\b", r"d\1", text)
    text = re.sub(r"[\"'`*_()\[\]{}]", " ", text)
    text = re.sub(r"\s+", " ", text)
    # A full stop ends a sentence, but one that opens the text may be a decimal point:
    # ".1 m ahead" is 0.1 m, not 1 m.
    return re.sub(r"^[ .!]+(?!\d)", "", text.rstrip(" .!"))


def _words(clause: str) -> set[str]:
    return set(re.findall(r"[a-z]+", clause))


def parse_action(text: object, space: ActionSpace = DEFAULT_SPACE) -> Action:
    """Parse an action string into an admissible Action.

    Args:
        text: e.g. ``"Turn right 30°, move forward 0.2 meters"`` or ``"hold"``.
        space: admissible magnitudes to check against.

    Raises:
        ActionError: with a reason that can be shown to a model, when the text is empty,
            ambiguous, names one component twice, or uses an inadmissible magnitude.
    """
    if not isinstance(text, str):
        raise ActionError(f"the action must be a string, got {type(text).__name__}")
    norm = _normalise(text)
    if not norm:
        raise ActionError("the action string is empty; name at least one motion or 'hold'")
    if len(norm) > 300:
        raise ActionError("the action string is too long; give only motions and magnitudes")
    components: dict[str, float] = {}
    held = False
    for clause in filter(None, _CLAUSE_SPLIT.split(norm)):
        kind, value = _parse_clause(clause)
        if kind == "hold":
            held = True
            continue
        if kind in components:
            raise ActionError(
                f"the action names the {_KIND_NAMES[kind]} component twice ('{text.strip()}'); "
                "give each of forward, lateral, vertical and yaw at most once"
            )
        components[kind] = value
    if held and any(v != 0 for v in components.values()):
        raise ActionError(f"'{text.strip()}' both holds and moves; choose one")
    action = Action(
        forward=components.get("forward", 0.0),
        right=components.get("right", 0.0),
        up=components.get("up", 0.0),
        yaw_deg=components.get("yaw", 0.0),
    )
    return space.validate(action)


_KIND_NAMES = {"forward": "forward", "right": "lateral", "up": "vertical", "yaw": "yaw"}


def _parse_clause(clause: str) -> tuple[str, float]:
    signed = _SIGNED_KEY.match(clause)
    if signed:
        key, number = signed.group(1).replace("_", ""), float(signed.group(2))
        kind = {"df": "forward", "dr": "right", "dz": "up", "dpsi": "yaw", "dyaw": "yaw"}[key]
        return kind, number + 0.0  # + 0.0 turns -0.0 into 0.0

    words = _words(clause)
    numbers = re.findall(_NUMBER, clause)
    if words & set(_HOLD_WORDS) and not numbers:
        return "hold", 0.0
    if "rad" in words or "radians" in words or "radian" in words:
        raise ActionError(f"'{clause}': give yaw in degrees, not radians")
    magnitude = _magnitude(clause, words, numbers)
    _check_words(clause, words)
    return _motion(clause, words, magnitude)


def _magnitude(clause: str, words: set[str], numbers: list[str]) -> float:
    """The clause's one unsigned number, in metres or degrees."""
    if not numbers:
        raise ActionError(f"'{clause}' has no magnitude; write e.g. 'forward 0.5 m'")
    if len(numbers) > 1:
        raise ActionError(f"'{clause}' has {len(numbers)} numbers; give one magnitude per motion")
    if numbers[0].startswith(("-", "+")):
        raise ActionError(
            f"'{clause}': give a magnitude with a direction word (e.g. 'descend 0.5 m'), "
            "not a signed number"
        )
    magnitude = float(numbers[0])
    if not math.isfinite(magnitude):
        raise ActionError(f"'{clause}': magnitude is not a finite number")
    return magnitude / 100.0 if "cm" in words else magnitude


def _check_words(clause: str, words: set[str]) -> None:
    """Refuse degrees on a translation, and any word the grammar does not know."""
    translation = set(_FORWARD_WORDS) | set(_BACK_WORDS) | set(_UP_WORDS) | set(_DOWN_WORDS)
    if "deg" in words and not words & set(_YAW_WORDS) and words & translation:
        raise ActionError(f"'{clause}': degrees only make sense for a turn")
    leftover = words - _FILLER - set(_YAW_WORDS) - set(_UP_WORDS) - set(_DOWN_WORDS)
    leftover -= set(_FORWARD_WORDS) | set(_BACK_WORDS) | set(_LEFT_WORDS) | set(_RIGHT_WORDS)
    leftover -= set(_LATERAL_WORDS)
    if leftover:
        raise ActionError(f"'{clause}': cannot read '{' '.join(sorted(leftover))}'")


def _sign(clause: str, positive: set[str], negative: set[str], what: str) -> float:
    """+1 or -1 from the direction words of one axis; exactly one side must be named."""
    if positive and negative:
        raise ActionError(f"'{clause}' names two opposite {what} directions")
    if not positive and not negative:
        raise ActionError(f"'{clause}' gives no {what} direction")
    return 1.0 if positive else -1.0


def _motion(clause: str, words: set[str], magnitude: float) -> tuple[str, float]:
    """The component a checked clause moves along, and its signed magnitude."""
    left, right = words & set(_LEFT_WORDS), words & set(_RIGHT_WORDS)
    up, down = words & set(_UP_WORDS), words & set(_DOWN_WORDS)
    ahead, back = words & set(_FORWARD_WORDS), words & set(_BACK_WORDS)
    is_lateral = bool(words & set(_LATERAL_WORDS))
    in_metres = "m" in words or "cm" in words
    if words & set(_YAW_WORDS) or "deg" in words:
        if in_metres:
            raise ActionError(f"'{clause}': a turn is measured in degrees, not metres")
        return "yaw", _sign(clause, left, right, "turn") * magnitude
    kinds = [bool(up or down), bool(ahead or back), bool(left or right or is_lateral)]
    if sum(kinds) > 1:
        raise ActionError(f"'{clause}' mixes several motions; separate them with commas")
    if up or down:
        return "up", _sign(clause, up, down, "vertical") * magnitude
    if ahead or back:
        return "forward", _sign(clause, ahead, back, "forward/back") * magnitude
    if left or right:
        if not is_lateral and not in_metres:
            raise ActionError(
                f"'{clause}' is ambiguous: write 'turn {next(iter(left or right))} N deg' "
                f"or 'strafe {next(iter(left or right))} N m'"
            )
        return "right", _sign(clause, right, left, "lateral") * magnitude
    raise ActionError(f"'{clause}' names no motion (forward, strafe, ascend, turn, hold)")


def action_bounds(space: ActionSpace = DEFAULT_SPACE) -> np.ndarray:
    """The largest move of each component of an action vector (df, dr, dz, dpsi in
    degrees), float32: a vector action space is the box from minus these to these."""
    return np.array(
        [max(space.forward_m), max(space.lateral_m), space.vertical_range_m[1], max(space.yaw_deg)],
        np.float32,
    )


def snap_action(vector: object, space: ActionSpace = DEFAULT_SPACE) -> Action:
    """The admissible action nearest ``vector`` = (df, dr, dz, dpsi in degrees).

    df, dr and dpsi go to the nearest signed value of their sets. dz is continuous but
    not near zero: a magnitude below half the smallest vertical move (0.05 m by default)
    becomes 0, any other is clipped to the vertical range (0.1-2.0 m) and rounded to
    the centimetre.

    Raises:
        ActionError: ``vector`` is not 4 finite real numbers of shape (4,), whatever it is
            instead (text, a dict, another shape, NaN, ...).
    """
    v = _four_numbers(vector)

    def nearest(value: float, magnitudes: tuple[float, ...]) -> float:
        # Clipped first: beyond 1e17 the distances to every candidate round to one float.
        value = min(max(value, -max(magnitudes)), max(magnitudes))
        signed = [s * m for m in magnitudes for s in (1.0, -1.0)]
        return float(min(signed, key=lambda c: (abs(c - value), abs(c)))) + 0.0

    lo, hi = space.vertical_range_m
    dz = 0.0 if abs(v[2]) < lo / 2 else math.copysign(round(min(max(abs(v[2]), lo), hi), 2), v[2])
    return Action(
        forward=nearest(v[0], space.forward_m),
        right=nearest(v[1], space.lateral_m),
        up=dz,
        yaw_deg=nearest(v[3], space.yaw_deg),
    )


# What an array holds when it holds no real numbers, by numpy's dtype kind.
_NOT_NUMBERS = {"U": "text", "S": "bytes", "c": "complex numbers", "O": "objects", "M": "dates"}


def _four_numbers(vector: object) -> np.ndarray:
    """``vector`` as a (4,) float64 array of finite numbers, or an ActionError saying what
    it is instead: a policy's output can be anything, and the step must say why it held."""

    def refused(what: str = "") -> ActionError:  # printed only to refuse: a step is cheap
        shown = reprlib.repr(vector)
        return ActionError(
            f"an action vector is 4 finite numbers (df, dr, dz, dpsi), got {what}{shown}"
        )

    try:
        array = np.asarray(vector)
    except (TypeError, ValueError):  # ragged nesting, an __array__ that refuses
        raise refused() from None
    if array.shape != (4,):
        raise refused(f"shape {array.shape}: ")
    if array.dtype == object and all(isinstance(x, numbers.Real) for x in array):
        try:  # Python numbers of mixed types; an int beyond float's range overflows
            array = array.astype(np.float64)
        except OverflowError:
            raise refused() from None
    if array.dtype.kind not in "biuf":  # booleans, integers or floats
        raise refused(f"{_NOT_NUMBERS.get(array.dtype.kind, str(array.dtype))}: ")
    v = array.astype(np.float64)
    if not np.isfinite(v).all():
        raise refused()
    return v

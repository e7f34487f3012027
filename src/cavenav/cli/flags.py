"""What the command line's options share: their enums, their checks, and `Group`, which
builds one value (`VLMOptions`, `EpisodeConfig`, ...) from the options of a command.

Each option is declared once, as a typer ``Annotated`` type in the module of its group
(`cavenav.cli.episode_flags`, `cavenav.cli.vehicle_flags`); a command lists the options it
takes in its own signature, with the defaults of the value they build, and hands its
arguments to the group: ``settings = SETTINGS.value(locals())``.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import typer

from cavenav.sensors.depth import EXR_COMPRESSIONS
from cavenav.sensors.optics import WATER_TYPES
from cavenav.world.guideline import GUIDELINE_COLOURS

__all__ = [
    "Backend",
    "ExrCompression",
    "Group",
    "LineColour",
    "Sounder",
    "WaterType",
    "bounded",
    "finite",
    "ranged",
]


class DepthSource(StrEnum):
    """What makes the depth image (see `cavenav.sensors.config.SensorConfig`)."""

    exact = "exact"
    stereo = "stereo"
    none = "none"


class SonarKind(StrEnum):
    """Imaging sonars (see `cavenav.sensors.sonar`)."""

    ping360 = "ping360"
    multibeam = "multibeam"
    none = "none"


class Sounder(StrEnum):
    """Echo-sounder models (see `cavenav.sensors.rig.SensorConfig`)."""

    camera = "camera"
    beam = "beam"


# Depth EXR compressions, all lossless (measured in `cavenav.sensors.depth`).
ExrCompression = StrEnum("ExrCompression", {name: name for name in EXR_COMPRESSIONS})  # type: ignore[misc]


class Backend(StrEnum):
    """Where the VLM pilot's model runs (`cavenav.pilots.backends`)."""

    openai = "openai"
    transformers = "transformers"


# The guideline's colours, named as `cavenav.world.guideline.GUIDELINE_COLOURS` names them.
LineColour = StrEnum("LineColour", {name: name for name in GUIDELINE_COLOURS})  # type: ignore[misc]

# Water presets, named as `cavenav.sensors.optics.WATER_TYPES` names them.
WaterType = StrEnum("WaterType", {name: name for name in WATER_TYPES})  # type: ignore[misc]


def finite(value: float | None) -> float | None:
    """A range's bounds let infinity through: refuse it (and NaN) by name."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"{value} is not finite; give a number")
    return value


@dataclass(frozen=True)
class Group:
    """The options that make one value: ``build`` is called with each option a command
    took, by name, enums and paths given as plain strings (JSON-able for sweep.json and
    run folders); an option the command does not take keeps the value's default.

    Raises:
        TypeError: a name that ``build`` does not take (a renamed field, a typo).
    """

    names: tuple[str, ...]
    build: Callable[..., Any]

    def __post_init__(self) -> None:
        takes_names = inspect.signature(self.build).parameters
        unknown = [name for name in self.names if name not in takes_names]
        if unknown:
            raise TypeError(f"{self.build.__name__} takes no option {', '.join(unknown)}")

    def value(self, given: Mapping[str, Any]) -> Any:
        """The value from a command's arguments (its ``locals()``)."""
        return self.build(**{n: _plain(given[n]) for n in self.names if n in given})


def _plain(value: Any) -> Any:
    """A flag's value as JSON keeps it: an enum by its value, a path as text."""
    if isinstance(value, StrEnum):
        return value.value
    return str(value) if isinstance(value, Path) else value


def _span(low: float | None, high: float | None) -> str:
    if low is not None and high is not None:
        return f"from {low:g} to {high:g}"
    return f"of {low:g} or more" if low is not None else f"of {high:g} or less"


def bounded(
    low: float | None, high: float | None, then: Callable[[Any], Any] | None = None
) -> Callable[[float | None], float | None]:
    """A callback that holds a float option within [low, high], naming NaN and infinity
    as what they are (typer's own range check calls NaN "not <= 1"); ``then`` runs after."""
    span = _span(low, high)

    def check(value: float | None) -> float | None:
        if value is not None:
            if not math.isfinite(value):
                raise typer.BadParameter(f"{value} is not a finite number; give one {span}")
            if (low is not None and value < low) or (high is not None and value > high):
                raise typer.BadParameter(f"{value}: give a number {span}")
        return then(value) if then else value

    return check


def ranged(text: str, low: float | None, high: float | None) -> str:
    """A float option's help ``text``, saying the range `bounded` holds it to."""
    return f"{text}; a number {_span(low, high)}"

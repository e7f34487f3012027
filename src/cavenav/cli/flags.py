"""The command line's shared options, each declared once: its flag, type, help and default.

A command names the value it wants (``vlm: VLMOptions``, ``settings: EpisodeConfig``)
and `takes` puts the options of that group into its signature in that value's place, so
typer shows them, then builds the value from what was given. A group's defaults are its
value's defaults (`VLMOptions`, `EpisodeConfig`); a flag the value does not take is an
error when the command is declared, not an option silently dropped.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer

from cavenav.sensors.depth import EXR_COMPRESSIONS
from cavenav.sensors.optics import WATER_TYPES

__all__ = [
    "Backend",
    "ExrCompression",
    "Flag",
    "OptionGroup",
    "Sounder",
    "WaterType",
    "bounded",
    "finite",
    "flag",
    "takes",
]

Command = TypeVar("Command", bound=Callable[..., Any])


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


# Water presets, named as `cavenav.sensors.optics.WATER_TYPES` names them.
WaterType = StrEnum("WaterType", {name: name for name in WATER_TYPES})  # type: ignore[misc]


def finite(value: float | None) -> float | None:
    """A range's bounds let infinity through: refuse it (and NaN) by name."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"{value} is not finite; give a number")
    return value


@dataclass(frozen=True)
class Flag:
    """One option: its parameter name (the flag, with dashes), type with help, default."""

    name: str
    kind: Any  # Annotated[type, typer.Option(...)]
    default: Any = None


@dataclass(frozen=True)
class OptionGroup:
    """Options that make one value: ``build`` is called with each flag by name, enums
    and paths given as plain strings (JSON-able for sweep.json and run folders).

    Raises:
        TypeError: a flag that ``build`` does not take (a renamed field, a typo).
    """

    flags: tuple[Flag, ...]
    build: Callable[..., Any]

    def __post_init__(self) -> None:
        takes_names = inspect.signature(self.build).parameters
        unknown = [flag.name for flag in self.flags if flag.name not in takes_names]
        if unknown:
            raise TypeError(f"{self.build.__name__} takes no option {', '.join(unknown)}")

    def only(self, *names: str) -> OptionGroup:
        """The group with just ``names``, in the group's order; the others keep the
        value's defaults (a command that shows fewer options)."""
        kept = self._known(names)
        return replace(self, flags=tuple(f for f in self.flags if f.name in kept))

    def without(self, *names: str) -> OptionGroup:
        """The group less ``names``: those keep the value's defaults."""
        gone = self._known(names)
        return replace(self, flags=tuple(f for f in self.flags if f.name not in gone))

    def _known(self, names: tuple[str, ...]) -> set[str]:
        unknown = set(names) - {flag.name for flag in self.flags}
        if unknown:
            raise TypeError(f"no option {', '.join(sorted(unknown))} for {self.build.__name__}")
        return set(names)

    def value(self, given: dict[str, Any]) -> Any:
        """Build the value from the command's arguments, taking this group's out of it."""
        return self.build(**{flag.name: _plain(given.pop(flag.name)) for flag in self.flags})


def _plain(value: Any) -> Any:
    """A flag's value as JSON keeps it: an enum by its value, a path as text."""
    if isinstance(value, StrEnum):
        return value.value
    return str(value) if isinstance(value, Path) else value


def takes(**groups: OptionGroup) -> Callable[[Command], Command]:
    """Put each group's options into the command's signature in place of the parameter
    of that name, and call the command with the group's value there.

    Example::

        @app.command()
        @takes(vlm=VLM)
        def ask(image: ..., vlm: VLMOptions = VLMOptions()) -> None: ...
    """

    def decorate(command: Command) -> Command:
        signature = inspect.signature(command, eval_str=True)
        missing = set(groups) - set(signature.parameters)
        if missing:
            raise TypeError(f"{command.__name__} has no parameter {', '.join(sorted(missing))}")
        names = [f.name for group in groups.values() for f in group.flags]
        twice = set(signature.parameters) & set(names) | {n for n in names if names.count(n) > 1}
        if twice:
            raise TypeError(f"{command.__name__} declares {', '.join(sorted(twice))} twice")
        parameters = []
        for parameter in signature.parameters.values():
            group = groups.get(parameter.name)
            if group is None:
                parameters.append(parameter)
                continue
            kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
            parameters += [
                inspect.Parameter(f.name, kind, default=f.default, annotation=f.kind)
                for f in group.flags
            ]

        @functools.wraps(command)
        def run(**given: Any) -> Any:
            for name, group in groups.items():
                given[name] = group.value(given)
            return command(**given)

        run.__signature__ = signature.replace(parameters=parameters)  # type: ignore[attr-defined]
        run.__annotations__ = {p.name: p.annotation for p in parameters}
        return run  # type: ignore[return-value]

    return decorate


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


def flag(name: str, kind: Any, default: Any, text: str, *decls: str, **limits: Any) -> Flag:
    """An option of type ``kind`` (None allowed when that is its default), helped by
    ``text``; ``decls`` and ``limits`` go to `typer.Option` (a float's min and max to
    `bounded`)."""
    if kind is float and ("min" in limits or "max" in limits):
        low, high = limits.pop("min", None), limits.pop("max", None)
        limits["callback"] = bounded(low, high, limits.get("callback"))
        text = f"{text}; a number {_span(low, high)}"
    if isinstance(kind, type) and issubclass(kind, StrEnum) and default is not None:
        default = kind(default)
    allowed = kind if default is not None else kind | None
    return Flag(name, Annotated[allowed, typer.Option(*decls, help=text, **limits)], default)

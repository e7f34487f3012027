"""Records read back: a run folder's summary.json, steps.jsonl and exchanges.jsonl, and a
sweep's sweep.json.

Every command that reads a record it did not just write (`report`, `compare`, `video`, a
resumed `eval`) reads it here, so a file damaged by hand or by another tool (``{}``,
``[1, 2]``, ``"steps": "many"``) is one line naming the file and the field, a
`RecordError`, instead of a traceback wherever the value is first used. The models check
the fields those readers use and keep every other field as written (``extra="allow"``):
records of another cavenav version still read.

The readers return plain dicts, the values converted to the types below (a "3" read as
steps becomes 3), holding only the keys the file held: a reader's ``.get(key, default)``
means what it meant before.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from cavenav.episode.run_folder import numbered_jsonl
from cavenav.errors import CavenavWarning, RecordError, invalid_field

__all__ = ["read_exchanges", "read_steps", "read_summary", "read_sweep_file"]

_Vector = tuple[float, float, float]
# Difficulty knobs: a count (obstacles = 3) must read back whole, or Difficulty refuses it.
_Knobs = dict[str, int | float]


class _Record(BaseModel):
    model_config = ConfigDict(extra="allow")


class _Pose(_Record):
    x: float
    y: float
    z: float
    yaw_deg: float = 0.0


class _Usage(_Record):
    prompt_tokens: int | None = None
    completion_tokens: int | None = None
    requeries: int | None = None
    transport_retries: int | None = None
    cost_usd: float | None = None
    mean_latency_s: float | None = None


class _Portal(_Record):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    point: _Vector
    normal: _Vector
    radius: float = Field(gt=0, le=1e4)  # a scenario file's bound (cavenav.world.scenarios)


class _EpisodeSettings(_Record):
    max_steps: int | None = None
    plots: bool = True


class _Summary(_Record):
    """summary.json: what `cavenav.evaluation.results.episode_row`, the report and the
    video read of it."""

    scenario: str | None = None
    scenario_description: str | None = None
    seed: int | None = None
    pilot: str | None = None
    mesh: str | None = None
    status: str | None = None
    success: bool | None = None
    termination: str | None = None
    failure: str | None = None
    failure_cause: str | None = None
    error: str | None = None
    steps: int | None = None
    collisions: int | None = None
    invalid_actions: int | None = None
    steps_below_standoff: int | None = None
    shield: bool | None = None
    shield_interventions: int | None = None
    progress_m: float | None = None
    passage_length_m: float | None = None
    path_length_m: float | None = None
    min_clearance_m: float | None = None
    mean_clearance_m: float | None = None
    exit_distance_m: float | None = None
    mean_pilot_ms: float | None = None
    mean_sense_ms: float | None = None
    wall_time_s: float | None = None
    usage: _Usage | None = None
    exits: list[_Portal] = Field(default_factory=list)
    difficulty: _Knobs | None = None
    config: _EpisodeSettings | None = None


class _Step(_Record):
    """One line of steps.jsonl: what the outcome, the report and the video read of it."""

    step: int
    pose: _Pose | None = None
    next_pose: _Pose | None = None
    action: str | None = None
    progress_m: float | None = None
    clearance_m: float | None = None
    d_top_m: float | None = None
    d_bottom_m: float | None = None
    collision: bool = False
    frames: dict[str, str] = Field(default_factory=dict)
    shield: dict[str, Any] | None = None

    @model_validator(mode="after")
    def _moved(self) -> _Step:
        # A step that flew an action is judged by where it was and how far it had got.
        if self.action is not None and (self.pose is None or self.progress_m is None):
            raise ValueError("a step with an action needs its pose and progress_m")
        return self


class _Message(_Record):
    role: str | None = None
    content: str | list[dict[str, Any]] | None = None  # text, or parts: text and images


class _Exchange(_Record):
    """One line of exchanges.jsonl: what the report files it under and shows of it."""

    step: int = -1
    attempt: int = 0
    messages: list[_Message] = Field(default_factory=list)


class _PilotEntry(_Record):
    name: str
    label: str | None = None
    options: dict[str, Any] = Field(default_factory=dict)
    recording: str | None = None


class _EpisodeEntry(_Record):
    steps: int | None  # null: each scenario's own budget; the key itself is required
    stuck_after: int | None = None  # absent in sweeps begun before stuck endings
    shield: bool
    frames: str


class _SweepFile(_Record):
    """sweep.json: what `cavenav.evaluation.sweep.SweepConfig.from_dict` and the report
    read of it."""

    format: int | None = None
    scenarios: list[str] = Field(min_length=1)
    seeds: list[int] = Field(min_length=1)
    pilot: _PilotEntry
    episode: _EpisodeEntry
    difficulty: _Knobs = Field(default_factory=dict)
    sensors: dict[str, Any] = Field(default_factory=dict)
    created_at: str | None = None
    cavenav_version: str | None = None


_Model = TypeVar("_Model", bound=_Record)


def _json_kind(value: Any) -> str:
    """What a JSON value is, in JSON's words: "an array", "a number", "null", ..."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    kinds = ((list, "an array"), (str, "a string"), (int | float, "a number"))
    return next((kind for types, kind in kinds if isinstance(value, types)), "an object")


def _checked(model: type[_Model], data: Any, where: str) -> dict[str, Any]:
    """``data`` as ``model`` reads it, as a dict of the keys it held; else one line."""
    if not isinstance(data, dict):
        raise RecordError(
            f"{where}: holds {_json_kind(data)}, not a JSON object: the record is damaged"
        )
    try:
        return model.model_validate(data).model_dump(exclude_unset=True)
    except ValidationError as exc:
        raise RecordError(str(invalid_field(exc, where))) from None


def _read_json(path: Path, model: type[_Model]) -> dict[str, Any]:
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise RecordError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordError(f"{path}: not valid JSON ({exc})") from None
    return _checked(model, data, str(path))


def read_summary(path: Path) -> dict[str, Any]:
    """A run folder's summary.json, checked.

    Raises:
        RecordError: the file is missing, unreadable, not JSON, not an object, or holds a
            field of the wrong type (the message names the field).
    """
    return _read_json(path, _Summary)


def read_steps(path: Path) -> list[dict[str, Any]]:
    """A run folder's steps.jsonl, every line checked ([] when there is none).

    A line that is not JSON is skipped, as `cavenav.episode.run_folder.read_jsonl` does: a
    crash or a kill can cut the last line short, and the record up to it is valid. A line
    that is JSON but not a step is damage.

    Raises:
        RecordError: the file cannot be read, or a line is not an object or holds a field
            of the wrong type, naming the line and the field.
    """
    path = Path(path)
    return [_checked(_Step, data, f"{path} line {n}") for n, data in _lines(path)]


def read_exchanges(path: Path) -> list[dict[str, Any]]:
    """A run folder's exchanges.jsonl ([] when there is none), read leniently.

    The exchanges are the audit trail of the model's requests and replies, not the
    episode's result: a damaged line is left out with one warning naming the file and
    the first such line, and the episode's outcome (from summary.json and steps.jsonl)
    stands.
    """
    path = Path(path)
    try:
        lines = _lines(path)
    except RecordError as exc:
        warnings.warn(f"{exc}; its model exchanges are not shown", CavenavWarning, stacklevel=2)
        return []
    exchanges, damaged = [], []
    for number, data in lines:
        try:
            exchanges.append(_checked(_Exchange, data, f"{path} line {number}"))
        except RecordError as exc:
            damaged.append(exc)
    if damaged:
        more = f" (and {len(damaged) - 1} more)" if len(damaged) > 1 else ""
        warnings.warn(
            f"{damaged[0]}{more}: skipped; the rest of the model exchanges are shown",
            CavenavWarning,
            stacklevel=2,
        )
    return exchanges


def _lines(path: Path) -> list[tuple[int, Any]]:
    """The JSON values of a JSON-lines record, numbered (`run_folder.numbered_jsonl`)."""
    try:
        return numbered_jsonl(path)
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise RecordError(f"{path}: cannot be read ({reason})") from None


def read_sweep_file(path: Path) -> dict[str, Any]:
    """A sweep folder's sweep.json, checked.

    Raises:
        RecordError: the file is unreadable, not JSON, not an object, or a field the
            sweep's configuration needs is missing or of the wrong type.
    """
    return _read_json(path, _SweepFile)

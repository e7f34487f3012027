"""The run folder's records as types: summary.json is an `EpisodeSummary`, each line of
steps.jsonl a `StepRecord`, and the words they end with (`TERMINATIONS`) and are judged by
(`OUTCOMES`) are written here once. Also read back here: exchanges.jsonl and a sweep's
sweep.json.

The recorder (`cavenav.episode.record`) builds these types and writes each as given
(`to_dict`: its fields, values and order, so a run folder is the same file for file);
every command that reads a record it did not just write (`report`, `compare`, `video`, a
resumed `eval`) reads it here, so a file damaged by hand or by another tool (``{}``,
``[1, 2]``, ``"steps": "many"``) is one line naming the file and the field, a
`RecordError`, instead of a traceback wherever the value is first used. The models keep
every field they do not name as written (``extra="allow"``): records of another cavenav
version still read.

`load_summary` and `load_steps` give the types; `read_summary` and `read_steps` the same
records as plain dicts, the values converted to the types below (a "3" read as steps
becomes 3), holding only the keys the file held, for code that rewrites a record.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    ValidatorFunctionWrapHandler,
    model_validator,
)

from cavenav.core.errors import CavenavWarning, RecordError, invalid_field

__all__ = [
    "OUTCOMES",
    "TERMINATED",
    "TERMINATIONS",
    "TRUNCATED",
    "EpisodeSummary",
    "Outcome",
    "StepRecord",
    "Termination",
    "UsageRecord",
    "load_steps",
    "load_summary",
    "numbered_jsonl",
    "read_exchanges",
    "read_steps",
    "read_summary",
    "read_sweep_file",
]

# How an episode ended (summary.json's ``termination``): `TERMINATED` ones end the task
# (Gymnasium's ``terminated``), `TRUNCATED` ones cut it short (``truncated``).
Termination = Literal[
    "exit", "collision", "budget", "pilot_failure", "exited_entrance", "stuck", "battery"
]
TERMINATIONS: tuple[Termination, ...] = get_args(Termination)
TRUNCATED: tuple[Termination, ...] = ("budget", "stuck")
TERMINATED: tuple[Termination, ...] = tuple(t for t in TERMINATIONS if t not in TRUNCATED)

# An episode's place in the failure taxonomy (`cavenav.evaluation.results.outcome`): an
# exit is "success", the other terminations are their own outcome, but for a budget
# ending, told apart by the last steps as "budget", "stuck" or "oscillating"; "error" and
# "incomplete" are episodes that did not finish.
Outcome = Literal[
    "success",
    "collision",
    "pilot_failure",
    "exited_entrance",
    "battery",
    "budget",
    "stuck",
    "oscillating",
    "error",
    "incomplete",
]
OUTCOMES: tuple[Outcome, ...] = get_args(Outcome)

_Vector = tuple[float, float, float]
# Difficulty knobs: a count (obstacles = 3) must read back whole, or Difficulty refuses it.
_Knobs = dict[str, int | float]


class _Record(BaseModel):
    """A record as read (values converted to the declared types) that also keeps what it
    was given, to write it back as given (`to_dict`)."""

    model_config = ConfigDict(extra="allow", frozen=True)
    _given: dict[str, Any] = PrivateAttr(default_factory=dict)

    @model_validator(mode="wrap")
    @classmethod
    def _keep_given(cls, data: Any, handler: ValidatorFunctionWrapHandler) -> Any:  # noqa: ANN401
        record = handler(data)
        if isinstance(data, dict):
            record._given = dict(data)
        return record

    def to_dict(self) -> dict[str, Any]:
        """The record as its JSON file holds it: the keys given, in their order, with the
        values as given (a radius of 3 stays 3, not 3.0)."""
        return dict(self._given)


class _Pose(_Record):
    x: float
    y: float
    z: float
    yaw_deg: float = 0.0


class UsageRecord(_Record):
    """summary.json's ``usage``: what a model pilot's requests cost (None: not recorded)."""

    model_steps: int | None = None
    prompt_tokens: int | None = None
    completion_tokens: int | None = None
    requeries: int | None = None
    transport_retries: int | None = None
    cost_usd: float | None = None
    mean_latency_s: float | None = None
    model_p50_s: float | None = None  # the server's time per step, apart from the queue
    model_p95_s: float | None = None


class _Portal(_Record):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False, frozen=True)
    point: _Vector
    normal: _Vector
    radius: float = Field(gt=0, le=1e4)  # a scenario file's bound (cavenav.world.scenarios)


class _EpisodeConfig(_Record):
    max_steps: int | None = None
    plots: bool = True


class EpisodeSummary(_Record):
    """summary.json: how an episode ended and what it measured (SPEC section 7).

    Rewritten after every step (status "running") and at the end ("finished",
    "interrupted" or "crashed"). Every field is optional on reading: a summary written
    before the first step, by an older cavenav or by a sweep recording a crash holds
    fewer. The drift fields are there only when a vehicle flew the episode (`cavenav
    fly`), ``plots`` only once the plots are drawn, ``error`` only when a sweep recorded
    the episode's crash.
    """

    scenario: str | None = None
    pilot: str | None = None
    seed: int | None = None  # the cave's
    noise_seed: int | None = None  # the sensor noise's; None: written before it was recorded
    pilot_seed: int | None = None  # the pilot's own draws (the random pilot's); None: none
    status: str | None = None  # running, finished, interrupted or crashed
    success: bool | None = None
    termination: Termination | None = None
    terminated: bool | None = None
    truncated: bool | None = None
    collisions: int | None = None
    shield: bool | None = None
    shield_interventions: int | None = None
    invalid_actions: int | None = None
    steps: int | None = None
    path_length_m: float | None = None
    progress_m: float | None = None
    passage_length_m: float | None = None
    shortest_path_m: float | None = None  # through free space, start to exit (successes)
    spl: float | None = None  # success x shortest / max(flown, shortest); 0 for a failure
    min_clearance_m: float | None = None
    mean_clearance_m: float | None = None
    steps_below_standoff: int | None = None
    final_pose: _Pose | None = None
    collision_pose: _Pose | None = None
    exit_distance_m: float | None = None
    failure: str | None = None
    failure_cause: str | None = None  # `PilotFailure.cause`: reply, backend or auth
    wall_time_s: float | None = None
    first_sense_ms: float | None = None
    mean_sense_ms: float | None = None
    mean_pilot_ms: float | None = None
    usage: UsageRecord | None = None
    mean_drift_m: float | None = None
    max_drift_m: float | None = None
    mean_drift_deg: float | None = None
    max_drift_deg: float | None = None
    move_endings: dict[str, int] | None = None  # a vehicle's: reached, settled, timeout
    depth_limited_moves: int | None = None  # a vehicle's moves its depth limits cut
    vehicle_start: dict[str, Any] | None = None  # a vehicle's way to its start depth
    mean_physics_ms: float | None = None
    energy_wh: float | None = None  # the battery energy the moves used (cavenav.motion.energy)
    moving_s: float | None = None  # how long the moves took through the water
    mean_current_m_s: float | None = None  # the water's speed met, where it flowed
    max_current_m_s: float | None = None
    cavenav_version: str | None = None
    scenario_set: str | None = None  # `cavenav.SCENARIO_SET`; None: set 1, before it was written
    python: str | None = None
    host: str | None = None
    pid: int | None = None
    started_at: str | None = None
    scenario_description: str | None = None
    difficulty: _Knobs | None = None
    mesh: str | None = None
    triangles: int | None = None
    start_pose: _Pose | None = None
    exits: list[_Portal] = Field(default_factory=list)
    entrances: list[dict[str, Any]] = Field(default_factory=list)
    config: _EpisodeConfig | None = None
    plots: dict[str, str] = Field(default_factory=dict)
    error: str | None = None


class StepRecord(_Record):
    """One line of steps.jsonl: where the vehicle was, what it sensed and did, and what
    came of it.

    A step that flew an action has ``action``, ``pose`` (before it) and ``progress_m``
    (after it); the step at which the pilot gave up has ``action`` None and ``failure``.
    ``frames`` names the images saved (empty with frames off); ``model_images`` the
    stored images of the current observation as the model was sent them
    ({"rgb", "depth_png"}, model pilots only; ``drawn``, the colour image with the
    choices drawn on it, in place of ``rgb`` for the arrows and waypoint designs). A
    designed VLM pilot's steps say its ``design``, whether the local planner flew the
    step without a call (``planned``), the model's ``choice`` among the ``candidates``
    drawn, and the waypoint's ``goal`` (body frame, metres). With acoustic instruments,
    ``dvl`` is what the DVL reported before the step (velocity forward, left, up in m/s,
    lock, altitude),
    ``sonar`` the sonar's kind and the beams it pinged since the step before, and
    ``frames`` adds its image (``sonar_png``) and its raw echoes (``sonar_npz``);
    ``reckoned`` is where dead reckoning put the vehicle then, and its standard error.
    """

    step: int
    pose: _Pose | None = None
    clearance_m: float | None = None
    d_top_m: float | None = None
    d_bottom_m: float | None = None
    action: str | None = None
    justification: str | None = None
    twist: dict[str, float] | None = None
    next_pose: _Pose | None = None
    collision: bool = False
    progress_m: float | None = None
    commanded_pose: _Pose | None = None
    drift_m: float | None = None
    drift_deg: float | None = None
    energy_wh: float | None = None
    move_s: float | None = None
    current_m_s: float | None = None
    shield: dict[str, Any] | None = None
    vehicle: dict[str, Any] | None = None  # how a vehicle flew the move: asked, flown, ended
    invalid_action: str | None = None
    proposed: str | None = None
    vlm: dict[str, Any] | None = None
    failure: str | None = None
    failure_cause: str | None = None
    timing_ms: dict[str, float] = Field(default_factory=dict)
    frames: dict[str, str] = Field(default_factory=dict)
    model_images: dict[str, str] = Field(default_factory=dict)
    dvl: dict[str, Any] | None = None
    sonar: dict[str, Any] | None = None
    reckoned: dict[str, float] | None = None
    design: str | None = None
    planned: bool | None = None
    choice: dict[str, Any] | None = None
    candidates: list[dict[str, Any]] | None = None
    goal: list[float] | None = None

    @model_validator(mode="after")
    def _moved(self) -> StepRecord:
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
    scenario_set: str | None = None


_Model = TypeVar("_Model", bound=_Record)


def _json_kind(value: Any) -> str:
    """What a JSON value is, in JSON's words: "an array", "a number", "null", ..."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    kinds = ((list, "an array"), (str, "a string"), (int | float, "a number"))
    return next((kind for types, kind in kinds if isinstance(value, types)), "an object")


def _checked(model: type[_Model], data: Any, where: str) -> _Model:
    """``data`` as ``model`` reads it; else one line naming ``where`` and the field."""
    if not isinstance(data, dict):
        raise RecordError(
            f"{where}: holds {_json_kind(data)}, not a JSON object: the record is damaged"
        )
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise RecordError(str(invalid_field(exc, where))) from None


def _read_json(path: Path, model: type[_Model]) -> _Model:
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise RecordError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordError(f"{path}: not valid JSON ({exc})") from None
    return _checked(model, data, str(path))


def load_summary(path: Path) -> EpisodeSummary:
    """A run folder's summary.json, checked.

    Raises:
        RecordError: the file is missing, unreadable, not JSON, not an object, or holds a
            field of the wrong type (the message names the field).
    """
    return _read_json(path, EpisodeSummary)


def load_steps(path: Path) -> list[StepRecord]:
    """A run folder's steps.jsonl, every line checked ([] when there is none).

    A line that is not JSON is skipped, as `numbered_jsonl` does: a
    crash or a kill can cut the last line short, and the record up to it is valid. A line
    that is JSON but not a step is damage.

    Raises:
        RecordError: the file cannot be read, or a line is not an object or holds a field
            of the wrong type, naming the line and the field.
    """
    path = Path(path)
    return [_checked(StepRecord, data, f"{path} line {n}") for n, data in _lines(path)]


def read_summary(path: Path) -> dict[str, Any]:
    """`load_summary` as a dict of the keys the file held, values converted."""
    return load_summary(path).model_dump(exclude_unset=True)


def read_steps(path: Path) -> list[dict[str, Any]]:
    """`load_steps` as dicts of the keys each line held, values converted."""
    return [step.model_dump(exclude_unset=True) for step in load_steps(path)]


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
            exchange = _checked(_Exchange, data, f"{path} line {number}")
            exchanges.append(exchange.model_dump(exclude_unset=True))
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


def numbered_jsonl(path: Path) -> list[tuple[int, Any]]:
    """(line number from 1, value) of each line of a JSON-lines file that reads as JSON;
    [] when there is no file. A line cut short by a crash or a kill is skipped.

    Raises:
        OSError, UnicodeDecodeError: the file cannot be read as text.
    """
    if not path.is_file():
        return []
    values = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        try:
            values.append((number, json.loads(line)))
        except json.JSONDecodeError:
            continue
    return values


def _lines(path: Path) -> list[tuple[int, Any]]:
    """The JSON values of a JSON-lines record, numbered (`numbered_jsonl`)."""
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
    return _read_json(path, _SweepFile).model_dump(exclude_unset=True)

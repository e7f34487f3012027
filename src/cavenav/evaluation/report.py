"""Static HTML reports of a sweep or of one episode, readable from disk with no server.

A sweep folder (sweep.json, results.csv, aggregate.json, episodes/<id>/) gets
``report/index.html`` (configuration, aggregate table, every episode, thumbnails) and one
page per episode under ``report/episodes/``; a lone run folder gets ``report.html`` beside
its files. Pages reach the run folders' images by relative paths, so a sweep folder can be
copied or zipped whole and its report still opens; nothing is fetched from the network
and no script is needed (the one inline script only sorts the episode table).

Everything a model wrote is escaped by the templates (autoescape): a reply is data to
read, never markup to run.
"""

from __future__ import annotations

import os
import re
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any
from urllib.parse import quote

from cavenav.core.errors import (
    CavenavError,
    ConfigError,
    DependencyError,
    RecordError,
    RecordingError,
)
from cavenav.core.files import not_a_file_to_replace
from cavenav.episode.records import (
    OUTCOMES,
    EpisodeSummary,
    StepRecord,
    load_steps,
    load_summary,
    read_exchanges,
    read_sweep_file,
)
from cavenav.episode.run_folder import write_atomic
from cavenav.evaluation.results import ResultRow, aggregate, cave_rates, priced
from cavenav.evaluation.results import outcome as episode_outcome
from cavenav.evaluation.sweep import read_rows

__all__ = ["RunRecord", "SweepRecord", "read_run", "read_sweep_record", "write_report"]

# Outcome -> CSS class: green for success, red for collision, amber for the other ways a
# finished episode fails, grey ("other") for episodes that did not finish.
_UNFINISHED = ("error", "incomplete")
_OUTCOME_CLASS = {"success": "ok", "collision": "bad"} | {
    outcome: "warn" for outcome in OUTCOMES if outcome not in ("success", "collision", *_UNFINISHED)
}
_EMPTY = "—"  # shown for a missing value
# What the page of an episode with no readable record says of its row's outcome.
_COUNTS_AS = {
    "error": "It counts as an error.",
    "incomplete": "It counts as incomplete: run the same sweep again to fly it.",
}


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class RunRecord:
    """A run folder as read from disk.

    Attributes:
        exchanges: the model requests of each step (exchanges.jsonl), attempts in order.
    """

    path: Path
    summary: EpisodeSummary
    steps: tuple[StepRecord, ...]
    exchanges: Mapping[int, tuple[Mapping[str, Any], ...]]


@dataclass(frozen=True)
class SweepRecord:
    """A sweep folder as read from disk.

    Attributes:
        rows: one results row per episode of the grid, read from the run folders (so a
            sweep still running or cut short is reported as it stands).
        groups: the aggregates of those rows (as in aggregate.json).
    """

    path: Path
    config: Mapping[str, Any]
    rows: tuple[ResultRow, ...]
    groups: tuple[Mapping[str, Any], ...]


def read_run(path: Path) -> RunRecord:
    """Read summary.json, steps.jsonl and exchanges.jsonl of a run folder.

    The exchanges are read leniently (`cavenav.episode.records.read_exchanges`): they are
    the audit trail, not the result, so a damaged line is left out with a warning and the
    page agrees with the episode's results row.

    Raises:
        RecordError: the summary or the steps are damaged (naming the file and the field).
    """
    by_step: dict[int, list[dict[str, Any]]] = {}
    for exchange in read_exchanges(path / "exchanges.jsonl"):
        by_step.setdefault(exchange.get("step", -1), []).append(exchange)
    return RunRecord(
        path=path,
        summary=load_summary(path / "summary.json"),
        steps=tuple(load_steps(path / "steps.jsonl")),
        exchanges={
            step: tuple(sorted(items, key=lambda e: e.get("attempt", 0)))
            for step, items in by_step.items()
        },
    )


def read_sweep_record(folder: Path, rows: Sequence[ResultRow] | None = None) -> SweepRecord:
    """Read sweep.json and every episode's results row, and aggregate them.

    Args:
        rows: the rows as the sweep just read them; None reads them from the run folders
            and rewrites results.csv and aggregate.json from them.
    """
    rows = list(rows) if rows is not None else read_rows(folder)
    return SweepRecord(
        path=folder,
        config=read_sweep_file(folder / "sweep.json"),
        rows=tuple(rows),
        groups=tuple(aggregate(rows)),
    )


# --------------------------------------------------------------------------- formatting


def _num(value: Any, digits: int = 2, unit: str = "") -> str:
    """A number with ``digits`` decimals and its unit; a dash when missing."""
    if value is None or value == "":
        return _EMPTY
    if isinstance(value, bool) or not isinstance(value, int | float):
        return str(value)
    text = f"{value:.{digits}f}"
    return f"{text.lstrip('-') if float(text) == 0 else text}{unit}"  # no "-0.0"


def _int(value: Any) -> str:
    return _EMPTY if value is None else f"{int(value):,}"


def _percent_ci(rate: Any, ci: Any) -> str:
    """A rate with its 95 % interval, as "95% [76-99]"."""
    if rate is None:
        return _EMPTY
    text = f"{100 * rate:.0f}%"
    if ci and None not in ci:
        text += f" [{100 * ci[0]:.0f}-{100 * ci[1]:.0f}]"
    return text


def _counts(counts: Mapping[str, int] | None) -> str:
    if not counts:
        return _EMPTY
    return " · ".join(f"{name} {n}" for name, n in sorted(counts.items(), key=lambda kv: -kv[1]))


def _href(target: Path, page_dir: Path) -> str:
    """A relative URL from a page in ``page_dir`` to ``target``, for file:// viewing."""
    return quote(Path(os.path.relpath(target, page_dir)).as_posix())


def outcome_class(outcome: Any) -> str:
    return _OUTCOME_CLASS.get(str(outcome), "other")


@dataclass(frozen=True)
class Column:
    """One column of a table: how to read its value from a record and how to show it.

    Attributes:
        value: the value the column sorts by and that decides whether it is empty.
        text: shows the value; ``row_text``, where given, shows the whole record instead
            (two numbers in one cell).
        zero_is_empty: a column of zeros is hidden like a column of blanks (token counts
            and costs are 0 for pilots without a model).
    """

    header: str
    value: Callable[[Mapping[str, Any]], Any]
    text: Callable[[Any], str] = _num
    zero_is_empty: bool = False
    numeric: bool = True  # right-aligned
    row_text: Callable[[Mapping[str, Any]], str] | None = None

    def empty(self, value: Any) -> bool:
        return value is None or value == "" or (self.zero_is_empty and value == 0)


@dataclass(frozen=True)
class Cell:
    text: str
    sort: str  # what the sorting script compares: the raw number where there is one
    numeric: bool = True


def _table(
    columns: Sequence[Column], records: Sequence[Mapping[str, Any]]
) -> tuple[list[str], list[list[Cell]]]:
    """Headers and cells, leaving out the columns that are empty for every record."""
    shown = [c for c in columns if any(not c.empty(c.value(r)) for r in records)]
    rows = []
    for record in records:
        cells = []
        for column in shown:
            value = column.value(record)
            sort = "" if value is None else str(value)
            if column.empty(value):
                text = _EMPTY
            elif column.row_text is not None:
                text = column.row_text(record)
            else:
                text = column.text(value)
            cells.append(Cell(text, sort, column.numeric))
        rows.append(cells)
    return [c.header for c in shown], rows


def _key(name: str) -> Callable[[Mapping[str, Any]], Any]:
    return lambda record: record.get(name)


_AGGREGATE_COLUMNS = (
    Column("scenario", _key("scenario"), str, numeric=False),
    Column("pilot", _key("pilot"), str, numeric=False),
    Column(
        "episodes",
        lambda g: (g.get("completed"), g.get("episodes")),
        lambda v: str(v[1]) if v[0] == v[1] else f"{v[0]} of {v[1]} completed",
    ),
    Column(
        "caves", lambda g: g.get("caves") if g.get("caves") != g.get("completed") else None, str
    ),
    Column(
        "success [95% CI]",
        lambda g: (g.get("success_rate"), g.get("success_ci95")),
        lambda v: _percent_ci(*v),
    ),
    Column(
        "collisions",
        lambda g: (g.get("collisions"), g.get("collision_rate")),
        lambda v: f"{v[0]} ({_percent_ci(v[1], None)})" if v[1] is not None else str(v[0]),
    ),
    Column("outcomes", _key("outcomes"), _counts, numeric=False),
    Column(
        "min clearance: min / mean",
        _key("min_clearance_m"),
        lambda v: f"{_num(v.get('min'))} / {_num(v.get('mean'))} m",
    ),
    Column("mean clearance", _key("mean_clearance_m"), lambda v: _num(v, 2, " m")),
    Column("steps below standoff", _key("steps_below_standoff"), lambda v: _num(v, 1)),
    Column("SPL", _key("spl"), lambda v: _num(v, 3)),
    Column(
        "path efficiency (successes / all)",
        _key("path_efficiency"),
        row_text=lambda g: (
            f"{_num(g.get('path_efficiency'))} / {_num(g.get('path_efficiency_all'))}"
        ),
    ),
    Column("steps", _key("steps"), lambda v: _num(v, 1)),
    Column("shield interventions", _key("shield_interventions"), lambda v: _num(v, 1)),
    Column("energy", _key("energy_wh"), lambda v: _num(v, 2, " Wh")),
    Column("pilot time", _key("mean_pilot_ms"), lambda v: _num(v, 1, " ms")),
    Column("model latency", _key("mean_model_latency_s"), lambda v: _num(v, 2, " s")),
    Column(
        "model time p50 / p95",
        _key("model_p50_s"),
        row_text=lambda g: f"{_num(g.get('model_p50_s'))} / {_num(g.get('model_p95_s'), 2, ' s')}",
    ),
    Column("prompt tokens", _key("prompt_tokens"), _int, zero_is_empty=True),
    Column("completion tokens", _key("completion_tokens"), _int, zero_is_empty=True),
    Column("cost", _key("cost_usd"), lambda v: f"${v:.4f}", zero_is_empty=True),
    Column("tokens per success", _key("tokens_per_success"), _int),
    Column("cost per success", _key("cost_per_success_usd"), lambda v: f"${v:.4f}"),
    Column("re-queries", _key("requeries"), _int, zero_is_empty=True),
    Column("model calls per episode", _key("calls_per_episode"), lambda v: _num(v, 1)),
    Column("model calls per m", _key("calls_per_m"), lambda v: _num(v, 2)),
    Column(
        "steps without a call",
        _key("steps_without_call_share"),
        lambda v: f"{v:.0%}",
        zero_is_empty=True,
    ),
)


_EPISODE_COLUMNS = (
    Column("scenario", _key("scenario"), str, numeric=False),
    Column("seed", _key("seed"), str),
    Column("trial", _key("trial"), str),
    Column("pilot", _key("pilot"), str, numeric=False),
    Column("steps", _key("steps"), _int),
    Column("collisions", _key("collisions"), _int),
    Column(
        "progress / passage (m)",
        _key("progress_m"),
        row_text=lambda r: f"{_num(r.get('progress_m'), 1)} / {_num(r.get('passage_length_m'), 1)}",
    ),
    Column("SPL", _key("spl"), lambda v: _num(v, 3)),
    Column("path efficiency", _key("path_efficiency")),
    Column("min clearance (m)", _key("min_clearance_m")),
    Column("mean clearance (m)", _key("mean_clearance_m")),
    Column("below standoff", _key("steps_below_standoff"), _int),
    Column("shield", _key("shield_interventions"), _int, zero_is_empty=True),
    Column("invalid", _key("invalid_actions"), _int, zero_is_empty=True),
    Column("energy (Wh)", _key("energy_wh"), lambda v: _num(v, 2)),
    Column("current (m/s)", _key("mean_current_m_s"), lambda v: _num(v, 2)),
    Column("drift (m)", _key("mean_drift_m"), lambda v: _num(v, 2)),
    Column("re-queries", _key("requeries"), _int, zero_is_empty=True),
    Column("retries", _key("transport_retries"), _int, zero_is_empty=True),
    Column("model calls", _key("model_calls"), _int),
    Column("calls per m", _key("calls_per_m"), lambda v: _num(v, 2)),
    Column("without a call", _key("steps_without_call"), _int, zero_is_empty=True),
    Column(
        "tokens in / out",
        lambda r: (r.get("prompt_tokens") or 0) + (r.get("completion_tokens") or 0),
        zero_is_empty=True,
        row_text=lambda r: f"{_int(r.get('prompt_tokens'))} / {_int(r.get('completion_tokens'))}",
    ),
    Column("cost", _key("cost_usd"), lambda v: f"${v:.4f}", zero_is_empty=True),
    Column("model latency (s)", _key("mean_model_latency_s")),
    Column(
        "model time p50 / p95 (s)",
        _key("model_p50_s"),
        row_text=lambda r: f"{_num(r.get('model_p50_s'))} / {_num(r.get('model_p95_s'))}",
    ),
    Column("pilot (ms)", _key("mean_pilot_ms"), lambda v: _num(v, 1)),
    Column("wall (s)", _key("wall_time_s"), lambda v: _num(v, 1)),
    Column("error", _key("error"), str, numeric=False),
)


def _summary_facts(s: EpisodeSummary, outcome: str) -> list[tuple[str, str]]:
    """The header of an episode page: what a reader checks first, in that order."""
    budget = s.config.max_steps if s.config and s.config.max_steps is not None else "?"
    facts = [
        ("scenario", f"{s.scenario} · {s.scenario_description or ''}".rstrip(" ·")),
        ("seed", _EMPTY if s.seed is None else str(s.seed)),
        ("pilot", str(s.pilot)),
        ("outcome", outcome),
        ("termination", str(s.termination)),
        ("status", str(s.status)),
        ("steps", f"{s.steps} of {budget}"),
        ("collisions", str(s.collisions)),
        ("min clearance", _num(s.min_clearance_m, 2, " m")),
        ("mean clearance", _num(s.mean_clearance_m, 2, " m")),
        ("steps below standoff", str(s.steps_below_standoff)),
        ("path length", _num(s.path_length_m, 2, " m")),
        ("progress / passage", f"{_num(s.progress_m, 2)} / {_num(s.passage_length_m, 2)} m"),
        ("exit distance", _num(s.exit_distance_m, 2, " m")),
        ("SPL / shortest path", f"{_num(s.spl, 3)} / {_num(s.shortest_path_m, 2, ' m')}"),
        ("shield", f"on, {s.shield_interventions or 0} interventions" if s.shield else "off"),
        ("invalid actions", str(s.invalid_actions or 0)),
        ("energy", f"{_num(s.energy_wh, 2, ' Wh')} over {_num(s.moving_s, 0, ' s')} of moves"),
        ("sense / pilot", f"{_num(s.mean_sense_ms, 1)} / {_num(s.mean_pilot_ms, 1)} ms a step"),
        ("wall time", _num(s.wall_time_s, 1, " s")),
        ("started", s.started_at or _EMPTY),
    ]
    if s.usage:
        u = s.usage
        facts += [
            ("tokens", f"{_int(u.prompt_tokens)} in, {_int(u.completion_tokens)} out"),
            ("model latency", _num(u.mean_latency_s, 2, " s a step")),
            ("re-queries / retries", f"{u.requeries} / {u.transport_retries}"),
            ("cost", _EMPTY if u.cost_usd is None else f"${u.cost_usd:.4f}"),
        ]
    if s.failure:
        facts.append(("failure", s.failure))
    return facts


# --------------------------------------------------------------------------- page views


@dataclass(frozen=True)
class Picture:
    """An image of a step, linked relative to the page.

    Attributes:
        sonar: a sonar's fan or disc, shown as high as the camera's images rather than as
            wide (a multibeam's fan is wider than it is high, a Ping360's disc square).
    """

    href: str
    label: str
    sonar: bool = False


@dataclass(frozen=True)
class Plot:
    name: str
    href: str | None  # None: missing, see reason
    reason: str = ""


@dataclass(frozen=True)
class StepView:
    """One step block of an episode page.

    Attributes:
        record: the steps.jsonl record.
        pictures: the colour and depth images (and the sonar's, where the vehicle
            carried one), relative to the page.
        pictures_note: where they came from, or why there are none.
        attempts: the model's exchanges of the step, first try first.
    """

    record: StepRecord
    pictures: tuple[Picture, ...]
    pictures_note: str
    attempts: tuple[Mapping[str, Any], ...]

    @property
    def marks(self) -> tuple[str, ...]:
        """CSS classes of what happened: collision, shield, invalid, failure, requery, a
        vehicle's move that did not reach its goal, and a step the planner flew without
        asking the model."""
        r = self.record
        marks = [
            name
            for name, hit in (
                ("collision", r.collision),
                ("shield", r.shield),
                ("invalid", r.invalid_action),
                ("failure", r.failure),
                ("requery", len(self.attempts) > 1),
                ("vehicle", r.vehicle is not None and r.vehicle.get("ended") != "reached"),
                ("planned", bool(r.planned)),
            )
            if hit
        ]
        return tuple(marks)

    @property
    def chosen_at(self) -> tuple[float, float] | None:
        """Where on the drawn image the model's choice lies, in percent from the top left
        (a designed pilot's point, or its number's disc); None for other steps."""
        choice, candidates = self.record.choice or {}, self.record.candidates or []
        point = choice.get("point")
        if point is None:
            chosen = [c for c in candidates if c.get("number") == choice.get("number")]
            point = [chosen[0]["x"], chosen[0]["y"]] if chosen else None
        return None if point is None else (100 * float(point[0]), 100 * float(point[1]))


def _step_pictures(
    run: RunRecord, record: StepRecord, page_dir: Path, no_frames_note: str
) -> tuple[tuple[Picture, ...], str]:
    """The step's saved frames, with its sonar image where the vehicle carried a sonar;
    else the current observation's images as the model was sent them (``model_images``,
    stored under images/, or for a step recorded before that field existed, read from its
    first request); else a note saying why none."""
    drawn = _pictures(run, page_dir, record.model_images, {"drawn": "the choices drawn, as sent"})
    saved = _pictures(run, page_dir, record.frames, {"rgb": "colour", "depth_png": "depth"})
    if saved:
        return drawn + saved + _sonar_picture(run, record, page_dir), ""
    labels = {
        "drawn": "the choices drawn, as sent to the model",
        "rgb": "colour, as sent to the model",
        "depth_png": "depth, as sent to the model",
    }
    sent_files = record.model_images or _sent_images_before_model_images(
        run.exchanges.get(record.step, ())
    )
    sent = _pictures(run, page_dir, sent_files, labels)
    if sent:
        return sent, "frames not saved; images from the model request"
    if record.frames:
        return (), "frames listed in steps.jsonl but missing from the run folder"
    return (), no_frames_note


def _sent_images_before_model_images(
    exchanges: Sequence[Mapping[str, Any]],
) -> dict[str, str]:
    """The current colour and depth images of a step recorded before ``model_images``.

    Run folders written before steps.jsonl named the images sent to the model keep them
    only in the step's first request: a request lists earlier observations first, the
    current one follows the text part that starts "Current observation". Without that
    marker, the last two images. Keys as in ``model_images`` ("rgb", "depth_png").
    """
    if not exchanges:
        return {}
    parts: list[Mapping[str, Any]] = []
    for message in exchanges[0].get("messages", []):
        if message.get("role") == "user" and isinstance(message.get("content"), list):
            parts.extend(message["content"])
    images = [k for k, p in enumerate(parts) if p.get("type") == "image" and p.get("file")]
    current = [
        k
        for k, p in enumerate(parts)
        if p.get("type") == "text" and str(p.get("text", "")).startswith("Current observation")
    ]
    after = [k for k in images if current and k > current[-1]][:2]
    files = [str(parts[k]["file"]) for k in (after or images[-2:])]
    return dict(zip(("rgb", "depth_png"), files, strict=False))


def _pictures(
    run: RunRecord, page_dir: Path, files: Mapping[str, str], labels: Mapping[str, str]
) -> tuple[Picture, ...]:
    """The images of ``files`` named in ``labels`` (keys as in a step's ``frames``: "rgb",
    "depth_png") that exist, in the order of ``labels``."""
    return tuple(
        Picture(_href(run.path / files[key], page_dir), label)
        for key, label in labels.items()
        if key in files and (run.path / files[key]).is_file()
    )


def _sonar_picture(run: RunRecord, record: StepRecord, page_dir: Path) -> tuple[Picture, ...]:
    """The step's sonar image (``frames["sonar_png"]``) where it exists, labelled with the
    sonar's kind ("multibeam sonar", "ping360 sonar")."""
    name = record.frames.get("sonar_png")
    if name is None or not (run.path / name).is_file():
        return ()
    kind = (record.sonar or {}).get("kind")
    return (Picture(_href(run.path / name, page_dir), f"{kind} sonar" if kind else "sonar", True),)


def _missing_plot_reason(summary: EpisodeSummary) -> str:
    status = summary.status
    if status == "interrupted":
        return "episode interrupted: no plot drawn"
    if status == "running":
        return "episode still running (or killed): no plot yet"
    if status == "crashed":
        return "episode crashed before its plots were drawn"
    if summary.config is not None and not summary.config.plots:
        return "plots turned off for this episode"
    return "plot file missing"


def _plots(run: RunRecord, page_dir: Path) -> tuple[Plot, Plot]:
    def plot(name: str) -> Plot:
        path = run.path / f"{name}.png"
        if path.is_file():
            return Plot(name, _href(path, page_dir))
        return Plot(name, None, _missing_plot_reason(run.summary))

    return plot("topdown"), plot("side")


def _system_prompt(run: RunRecord) -> str | None:
    for exchanges in run.exchanges.values():
        for message in exchanges[0].get("messages", [])[:1]:
            if message.get("role") == "system" and isinstance(message.get("content"), str):
                return message["content"]
    return None


# --------------------------------------------------------------------------- rendering


@lru_cache(maxsize=1)
def _environment() -> Any:
    try:
        import jinja2
    except ImportError:
        raise DependencyError("reports need jinja2: pip install jinja2") from None
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("cavenav", "evaluation/templates"),
        # select_autoescape's default list checks the last suffix only, which for
        # "index.html.j2" is "j2": name the double suffix or nothing would be escaped.
        autoescape=jinja2.select_autoescape(enabled_extensions=("html", "html.j2")),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = _num
    env.filters["int"] = _int
    env.filters["outcome_class"] = outcome_class
    return env


def render_page(template: str, path: Path, **context: Any) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    # Atomic: a reader refreshing the page never sees half of it.
    write_atomic(path, _environment().get_template(template).render(**context))
    return path


@dataclass(frozen=True)
class Neighbours:
    """Links from an episode page of a sweep: the index and the episodes beside it."""

    index: str
    previous: str | None = None
    next: str | None = None


def _episode_title(summary: EpisodeSummary) -> str:
    seed = summary.seed
    parts = [summary.scenario, summary.pilot]
    return " · ".join(map(str, parts + ([f"seed {seed}"] if seed is not None else [])))


def _write_episode_page(
    run: RunRecord,
    page: Path,
    outcome: str | None = None,
    neighbours: Neighbours | None = None,
    no_frames_note: str = "no frames saved (flown with --no-frames)",
) -> Path:
    """Render one episode's page at ``page``; image links are relative to its folder.

    Args:
        outcome: the sweep's outcome for it (stuck, oscillating ...), else from its summary.
        neighbours: links back to the sweep's index, for episodes of a sweep.
        no_frames_note: what a step without images says.
    """
    page_dir = page.parent
    steps = []
    for record in run.steps:
        pictures, note = _step_pictures(run, record, page_dir, no_frames_note)
        attempts = run.exchanges.get(record.step, ())
        steps.append(StepView(record, pictures, note, attempts))
    outcome = outcome or episode_outcome(run.summary, run.steps)
    video = run.path / "episode.mp4"
    return render_page(
        "episode.html.j2",
        page,
        title=_episode_title(run.summary),
        run_href=_href(run.path, page_dir),
        video_href=_href(video, page_dir) if video.is_file() else None,
        summary=run.summary,
        outcome=outcome,
        facts=_summary_facts(run.summary, outcome),
        plots=_plots(run, page_dir),
        steps=steps,
        system_prompt=_system_prompt(run),
        models=sorted({str(e.get("model")) for ex in run.exchanges.values() for e in ex}),
        neighbours=neighbours,
    )


@dataclass(frozen=True)
class EpisodeLink:
    """An episode on the index: its row, its page and its thumbnail."""

    id: str
    outcome: str
    href: str
    cells: list[Cell]
    thumb: str | None
    thumb_reason: str


def _flat(values: Mapping[str, Any], prefix: str = "") -> str:
    """``{"a": 1, "b": {"c": 2}}`` as "a=1, b.c=2"; a dash when empty."""
    items = []
    for key, value in values.items():
        if isinstance(value, Mapping):
            items.append(_flat(value, f"{prefix}{key}.") if value else "")
        else:
            items.append(f"{prefix}{key}={value}")
    return ", ".join(i for i in items if i) or _EMPTY


def _sweep_facts(config: Mapping[str, Any]) -> list[tuple[str, str]]:
    pilot = config.get("pilot") or {}
    name, label = pilot.get("name"), pilot.get("label") or pilot.get("name")
    facts = [
        ("scenarios", ", ".join(map(str, config.get("scenarios", [])))),
        ("seeds", _seed_text([str(s) for s in config.get("seeds", [])])),
        ("pilot", str(label) if label == name else f"{label} ({name})"),
        ("pilot options", _flat(pilot.get("options") or {})),
        ("episode", _flat(config.get("episode") or {})),
    ]
    if config.get("trials", 1) > 1:
        facts.append(("trials", f"{config['trials']} flights of each cave"))
    facts += [
        (key, _flat(config[key]))
        for key in ("difficulty", "sensors")
        if isinstance(config.get(key), Mapping) and config[key]
    ]
    return facts + [
        ("created", str(config.get("created_at", _EMPTY))),
        ("cavenav", str(config.get("cavenav_version", _EMPTY))),
        ("scenario set", str(config.get("scenario_set") or "1")),
    ]


def _seed_text(seeds: Sequence[str]) -> str:
    """Seeds as "0-19" when they are a run of integers, else listed."""
    if len(seeds) > 2 and all(s.isdigit() for s in seeds):
        numbers = [int(s) for s in seeds]
        if numbers == list(range(numbers[0], numbers[0] + len(numbers))):
            return f"{numbers[0]}-{numbers[-1]} ({len(numbers)} seeds)"
    return ", ".join(seeds) or _EMPTY


def page_name(episode: str) -> str:
    """The file name of an episode's page: its id, made safe to stay inside report/."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", episode).lstrip(".") + ".html"


def _episode_pages(
    sweep: SweepRecord, report: Path, cells: Sequence[list[Cell]]
) -> Iterable[EpisodeLink]:
    """Write every episode's page; yield what the index shows of each (``cells``: its row)."""
    frames_note = (
        "no frames saved (--frames none)"
        if sweep.config["episode"]["frames"] == "none"
        else "no frames saved for this step"
    )
    ids = [str(row.get("episode")) for row in sweep.rows]
    pages = [f"episodes/{quote(page_name(i))}" for i in ids]
    for k, row in enumerate(sweep.rows):
        run_dir = sweep.path / str(row.get("run_dir") or f"episodes/{ids[k]}")
        page = report / "episodes" / page_name(ids[k])
        outcome = str(row.get("outcome") or "incomplete")
        neighbours = Neighbours(
            index="../index.html",
            previous=f"../{pages[k - 1]}" if k > 0 else None,
            next=f"../{pages[k + 1]}" if k + 1 < len(pages) else None,
        )
        run, error = None, row.get("error") or "the run folder holds no summary.json"
        if (run_dir / "summary.json").is_file():
            try:
                run = read_run(run_dir)
            except RecordError as exc:  # its summary or steps: an error row, with a warning
                error = str(exc)
        if run is not None:
            _write_episode_page(run, page, outcome, neighbours, frames_note)
            topdown = run_dir / "topdown.png"
            thumb = _href(topdown, report) if topdown.is_file() else None
            reason = "" if thumb else _missing_plot_reason(run.summary)
        else:
            damaged = (run_dir / "summary.json").is_file()
            label = "damaged record" if damaged else "no run folder"
            note = "Its record does not read back." if damaged else "It left no run folder."
            render_page(
                "missing.html.j2",
                page,
                title=ids[k],
                id=ids[k],
                label=label,
                note=f"{note} {_COUNTS_AS.get(outcome, f'Its outcome is {outcome}.')}",
                error=error,
                neighbours=neighbours,
            )
            thumb, reason = None, f"{label}: {error}"
        yield EpisodeLink(ids[k], outcome, pages[k], cells[k], thumb, reason)


def _write_sweep_report(
    folder: Path, rows: Sequence[ResultRow] | None, prices: tuple[float, float] | None
) -> Path:
    """report/index.html and report/episodes/<id>.html for a sweep folder; returns the index."""
    if prices is not None:  # results.csv keeps what was recorded; the page, these prices
        rows = priced(read_rows(folder) if rows is None else rows, prices)
    sweep = read_sweep_record(folder, rows)
    report = folder / "report"
    headers, cells = _table(_EPISODE_COLUMNS, sweep.rows)
    episodes = list(_episode_pages(sweep, report, cells))
    groups = list(sweep.groups)
    group_headers, group_rows = _table(_AGGREGATE_COLUMNS, groups)
    outcomes = Counter(link.outcome for link in episodes)
    pages = {link.id: link.href for link in episodes}
    caves = [
        {**cave, "links": [(name, pages[name]) for name in cave["episodes"]]}
        for cave in (cave_rates(sweep.rows) if sweep.config.get("trials", 1) > 1 else [])
    ]
    facts = _sweep_facts(sweep.config)
    if prices:
        priced_at = f"USD {prices[0]:g} / {prices[1]:g} per million tokens in / out"
        facts.append(("prices", f"{priced_at}, applied to the recorded tokens (--price)"))
    return render_page(
        "index.html.j2",
        report / "index.html",
        title=f"sweep {folder.name}",
        facts=facts,
        groups=list(zip(groups, group_rows, strict=True)),
        group_headers=group_headers,
        episode_headers=headers,
        episodes=episodes,
        outcomes=outcomes.most_common(),
        caves=caves,
    )


def write_report(
    folder: Path,
    rows: Sequence[ResultRow] | None = None,
    prices: tuple[float, float] | None = None,
) -> Path:
    """Write the HTML report of a sweep folder or of one run folder; returns its main page.

    A sweep folder (holding sweep.json) gets ``report/index.html`` and one page per
    episode under ``report/episodes/``, with results.csv and aggregate.json refreshed
    from the run folders unless the sweep hands over the ``rows`` it just read; a run
    folder (holding summary.json) gets ``report.html``. Rewriting is safe at any time,
    also while the sweep runs. ``prices`` (USD per million tokens in, out) price a
    sweep's recorded tokens on its pages (`priced`); results.csv keeps what was recorded.

    Raises:
        CavenavError: ``folder`` is neither a sweep folder nor a run folder.
        RecordError: its sweep.json, or the summary or steps of a lone run folder, is
            damaged (an episode of a sweep with a damaged record is shown as an error).
        RecordingError: the report cannot be written (a read-only folder, a full disk);
            every page is written whole or not at all.
    """
    folder = Path(folder)
    sweep = (folder / "sweep.json").is_file()
    if not sweep and not (folder / "summary.json").is_file():
        raise CavenavError(
            f"{folder} is neither a sweep folder (no sweep.json) nor a run folder "
            "(no summary.json): give the folder `cavenav eval` or `cavenav run` wrote"
        )
    page = folder / "report" / "index.html" if sweep else folder / "report.html"
    if why := not_a_file_to_replace(page):  # a device there would be replaced by a file
        raise ConfigError(f"cannot write the report: {why}")
    try:
        if sweep:
            return _write_sweep_report(folder, rows, prices)
        return _write_episode_page(read_run(folder), page)
    except OSError as exc:
        raise RecordingError.cannot_write(f"the report in {folder}", exc) from None

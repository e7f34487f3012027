"""Training data from flights: `cavenav dataset SWEEP_OR_RUN... --out DIR`.

One row is one decision: the request the VLM pilot sends at that step (system prompt,
history, the current colour and depth images, the sounder readings) and the reply it
should give, with the cave, step and outcome it came from. The folder is a Hugging Face
dataset, loaded with ``datasets.load_dataset(DIR)``:

DIR/
  README.md              the dataset card: sources, pilot, prompt, settings, counts
  cavenav_dataset.json   the same as data, and the prompt options a model trained on it
                         must fly with (`cavenav finetune` keeps them in its model card)
  data/train-00000-of-00002.parquet, data/validation-00000-of-00001.parquet

Columns: ``messages`` (the request in the chat form processors take: each message's
content a list of parts, an image part standing for the next of ``images``; the form
the transformers backend gives a request, `cavenav.pilots.backends.local_chat`), ``images``
(the very bytes the request carries, PNG or JPEG), ``reply`` (the target), ``action``
(its action string), ``teacher``, ``pilot``, ``scenario``, ``seed``, ``cave``,
``episode``, ``step``, ``success``, ``termination``, ``shielded``, ``detail``.
`request_messages` turns a row back into the OpenAI request, byte for byte.

Where the requests come from: a model pilot's run folder recorded them
(exchanges.jsonl, images/); any other run is flown again (`cavenav.training.replay`),
which needs no frames. Where the replies come from (``labels``): ``recorded``, the
pilot's own (a model's raw reply, reasoning and all, for distillation; another pilot's
action and justification as the one-pair reply, after its situation, constraints and
choice for the geometric pilot), or ``teacher``, the answer of a teacher that flew in
the pilot's shadow (`cavenav run/eval --teacher`; DAgger), a teacher that flew alone
being its own: DAgger's rounds and the teacher's flights make one dataset.

Rows are written as they are made, a shard at a time, under names that say they are
partial; the shards get their final names and the card is written only when every row
is in. An export stopped by a full disk, a refused episode or Ctrl-C removes what it
wrote; one killed leaves no card and no shard that looks complete.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import os
import re
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from cavenav import SCENARIO_SET, __version__
from cavenav.core.errors import ActionError, ConfigError, DependencyError, RecordingError
from cavenav.episode.records import read_exchanges, read_steps, read_summary
from cavenav.episode.run_folder import write_atomic, write_json
from cavenav.episode.settings import SETTLED
from cavenav.evaluation.sweep import plan, read_sweep
from cavenav.pilots.backends import Message, local_chat
from cavenav.pilots.factory import TEACHERS, VLMOptions
from cavenav.pilots.reply import parse_reply
from cavenav.training.card import dataset_card
from cavenav.training.replay import recorded_cave, recorded_config, recorded_requests

__all__ = [
    "EPISODES",
    "LABELS",
    "REPLIES",
    "DatasetOptions",
    "Export",
    "export_dataset",
    "request_messages",
    "target_reply",
]

LABELS = ("recorded", "teacher")
EPISODES = ("successful", "all")
REPLIES = ("full", "brief", "terse")
FORMAT = 1
# The geometric pilot's justification: "Situation: ... Constraints: ... Choice: ..."
_GEOMETRIC = re.compile(r"Situation: (?P<situation>.*?) Constraints: (?P<constraints>.*?) "
                        r"Choice: (?P<choice>.*)", re.DOTALL)  # fmt: skip


@dataclass(frozen=True)
class DatasetOptions:
    """What `export_dataset` keeps, and how it asks.

    Attributes:
        labels: "recorded" (the pilot's own replies) or "teacher" (a shadow teacher's).
        episodes: "successful" (episodes that reached the exit) or "all"; None takes
            "successful" for recorded labels and "all" for a teacher's, whose labels are
            worth most where the student went wrong.
        drop_shielded: leave out the steps whose action the safety shield replaced.
        validation: the share of caves (never of steps) held out as the validation split.
        reply: "full" (reasoning, then the one-pair dictionary), "brief" (the
            dictionary alone, with a short justification) or "terse" (the dictionary,
            its justification the choice's reason alone): for a small model, whose
            every token costs time on the vehicle. A model's recorded reply stays whole.
        shard_rows: rows in a Parquet shard.
        allow_mixed: accept sources flown with different settings or prompts.
        vlm: the prompt and images of the requests made again (runs of pilots other than
            a model): `VLMOptions`' history, image format and size, prompt file, detail.
    """

    labels: str = "recorded"
    episodes: str | None = None
    drop_shielded: bool = True
    validation: float = 0.1
    reply: str = "full"
    shard_rows: int = 1000
    allow_mixed: bool = False
    vlm: VLMOptions = field(default_factory=VLMOptions)

    def __post_init__(self) -> None:
        for name, value, allowed in (
            ("--labels", self.labels, LABELS),
            ("--episodes", self.episodes or EPISODES[0], EPISODES),
            ("--reply", self.reply, REPLIES),
        ):
            if value not in allowed:
                raise ConfigError(f"{name} must be one of {', '.join(allowed)}, not '{value}'")
        if not 0.0 <= self.validation < 1.0:
            raise ConfigError(f"--validation must lie in [0, 1), not {self.validation}")
        if self.shard_rows < 1:
            raise ConfigError(f"--shard-rows must be at least 1, not {self.shard_rows}")
        self.vlm.request_images()  # a bad image setting fails now
        self.vlm.prompt_config()

    @property
    def successful_only(self) -> bool:
        chosen = self.episodes or ("successful" if self.labels == "recorded" else "all")
        return chosen == "successful"


@dataclass(frozen=True)
class _Episode:
    """One recorded episode to draw rows from.

    Attributes:
        run_dir: its run folder.
        scenario: how its cave loads: a family's name or the scenario file a sweep names.
        summary: its summary.json.
    """

    run_dir: Path
    scenario: str
    summary: Mapping[str, Any]

    @property
    def cave(self) -> str:
        return f"{Path(self.scenario).stem}-seed{self.summary.get('seed') or 0:04d}"

    @property
    def settings(self) -> str:
        """What must agree across the sources: the sensors, rules, body, water and shield
        the episode flew with (its seeds and step budget may differ)."""
        config = dict(self.summary.get("config") or {})
        for per_episode in ("seed", "max_steps", "plots", "save_frames", "save_exr",
                            "exr_compression", "difficulty", *SETTLED):  # fmt: skip
            config.pop(per_episode, None)  # the settled ones are in "sensors" and "current"
        sensors = dict(config.get("sensors") or {})
        sensors.pop("seed", None)  # a trial's noise
        config["sensors"] = sensors
        config["scenario_set"] = self.summary.get("scenario_set")
        return json.dumps(config, sort_keys=True)

    @property
    def system_prompt(self) -> str | None:
        """The system prompt of a model pilot's requests; None for a run flown again,
        whose requests take the dataset's own prompt (a teacher's sweep was flown with
        none, so it agrees with any DAgger round)."""
        exchanges = self.run_dir / "exchanges.jsonl"
        if not exchanges.is_file():
            return None
        with open(exchanges, encoding="utf-8") as lines:
            first = json.loads(next(lines, "{}") or "{}")
        return next(
            (m.get("content") for m in first.get("messages", []) if m.get("role") == "system"),
            None,
        )


def _episodes_of(source: Path) -> tuple[list[_Episode], dict[str, Any]]:
    """The finished episodes of a sweep or run folder, and what the source is.

    Raises:
        ConfigError: ``source`` is neither, or cannot be read.
    """
    if (source / "sweep.json").is_file():
        config, meta = read_sweep(source)
        jobs, episodes = plan(config), []
        for job in jobs:
            run_dir = source / "episodes" / job.episode
            if (run_dir / "summary.json").is_file():
                summary = read_summary(run_dir / "summary.json")
                if summary.get("status") == "finished":
                    episodes.append(_Episode(run_dir, job.scenario, summary))
        about = {"kind": "sweep", "pilot": meta["pilot"], "grid": len(jobs)}
        return episodes, about
    if (source / "summary.json").is_file():
        summary = read_summary(source / "summary.json")
        scenario = str(summary.get("scenario"))
        finished = [_Episode(source, scenario, summary)]
        about = {"kind": "run", "pilot": {"label": summary.get("pilot")}, "grid": 1}
        return (finished if summary.get("status") == "finished" else []), about
    raise ConfigError(f"{source} is neither a sweep folder (sweep.json) nor a run folder")


def _geometric_parts(justification: str) -> dict[str, str] | None:
    match = _GEOMETRIC.fullmatch(justification.strip())
    return None if match is None else match.groupdict()


def target_reply(action: str, justification: str, style: str = "full") -> str:
    """The reply a pilot's action and justification make, in the form the prompt asks for.

    "full": the geometric pilot's situation, constraints and choice as reasoning (a), (b)
    and (c), then the one-pair dictionary ``{action: justification}``, its justification
    the constraints and the choice's reason ("all clearances above the 2.0 m standoff;
    holding the passage centre"); other pilots' the dictionary alone, with their whole
    justification. "brief": the dictionary alone. "terse": the dictionary alone, the
    geometric pilot's justification its reason alone ("holding the passage centre"): the
    action comes first, so what follows it only costs time on the vehicle.
    """
    parts = _geometric_parts(justification)
    if parts is not None:  # the dictionary's justification: the constraints and the reason
        reason = parts["choice"].removeprefix(action).strip(" ,.")
        constraints = parts["constraints"].rstrip(".")
        kept = (reason or constraints,) if style == "terse" else (constraints, reason)
        justification = "; ".join(p for p in kept if p)
    answer = json.dumps({action: justification}, ensure_ascii=False)
    if style != "full" or parts is None:
        return answer
    return (
        f"(a) Situation: {parts['situation']}\n(b) Constraints: {parts['constraints']}\n"
        f"(c) Choice: {parts['choice']}\n{answer}"
    )


def _proposed(step: Mapping[str, Any]) -> str:
    """The action the pilot itself chose at a step (before any shield or refusal)."""
    shield = step.get("shield")
    if shield:
        return str(shield["proposed"])
    return str(step.get("proposed") or step["action"])


def _own_teacher(labels: str, pilot: str, steps: Sequence[Mapping[str, Any]]) -> str:
    """The labels an episode gives: a teacher that flew alone (a pilot that can teach,
    flown with no teacher beside it) is its own teacher, so that DAgger's rounds and the
    teacher's own flights go into one dataset under ``--labels teacher``."""
    alone = not any(isinstance(step.get("teacher"), Mapping) for step in steps)
    return "recorded" if labels == "teacher" and pilot in TEACHERS and alone else labels


def _label(step: Mapping[str, Any], labels: str, style: str, where: Path) -> tuple[str, str, str]:
    """(reply, its action, who gave it) for a step flown by a pilot without a model.

    Raises:
        ConfigError: teacher labels asked of an episode flown without a teacher.
    """
    if labels == "teacher":
        teacher = step.get("teacher")
        if not isinstance(teacher, Mapping):
            raise ConfigError(
                f"{where}: step {step['step']} has no teacher label; fly it with --teacher "
                "geometric, or export it with --labels recorded"
            )
        action, why = str(teacher["action"]), str(teacher.get("justification") or "")
        return target_reply(action, why, style), action, str(teacher.get("pilot"))
    action = _proposed(step)
    return target_reply(action, str(step.get("justification") or ""), style), action, ""


# --------------------------------------------------------------------------- messages


def _image_bytes(url: str) -> bytes:
    return base64.b64decode(url.partition(",")[2])


def _data_url(data: bytes) -> str:
    kind = "png" if data.startswith(b"\x89PNG") else "jpeg"
    return f"data:image/{kind};base64," + base64.b64encode(data).decode("ascii")


def request_messages(row: Mapping[str, Any]) -> list[Message]:
    """A row's request as the VLM pilot sends it (OpenAI chat messages, images as data
    URLs): byte for byte what the pilot sent, or would have sent, at that step.

    ``row["images"]`` are bytes, or {"bytes": ...} as datasets gives them with
    ``Image(decode=False)`` or pyarrow reads them. A system message's content is text,
    every other message's a list of parts, as the pilot sends them.
    """
    images = iter(row["images"])
    messages: list[Message] = []
    for message in row["messages"]:
        if message["role"] == "system":
            messages.append({"role": "system", "content": message["content"][0]["text"]})
            continue
        parts: list[dict[str, Any]] = []
        for part in message["content"]:
            if part["type"] == "text":
                parts.append({"type": "text", "text": part["text"]})
                continue
            data = next(images)
            url = {"url": _data_url(data["bytes"] if isinstance(data, Mapping) else data)}
            if row.get("detail"):
                url["detail"] = row["detail"]
            parts.append({"type": "image_url", "image_url": url})
        messages.append({"role": message["role"], "content": parts})
    return messages


# --------------------------------------------------------------------------- rows


def _recorded_exchanges(
    run_dir: Path, read: dict[str, bytes]
) -> dict[int, tuple[list[Message], str]]:
    """Each step's first request and accepted reply, from a model pilot's run folder
    (images read back from images/ as data URLs); ``read`` gains each URL's bytes, so
    that no image is decoded again from the URL made of it."""
    by_step: dict[int, tuple[list[Message], str]] = {}
    urls: dict[str, str] = {}

    def url(name: str) -> str:
        if name not in urls:
            data = (run_dir / name).read_bytes()
            urls[name] = _data_url(data)
            read[urls[name]] = data
        return urls[name]

    for record in read_exchanges(run_dir / "exchanges.jsonl"):
        step = record["step"]
        if record.get("attempt") == 0:
            messages = [_with_urls(m, url) for m in record["messages"]]
            by_step[step] = (messages, "")
        if record.get("rejected") is None and step in by_step:
            by_step[step] = (by_step[step][0], str(record.get("reply") or ""))
    return {step: kept for step, kept in by_step.items() if kept[1]}


def _with_urls(message: Mapping[str, Any], url: Any) -> Message:  # noqa: ANN401 - a reader
    """A message of exchanges.jsonl with its stored images as the data URLs sent."""
    content = message["content"]
    if isinstance(content, str):
        return dict(message)
    parts = [
        {"type": "image_url", "image_url": {"url": url(p["file"])}} if p.get("type") == "image"
        else p for p in content
    ]  # fmt: skip
    return {**message, "content": parts}


def _rows(episode: _Episode, options: DatasetOptions, split: str) -> Iterator[dict[str, Any]]:
    """The rows of one episode, in step order, filtered as ``options`` ask."""
    steps = [s for s in read_steps(episode.run_dir / "steps.jsonl") if s.get("action")]
    summary = episode.summary
    exchanges = (episode.run_dir / "exchanges.jsonl").is_file()
    requests: Iterable[list[Message]]
    decoded: dict[str, bytes] = {}  # an image is sent again as history: decoded once
    if exchanges:  # a model pilot: its own requests, and its own replies as recorded labels
        recorded = _recorded_exchanges(episode.run_dir, decoded)
        steps = [s for s in steps if s["step"] in recorded]
        requests = [recorded[s["step"]][0] for s in steps]
        labels = [_model_label(s, recorded[s["step"]][1], summary, options, episode.run_dir)
                  for s in steps]  # fmt: skip
    else:
        labels_from = _own_teacher(options.labels, str(summary.get("pilot")), steps)
        labels = [_label(s, labels_from, options.reply, episode.run_dir) for s in steps]
        requests = _flown_again(episode, steps, [reply for reply, _, _ in labels], options)
    pilot = str(summary.get("pilot"))

    def image(part: Mapping[str, Any]) -> bytes:
        url = part["image_url"]["url"]
        if url not in decoded:
            decoded[url] = _image_bytes(url)
        return decoded[url]

    for step, request, (reply, action, teacher) in zip(steps, requests, labels, strict=True):
        if options.drop_shielded and step.get("shield"):
            continue
        chat, images = local_chat(request, image)
        yield {
            "messages": chat,
            "images": [{"bytes": data, "path": None} for data in images],
            "reply": reply,
            "action": action,
            "teacher": teacher or pilot,
            "pilot": pilot,
            "scenario": str(summary.get("scenario")),
            "seed": int(summary.get("seed") or 0),
            "cave": episode.cave,
            "episode": str(episode.run_dir),
            "step": int(step["step"]),
            "success": bool(summary.get("success")),
            "termination": str(summary.get("termination")),
            "shielded": bool(step.get("shield")),
            "detail": _detail(request),
            "split": split,
        }


def _detail(request: Sequence[Mapping[str, Any]]) -> str | None:
    """The detail the request's images are sent with (`VLMOptions.detail`), if any."""
    for message in request:
        for part in message["content"] if isinstance(message["content"], list) else ():
            if part["type"] == "image_url":
                return part["image_url"].get("detail")
    return None


def _flown_again(
    episode: _Episode, steps: list[dict[str, Any]], replies: list[str], options: DatasetOptions
) -> Iterator[list[Message]]:
    """The requests of an episode flown again (`cavenav.training.replay`).

    Raises:
        ConfigError: it cannot be, naming the run folder and why.
    """
    try:
        cave = recorded_cave(episode.scenario, episode.summary)
        config = recorded_config(episode.summary)
        yield from recorded_requests(cave, config, steps, replies, options.vlm)
    except ConfigError as exc:
        raise ConfigError(f"{episode.run_dir}: {exc}") from None


def _model_label(
    step: Mapping[str, Any],
    reply: str,
    summary: Mapping[str, Any],
    options: DatasetOptions,
    where: Path,
) -> tuple[str, str, str]:
    """(reply, action, who) for a model pilot's step: its raw reply, or its teacher's."""
    if options.labels == "teacher":
        return _label(step, "teacher", options.reply, where)
    try:
        action = parse_reply(reply).action_text
    except ActionError:
        action = str(step["action"])
    return reply, action, str(summary.get("pilot"))


# --------------------------------------------------------------------------- export


def _datasets() -> Any:  # noqa: ANN401 - the module
    try:
        import datasets
        import pyarrow.parquet  # noqa: F401 - what writes the shards
    except ImportError as exc:
        raise DependencyError(
            f"cavenav dataset needs datasets ({exc}); install with: pip install 'cavenav[train]'"
        ) from None
    return datasets


def features() -> Any:  # noqa: ANN401 - a datasets.Features
    """The dataset's columns, as datasets types them."""
    datasets = _datasets()
    text, part = datasets.Value("string"), {"type": datasets.Value("string")}
    return datasets.Features(
        {
            "messages": datasets.List(
                {"role": text, "content": datasets.List({**part, "text": text})}
            ),
            "images": datasets.List(datasets.Image()),
            "reply": text,
            "action": text,
            "teacher": text,
            "pilot": text,
            "scenario": text,
            "seed": datasets.Value("int64"),
            "cave": text,
            "episode": text,
            "step": datasets.Value("int64"),
            "success": datasets.Value("bool"),
            "termination": text,
            "shielded": datasets.Value("bool"),
            "detail": text,
        }
    )


class _Shards:
    """One split's rows, written a shard at a time under a partial name (``.partial-``),
    renamed ``SPLIT-00000-of-00003.parquet`` once every shard is in."""

    def __init__(self, folder: Path, split: str, types: Any, rows: int):  # noqa: ANN401
        self.folder, self.split, self.types, self.size = folder, split, types, rows
        self.pending: list[dict[str, Any]] = []
        self.written: list[Path] = []
        self.count = 0

    def add(self, row: dict[str, Any]) -> None:
        self.pending.append(row)
        self.count += 1
        if len(self.pending) >= self.size:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pylist(
            [self.types.encode_example(row) for row in self.pending], schema=self.types.arrow_schema
        )
        path = self.folder / f".partial-{self.split}-{len(self.written):05d}.parquet"
        self.written.append(path)
        pq.write_table(table, path)
        self.pending = []

    def finish(self) -> list[str]:
        """Give every shard its final name; the names, relative to the dataset."""
        self.flush()
        names = []
        for k, path in enumerate(self.written):
            name = f"{self.split}-{k:05d}-of-{len(self.written):05d}.parquet"
            os.replace(path, self.folder / name)
            names.append(f"data/{name}")
        return names


@dataclass(frozen=True)
class Export:
    """What an export wrote: the folder, rows per split, episodes used and skipped, time."""

    out: Path
    rows: dict[str, int]
    episodes: int
    skipped: dict[str, int]
    seconds: float
    card: dict[str, Any]

    @property
    def decisions_per_s(self) -> float:
        return sum(self.rows.values()) / max(self.seconds, 1e-9)


def _validation_caves(caves: Sequence[str], share: float) -> set[str]:
    """The caves held out: ``share`` of them, at least one where there are two or more,
    chosen by a hash of their names (the same caves on every machine and every run)."""
    ordered = sorted(set(caves), key=lambda cave: hashlib.sha256(cave.encode()).hexdigest())
    count = round(share * len(ordered))
    if share > 0 and len(ordered) >= 2:
        count = min(max(count, 1), len(ordered) - 1)
    return set(ordered[:count])


def _gather(
    sources: Sequence[Path], options: DatasetOptions
) -> tuple[list[_Episode], list[dict[str, Any]], dict[str, int]]:
    """Every episode to export, what each source is, and the episodes left out (why).

    Raises:
        ConfigError: a source that is no sweep or run folder, sources flown with
            different settings (unless allowed), or nothing to export.
    """
    episodes, about, skipped = [], [], {"unfinished": 0, "unsuccessful": 0}
    for source in sources:
        found, described = _episodes_of(Path(source))
        skipped["unfinished"] += described["grid"] - len(found)
        kept = [e for e in found if e.summary.get("success") or not options.successful_only]
        skipped["unsuccessful"] += len(found) - len(kept)
        about.append({"path": str(source), **described, "episodes": len(kept)})
        episodes += kept
    if not episodes:
        raise ConfigError(
            "no episode to export: "
            + ", ".join(f"{k} {v}" for k, v in skipped.items())
            + " (--episodes all keeps unsuccessful ones)"
        )
    settings: dict[str, _Episode] = {}
    prompts: dict[str, _Episode] = {}
    for episode in episodes:
        settings.setdefault(episode.settings, episode)
        prompt = episode.system_prompt
        if prompt is not None:
            prompts.setdefault(prompt, episode)
    for differing in (settings, prompts):
        if len(differing) > 1 and not options.allow_mixed:
            first, other = list(differing.values())[:2]
            raise ConfigError(
                f"{first.run_dir} and {other.run_dir} were flown with different settings or "
                "prompts; export them apart, or pass --allow-mixed"
            )
    return episodes, about, skipped


def export_dataset(
    sources: Sequence[Path], out: Path, options: DatasetOptions | None = None,
    progress: Any = None,  # noqa: ANN401 - called with each row's count, e.g. a progress bar
) -> Export:  # fmt: skip
    """Write the dataset of ``sources`` (sweep and run folders) to ``out``.

    Raises:
        ConfigError: bad sources (see `_gather`), an ``out`` that is not empty, an
            episode that cannot be flown again.
        RecordingError: ``out`` cannot be written (a full disk); no card is written.
        DependencyError: datasets is missing.
    """
    options = options or DatasetOptions()
    types = features()
    episodes, about, skipped = _gather(sources, options)
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"{out} exists and is not an empty folder: a dataset starts empty")
    held_out = _validation_caves([e.cave for e in episodes], options.validation)
    started, made = time.perf_counter(), not out.exists()
    try:
        (out / "data").mkdir(parents=True, exist_ok=True)
        shards = {s: _Shards(out / "data", s, types, options.shard_rows)
                  for s in ("train", "validation")}  # fmt: skip
        for episode in episodes:
            split = "validation" if episode.cave in held_out else "train"
            for row in _rows(episode, options, split):
                shards[row.pop("split")].add(row)
                if progress:
                    progress(1)
        files = {split: s.finish() for split, s in shards.items()}
    except BaseException as exc:  # a full disk, an episode refused, Ctrl-C: none of it stays
        _remove_partial(out, made)
        if isinstance(exc, OSError):
            raise RecordingError.cannot_write(out, exc) from None
        raise
    rows = {split: s.count for split, s in shards.items()}
    card = _card_data(episodes, about, skipped, rows, options, held_out, files)
    seconds = time.perf_counter() - started
    card["export_s"] = round(seconds, 2)
    try:
        write_json(out / "cavenav_dataset.json", card)
        write_atomic(out / "README.md", dataset_card(card))  # last: the export is whole
    except OSError as exc:
        raise RecordingError.cannot_write(out, exc) from None
    return Export(out, rows, len(episodes), skipped, seconds, card)


def _remove_partial(out: Path, made: bool) -> None:
    """Remove what a stopped export wrote: its partial shards, and the folders it made."""
    for partial in (out / "data").glob(".partial-*"):
        partial.unlink(missing_ok=True)
    for folder in (out / "data", out) if made else (out / "data",):
        with contextlib.suppress(OSError):
            folder.rmdir()  # only if empty


def _card_data(
    episodes: Sequence[_Episode],
    about: list[dict[str, Any]],
    skipped: dict[str, int],
    rows: dict[str, int],
    options: DatasetOptions,
    held_out: set[str],
    files: dict[str, list[str]],
) -> dict[str, Any]:
    """cavenav_dataset.json: where the rows came from and how they were made."""
    first = episodes[0]
    config = dict(first.summary.get("config") or {})
    return {
        "format": FORMAT,
        "cavenav_version": __version__,
        "scenario_set": first.summary.get("scenario_set", SCENARIO_SET),
        "sources": about,
        "pilots": sorted({str(e.summary.get("pilot")) for e in episodes}),
        "scenarios": sorted({str(e.summary.get("scenario")) for e in episodes}),
        "caves": {"train": len({e.cave for e in episodes} - held_out), "validation": len(held_out)},
        "validation_caves": sorted(held_out),
        "episodes": len(episodes),
        "skipped_episodes": skipped,
        "rows": rows,
        "files": files,
        "labels": options.labels,
        "reply": options.reply,
        "successful_only": options.successful_only,
        "drop_shielded": options.drop_shielded,
        "prompt": {k: v for k, v in asdict(options.vlm).items() if k in _PROMPT_OPTIONS},
        "settings": {k: config.get(k) for k in ("sensors", "rules", "body", "current", "shield")},
    }


# The VLM options that shape a request made again: a model trained on the rows must be
# flown with them (`cavenav finetune` writes them into its model card).
_PROMPT_OPTIONS = ("history", "prompt_file", "structured", "map_image", "energy_prompt",
                   "image_format", "jpeg_quality", "image_size", "detail")  # fmt: skip

"""Sweeps: one pilot over a grid of caves (scenario x seed), resumable, one folder.

DIR/
  sweep.json      the configuration, written once; a re-run must match it
  episodes/       one run folder per episode, named SCENARIO-seedNNNN
  results.csv     one row per episode (see `cavenav.evaluation.results.COLUMNS`)
  aggregate.json  per scenario and overall: success rate with its Wilson interval, ...
  report/         index.html and one page per episode

Re-running the same command skips every episode whose summary says ``finished`` and
flies the others again from scratch: never started, interrupted by Ctrl-C, killed, or
crashed with an error. An episode that fails is recorded with its error in its summary
and never stops the sweep; a sweep folder that cannot be written (a full disk) does, with
a `RecordingError`, keeping every record whole.

The folder is held by one sweep at a time (`_only_sweep_in`), and its pool workers hold
``episodes/`` as long as they live (`hold_episodes`): a rerun never flies beside the
workers of a sweep that was killed.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager, nullcontext, suppress
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from cavenav import SCENARIO_SET, __version__
from cavenav.core.errors import (
    CavenavError,
    CavenavWarning,
    ConfigError,
    RecordError,
    RecordingError,
)
from cavenav.core.types import STEP_BUDGET
from cavenav.episode.loop import run_episode
from cavenav.episode.records import read_summary, read_sweep_file
from cavenav.episode.run_folder import prepare_root, write_atomic, write_json
from cavenav.episode.settings import (
    FRAME_MODES,
    SENSOR_FIELDS,
    VIDEO_MODES,
    EpisodeConfig,
    configured,
)
from cavenav.evaluation.results import ResultRow, episode_row, outcome, read_episode, write_results
from cavenav.pilots.base import Pilot
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.world.scenarios import (
    SCENARIOS,
    Difficulty,
    Scenario,
    check_scenario,
    load_scenario,
)

__all__ = [
    "FRAMES",
    "MAX_EPISODES",
    "EpisodeJob",
    "EpisodeWorker",
    "Executor",
    "SweepConfig",
    "check_grid",
    "hold_episodes",
    "parse_seeds",
    "plan",
    "prepare",
    "read_rows",
    "read_sweep",
    "run_sweep",
]

FRAMES = tuple(FRAME_MODES)  # what a sweep keeps of each step's images
FORMAT = 1
# Pilot settings that change how a request travels, not what the pilot does: a resumed
# sweep may change them (a longer timeout, more retries, a reply cache).
_TRANSPORT_OPTIONS = ("timeout", "retries", "cache", "device", "api_key_env")
# The largest grid a sweep flies (scenarios x seeds). sweep.json lists every seed and
# results.csv holds a row per episode, so the grid must fit in memory and on a page:
# 100,000 episodes of the geometric pilot are about a day on 16 cores. A larger study is
# several sweeps (e.g. by seed range), each resumable on its own.
MAX_EPISODES = 100_000
# How long a new sweep waits for the pool workers of a killed one to die before refusing
# the folder: they die with their parent within milliseconds (`executors._pool_worker`).
LEFTOVER_GRACE_S = 5.0
# Failures to write that stop the whole sweep: the next episode would fail the same way.
_FOLDER_FAULTS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


@dataclass(frozen=True, init=False)
class SweepConfig:
    """What a sweep flies; everything that changes its results, nothing about how it runs.

    Attributes:
        scenarios: family names (S1..S5, crawl, maze, long) or scenario-file paths.
        seeds: caves drawn from each family (development seeds below 1000, test split
            from 1000; see `cavenav.world.scenarios.HELD_OUT_SEEDS`).
        pilot: which pilot flies every episode.
        settings: every episode's settings; its difficulty knobs are each set on the
            families that have them (`difficulty_for`).
        video: which episodes get an episode.mp4 (`VIDEO_MODES`).
        trials: flights of each cave, for pilots that sample (a VLM at a temperature
            above 0, the random pilot). Each trial draws its own sensor noise and, for
            the random pilot, its own actions; the first is the flight a sweep of one
            trial makes. A deterministic pilot flies every trial alike.
    """

    scenarios: tuple[str, ...]
    seeds: tuple[int, ...]
    pilot: PilotSpec
    settings: EpisodeConfig
    video: str = "none"
    trials: int = 1

    def __init__(
        self,
        scenarios: Sequence[str],
        seeds: Sequence[int],
        pilot: PilotSpec | None = None,
        settings: EpisodeConfig | None = None,
        **fields: Any,
    ) -> None:
        """``fields`` are `EpisodeConfig` fields set over ``settings``, ``frames``, a
        `FRAMES` mode, and ``sensors``, a mapping laid out as sweep.json's "sensors" (the
        keyword scripts passed before `EpisodeConfig` existed):
        ``SweepConfig(("S1",), (0,), steps=6, frames="none")``.

        Raises:
            ConfigError: an empty grid, one over `MAX_EPISODES`, a bad frames mode, an
                unknown sensors key, or a difficulty knob that applies to none of the
                scenarios.
            TypeError: a name that is not a settings field.
        """
        frames = fields.pop("frames", None)
        object.__setattr__(self, "video", fields.pop("video", "none"))
        object.__setattr__(self, "trials", fields.pop("trials", 1))
        sensors = dict(fields.pop("sensors", {}))
        unknown = set(sensors) - set(SENSOR_FIELDS)
        if unknown:
            raise ConfigError(f"sensors: unknown key(s) {', '.join(sorted(unknown))}")
        settings = configured(settings, **sensors, **fields)
        object.__setattr__(self, "scenarios", tuple(scenarios))
        object.__setattr__(self, "seeds", tuple(seeds))
        object.__setattr__(self, "pilot", pilot or PilotSpec())
        object.__setattr__(self, "settings", settings.with_frames(frames or settings.frames))
        self._check()

    def _check(self) -> None:
        if self.video not in VIDEO_MODES:
            raise ConfigError(
                f"--video must be one of {', '.join(VIDEO_MODES)}, not '{self.video}'"
            )
        if self.video != "none" and self.settings.frames == "none":
            raise ConfigError("--video needs the frames it is made of: --frames all or png")
        if not self.scenarios:
            raise ConfigError("give at least one scenario, e.g. --scenarios S1,S2")
        if not self.seeds:
            raise ConfigError("give at least one seed, e.g. --seeds 0-19")
        if not isinstance(self.trials, int) or self.trials < 1:
            raise ConfigError(f"--trials must be a whole number of 1 or more, not {self.trials}")
        if self.episodes > MAX_EPISODES:
            trials = f" x {self.trials} trials" if self.trials > 1 else ""
            raise ConfigError(
                f"{len(self.scenarios)} scenarios x {len(self.seeds)} seeds{trials} is more "
                f"than the {MAX_EPISODES:,} episodes a sweep flies; split it into several sweeps"
            )
        files = [s for s in self.scenarios if s not in SCENARIOS]
        for knob in self.settings.difficulty:
            if not files and not any(knob in SCENARIOS[s].knobs for s in self.scenarios):
                raise ConfigError(
                    f"difficulty knob {knob} applies to none of {', '.join(self.scenarios)}"
                )

    @property
    def episodes(self) -> int:
        """Episodes in the grid: scenarios x seeds x trials."""
        return len(self.scenarios) * len(self.seeds) * self.trials

    # The settings under the names a SweepConfig gave them before it held an
    # `EpisodeConfig`, read-only, for the scripts that read them.

    @property
    def steps(self) -> int | None:
        """Step budget; None gives each scenario its own."""
        return self.settings.max_steps

    @property
    def stuck_after(self) -> int | None:
        """Steps without headway that end an episode as stuck; None never does."""
        return self.settings.stuck_after

    @property
    def shield(self) -> bool:
        """Whether the safety shield flies every episode."""
        return self.settings.shield

    @property
    def frames(self) -> str:
        """What each step keeps: "all" (PNG and EXR), "png" (no EXR) or "none"."""
        return self.settings.frames

    @property
    def difficulty(self) -> Mapping[str, float]:
        """`Difficulty` knobs, each set on the families that have it."""
        return self.settings.difficulty

    @property
    def sensors(self) -> dict[str, Any]:
        """Sounder, depth_max_m, an "optics" table of flag overrides and, where given,
        "resolution" and "sounder_resolution" ([width, height]), as in sweep.json."""
        return self.settings.to_dict()["sensors"]

    def difficulty_for(self, scenario: str) -> Difficulty:
        """The knobs ``scenario`` takes: a sweep over several families sets each knob on
        the families that have it (constriction_m on S1 and S2, bend_deg on S4, ...)."""
        knobs = Difficulty.from_dict(self.settings.difficulty)
        family = SCENARIOS.get(scenario)
        if family is None:  # a scenario file: its family, if any, judges the knobs
            return knobs
        return Difficulty.from_dict({k: v for k, v in knobs.to_dict().items() if k in family.knobs})

    def to_dict(self) -> dict[str, Any]:
        """sweep.json."""
        return {
            "format": FORMAT,
            "scenarios": list(self.scenarios),
            "seeds": list(self.seeds),
            "pilot": self.pilot.to_dict(),
            **self.settings.to_dict(),  # "episode", "difficulty", "sensors"
            **({"video": self.video} if self.video != "none" else {}),
            **({"trials": self.trials} if self.trials > 1 else {}),
            "created_at": datetime.now(UTC).isoformat(timespec="seconds"),
            "cavenav_version": __version__,
            "scenario_set": SCENARIO_SET,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SweepConfig:
        """The configuration a sweep.json describes (compare, report, resumed sweeps)."""
        pilot, episode = data["pilot"], dict(data["episode"])
        # A sweep begun before scenarios had budgets of their own and episodes could end
        # stuck: its 150 steps are the budget every scenario it could fly now gets by
        # default, and it never ended an episode stuck.
        if "stuck_after" not in episode:
            episode["stuck_after"] = None
            if episode["steps"] == STEP_BUDGET:
                episode["steps"] = None
        return cls(
            scenarios=tuple(data["scenarios"]),
            seeds=tuple(data["seeds"]),
            pilot=PilotSpec(
                pilot["name"],
                VLMOptions(**pilot.get("options", {})),
                pilot.get("recording"),
                pilot.get("policy"),
                pilot.get("policy_sha256"),
                pilot.get("teacher"),
            ),
            settings=EpisodeConfig.from_dict({**data, "episode": episode}),
            video=data.get("video", "none"),
            trials=data.get("trials", 1),
        )


@dataclass(frozen=True)
class EpisodeJob:
    """One cell of the grid: a cave (scenario, seed), which of its trials (None in a sweep
    of one trial a cave) and where its run folder goes."""

    scenario: str
    seed: int
    trial: int | None = None

    @property
    def episode(self) -> str:
        """The run folder's name: SCENARIO-seedNNNN, then -trialK in a sweep of several
        trials (a scenario file by its stem)."""
        stem = (
            Path(self.scenario).stem if self.scenario.lower().endswith(".toml") else self.scenario
        )
        trial = f"-trial{self.trial}" if self.trial is not None else ""
        return re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{stem}-seed{self.seed:04d}{trial}")

    def noise_seed(self, held: int | None = None) -> int:
        """Seeds the sensor noise: the episode's own seed (`pilot_seed`), or with ``held``
        (`EpisodeConfig.seed`) that for the first trial and one more for each
        other."""
        return self.pilot_seed if held is None else held + (self.trial or 1) - 1

    @property
    def pilot_seed(self) -> int:
        """Seeds the random pilot: the cave's seed for the first trial, then a draw of its
        own for each other (from the cave's seed and the trial, so it repeats)."""
        if self.trial is None or self.trial == 1:
            return self.seed
        return int(np.random.SeedSequence([self.seed, self.trial]).generate_state(1)[0])


def parse_seeds(text: str) -> tuple[int, ...]:
    """ "0-19", "3", "0,5,7-9" -> the seeds, in order, without repeats.

    Raises:
        ConfigError: naming the part that is not a seed or a range, or more seeds than
            `MAX_EPISODES` (refused before they are counted out one by one).
    """
    seeds: dict[int, None] = {}
    for part in (p.strip() for p in text.split(",")):
        match = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not match:
            raise ConfigError(
                f"--seeds: '{part}' is not a seed or a range; write e.g. 0-19 or 0,5,1000-1019"
            )
        first = int(match[1])
        last = int(match[2]) if match[2] else first
        if last < first:
            raise ConfigError(f"--seeds: the range '{part}' runs backwards")
        if last - first >= MAX_EPISODES:  # refused before it is counted out
            raise _too_many(text)
        seeds.update(dict.fromkeys(range(first, last + 1)))
        if len(seeds) > MAX_EPISODES:
            raise _too_many(text)
    return tuple(seeds)


def _too_many(seeds: str) -> ConfigError:
    return ConfigError(
        f"--seeds {seeds}: more than the {MAX_EPISODES:,} episodes a sweep flies; "
        "split it into several sweeps"
    )


def check_grid(config: SweepConfig) -> None:
    """Refuse a grid whose episodes could only crash, before anything is written: an
    unknown scenario, a scenario file that does not read, a difficulty knob that its
    family lacks or out of its range, a guideline in a cave with no centre line, two
    scenarios sharing run folders. Each is checked as its episodes would load it
    (`SweepConfig.difficulty_for`), in milliseconds: no cave is built
    (`cavenav.world.scenarios.check_scenario`).

    Raises:
        ConfigError, MeshError, ScenarioError: naming the scenario and what is wrong.
    """
    guideline = bool(config.settings.guideline)  # laid along a centre line
    for scenario in config.scenarios:
        check_scenario(scenario, config.difficulty_for(scenario), guideline)
    plan(config)


def plan(config: SweepConfig) -> list[EpisodeJob]:
    """Every episode of the grid, scenario by scenario, each cave's trials together.

    Raises:
        ConfigError: two scenarios would share run folders (two files with one name).
    """
    trials: list[int | None] = list(range(1, config.trials + 1)) if config.trials > 1 else [None]
    jobs = [
        EpisodeJob(s, seed, trial)
        for s in config.scenarios
        for seed in config.seeds
        for trial in trials
    ]
    names = [job.episode for job in jobs]
    if len(set(names)) != len(names):
        raise ConfigError("two scenarios of --scenarios share a name; rename one of the files")
    return jobs


def _identity(data: Mapping[str, Any]) -> dict[str, Any]:
    """The part of sweep.json a resumed sweep must match."""
    # What wrote it and when, and the videos: a resumed sweep may make more or fewer.
    stamps = ("created_at", "cavenav_version", "scenario_set", "video")
    same = {k: v for k, v in data.items() if k not in stamps}
    pilot = dict(same["pilot"])
    if "options" in pilot:
        pilot["options"] = {
            k: v for k, v in pilot["options"].items() if k not in _TRANSPORT_OPTIONS
        }
    same["pilot"] = pilot
    return same


def _first_difference(old: Any, new: Any, where: str = "") -> str:
    if isinstance(old, dict) and isinstance(new, dict):
        for key in dict.fromkeys([*old, *new]):
            if old.get(key) != new.get(key):
                return _first_difference(old.get(key), new.get(key), f"{where}.{key}".strip("."))
    return f"{where or 'configuration'}: {json.dumps(old)} there, {json.dumps(new)} now"


def _resume_hint(recorded: EpisodeConfig, wanted: EpisodeConfig) -> str:
    """The flag a sweep begun by an older cavenav needs to resume, where one does."""
    if recorded.stuck_after is None and wanted.stuck_after:
        return " (it was flown without stuck endings: add --stuck-after 0)"
    if recorded.seed is not None and wanted.seed is None:
        seed = recorded.seed
        return f" (its episodes drew their noise from seed {seed}: add --noise-seed {seed})"
    return ""


def prepare(config: SweepConfig, folder: Path) -> list[EpisodeJob]:
    """Create or reopen the sweep folder; the episodes still to fly.

    Raises:
        ConfigError: ``folder`` holds another sweep (naming the first difference), or
            something that is not a sweep.
        RecordingError: sweep.json cannot be written (a full disk).
    """
    folder = Path(folder)
    jobs = plan(config)
    settings = folder / "sweep.json"
    wanted = config.to_dict()
    if settings.is_file():
        flown, recorded = read_sweep(folder)  # a damaged one is one line, naming the field
        # Read back through SweepConfig, so that settings added since the sweep began
        # take the values it was flown with (no stuck endings, no map image).
        recorded = {**recorded, **flown.to_dict()}
        if _identity(recorded) != _identity(wanted):
            hint = _resume_hint(flown.settings, config.settings)
            raise ConfigError(
                f"{folder} holds a sweep with another configuration "
                f"({_first_difference(_identity(recorded), _identity(wanted))}); "
                f"re-run with the same options to resume it{hint}, or choose another --out"
            )
    elif folder.exists() and any(folder.iterdir()):
        raise ConfigError(f"{folder} is not empty and holds no sweep.json; choose another --out")
    else:
        try:
            (folder / "episodes").mkdir(parents=True, exist_ok=True)
            write_json(settings, wanted)
        except OSError as exc:
            raise RecordingError.cannot_write(folder, exc) from None
    return [job for job in jobs if not _finished(folder / "episodes" / job.episode)]


def _finished(run_dir: Path) -> bool:
    """Flown to an ending the pilot is answerable for: nothing to fly again on resume.

    Judged as its results row judges it (`episode_row`): an episode whose row would be
    an error or incomplete, a damaged record included, is flown again.
    """
    try:
        summary, steps = read_episode(run_dir)
    except RecordError:  # none yet, or damaged: fly it again
        return False
    return outcome(summary, steps) not in ("error", "incomplete")


class EpisodeWorker:
    """Flies a sweep's episodes in one process, keeping the process warm.

    A worker lives as long as the sweep: its compiled kernels, imports and the caves it
    built stay loaded between episodes. It is safe to call `fly` from several threads
    at once (``--concurrency``): each thread keeps its own pilot, and caves are shared.
    """

    def __init__(self, config: SweepConfig, folder: Path, caves_kept: int = 4):
        self.config = config
        self.folder = Path(folder)
        self._caves: dict[tuple[str, int], Scenario] = {}
        self._caves_kept = caves_kept
        self._lock = threading.Lock()
        self._local = threading.local()

    def _cave(self, job: EpisodeJob) -> Scenario:
        key = (job.scenario, job.seed)
        with self._lock:
            if key in self._caves:
                return self._caves[key]
        difficulty = self.config.difficulty_for(job.scenario)
        cave = load_scenario(job.scenario, job.seed, difficulty=difficulty)
        cave = self.config.settings.cave(cave)  # with the guideline the sweep asks for
        with self._lock:
            self._caves[key] = cave
            while len(self._caves) > self._caves_kept:
                del self._caves[next(iter(self._caves))]
        return cave

    def _pilot(self, job: EpisodeJob) -> Pilot:
        spec = self.config.pilot
        if spec.name == "random":  # seeded per cave, so every episode is reproducible
            return spec.build(seed=job.pilot_seed)
        if getattr(self._local, "pilot", None) is None:
            self._local.pilot = spec.build()
        return self._local.pilot

    def episode_config(self, cave: Scenario, job: EpisodeJob | None = None) -> EpisodeConfig:
        """The `EpisodeConfig` of this sweep's episode in ``cave`` (``job``: its trial's)."""
        settings = self.config.settings
        return settings.for_episode(cave, job.noise_seed(settings.seed) if job else 0)

    def fly(self, job: EpisodeJob) -> ResultRow:
        """Fly one episode into a fresh run folder, with its episode.mp4 where the sweep's
        ``video`` asks for one; its results row.

        Any error is recorded in the run folder's summary (status "crashed", "error")
        and returned in the row: one episode never stops the sweep, unless the sweep
        folder cannot be written.

        Raises:
            RecordingError: the run folder cannot be written (a full disk): the episode is
                recorded as crashed where that can still be written, else its summary
                stays the last whole one ("running"); never "finished". Every episode
                after it would fail the same way, so the sweep stops.
        """
        run_dir = self.folder / "episodes" / job.episode
        try:
            if run_dir.exists():
                shutil.rmtree(run_dir)  # an interrupted or crashed attempt: start again
            cave = self._cave(job)
            run_episode(cave, self._pilot(job), self.episode_config(cave, job), run_dir)
        except Exception as exc:  # noqa: BLE001 - recorded, and the sweep goes on
            fault = _folder_fault(job, exc)
            try:
                record_error(run_dir, job, f"{type(exc).__name__}: {exc}", traceback.format_exc())
            except RecordingError:
                if fault is None:
                    raise
            if fault is not None:  # the first cause, naming the file
                raise fault from None
        row = episode_row(run_dir, self.folder)
        row["trial"] = job.trial
        wanted = {"all": True, "failures": row["outcome"] != "success"}.get(self.config.video)
        if wanted and row.get("status") == "finished":
            _video(run_dir)
        return row


def _video(run_dir: Path) -> None:
    """``run_dir/episode.mp4``, made where the episode flew (`cavenav.episode.video`); a
    video that cannot be made is a warning, not a lost episode, unless the disk is full.

    Raises:
        RecordingError: it cannot be written (the sweep stops, as for any record).
    """
    from cavenav.episode.video import write_video

    try:
        write_video(run_dir)
    except RecordingError:
        raise
    except CavenavError as exc:
        warnings.warn(f"no video of {run_dir.name}: {exc}", CavenavWarning, stacklevel=2)


def record_error(run_dir: Path, job: EpisodeJob, error: str, trace: str = "") -> None:
    """Mark ``run_dir`` as crashed with ``error``, keeping whatever it already holds.

    Raises:
        RecordingError: it cannot be written (a full disk); each file is whole or absent.
    """
    path = run_dir / "summary.json"
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        try:
            summary = read_summary(path)
        except RecordError:
            summary = {"scenario": job.scenario, "seed": job.seed, "termination": None}
        summary.update(status="crashed", error=error)
        write_json(path, summary)
        if trace:
            write_atomic(run_dir / "error.txt", trace)
    except OSError as exc:
        raise RecordingError.cannot_write(run_dir, exc) from None


def _folder_fault(job: EpisodeJob, error: Exception) -> RecordingError | None:
    """``error`` as the sweep's reason to stop: its run folder cannot be written, or a
    disk it needs is full or read-only (the cave cache, the reply cache, /tmp).

    The episode loop names its run folder itself (a `RecordingError`); a raw `OSError`
    here came from elsewhere, so it names its own file, never the run folder.
    """
    if isinstance(error, RecordingError):
        return error
    if isinstance(error, OSError) and error.errno in _FOLDER_FAULTS:
        where = error.filename or f"a file while flying {job.episode}"
        return RecordingError.cannot_write(where, error)
    return None


class Executor(Protocol):
    """Runs episode jobs somewhere (`cavenav.evaluation.executors`)."""

    def run(
        self,
        config: SweepConfig,
        folder: Path,
        jobs: Sequence[EpisodeJob],
        done: Callable[[ResultRow], None],
    ) -> None:
        """Fly every job, calling ``done`` with each results row as it arrives."""


def run_sweep(
    config: SweepConfig,
    folder: Path,
    executor: Executor,
    done: Callable[[ResultRow], None] | None = None,
    started: Callable[[int, int], None] | None = None,
) -> list[ResultRow]:
    """Fly what is left of the sweep in ``folder``; write results.csv and aggregate.json.

    Args:
        done: called with each episode's results row as it finishes.
        started: called once with (episodes left to fly, episodes in the grid).

    Returns:
        Every episode's row, finished earlier or now. On Ctrl-C, or when the folder
        cannot be written, the tables are still written where they can be (the episodes
        in flight count as incomplete) before the exception goes on.

    Raises:
        ConfigError, MeshError, ScenarioError: the grid is refused (`check_grid`), or the
            folder is held by another sweep or its workers; nothing was written.
        RecordingError: the sweep folder cannot be written (a full disk): the sweep stops.
    """
    folder = Path(folder)
    check_grid(config)
    opened = getattr(executor, "opened", nullcontext)  # Ray: reached before any write
    with opened(), _only_sweep_in(folder):
        jobs = prepare(config, folder)
        if started:
            started(len(jobs), config.episodes)
        try:
            executor.run(config, folder, jobs, done or (lambda row: None))
        except BaseException:
            # The cause goes on, not a full disk's echo nor a record damaged meanwhile.
            with suppress(OSError, CavenavError):
                read_rows(folder)
            raise
        try:
            return read_rows(folder)
        except OSError as exc:
            raise RecordingError.cannot_write(folder, exc) from None


@contextmanager
def _only_sweep_in(folder: Path) -> Iterator[None]:
    """Hold ``folder`` for this sweep: a second sweep started into it (the same command in
    another terminal) would fly the same episodes into the same run folders.

    The lock is the kernel's (flock on the folder itself): a killed sweep releases it.
    Its pool workers hold episodes/ (`hold_episodes`) and die with it; until the last of
    them is gone, which takes milliseconds, the folder is not flown into.

    Raises:
        ConfigError: another sweep holds ``folder``, or the workers of a killed one still
            live after `LEFTOVER_GRACE_S`.
    """
    prepare_root(folder)
    fd = os.open(folder, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(
                f"another sweep is writing into {folder}; wait for it to end, or choose "
                "another --out"
            ) from None
        _wait_for_leftovers(folder)
        yield
    finally:
        os.close(fd)  # releases the lock


def hold_episodes(folder: Path) -> None:
    """Hold ``folder``'s episodes/ for as long as this process lives (a pool worker):
    shared with the sweep's other workers, exclusive of a sweep started after a kill.

    The descriptor that holds it is left open on purpose: the process ending lets go.
    """
    fcntl.flock(os.open(Path(folder) / "episodes", os.O_RDONLY), fcntl.LOCK_SH)


def _wait_for_leftovers(folder: Path) -> None:
    """Return once no worker of an earlier sweep holds ``folder``'s episodes/.

    Raises:
        ConfigError: some still do after `LEFTOVER_GRACE_S`.
    """
    if not (folder / "episodes").is_dir():
        return
    fd = os.open(folder / "episodes", os.O_RDONLY)
    try:
        deadline = time.monotonic() + LEFTOVER_GRACE_S
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise ConfigError(
                        f"processes of an earlier sweep into {folder} still hold its "
                        "episodes; wait for them to end (or end them), then run it again"
                    ) from None
                time.sleep(0.05)
    finally:
        os.close(fd)  # lets go at once: this sweep's own workers share it


def read_sweep(folder: Path) -> tuple[SweepConfig, dict[str, Any]]:
    """The configuration of the sweep in ``folder`` and its sweep.json as written.

    Raises:
        ConfigError: ``folder`` holds no readable sweep.json.
    """
    path = Path(folder) / "sweep.json"
    if not path.is_file():
        raise ConfigError(f"{folder} is not a sweep folder: no sweep.json")
    data = read_sweep_file(path)  # a damaged one names the field
    try:
        return SweepConfig.from_dict(data), data
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{path} cannot be read as a sweep: {exc}") from None


def read_rows(folder: Path, write: bool = True) -> list[ResultRow]:
    """Every episode's results row, in grid order; with ``write``, results.csv and
    aggregate.json are (re)written from them. Episodes never started are "incomplete"."""
    folder = Path(folder)
    config, meta = read_sweep(folder)
    rows = []
    for job in plan(config):
        row = episode_row(folder / "episodes" / job.episode, folder)
        if row["status"] in ("missing", "damaged"):  # no summary to say whose it is
            row["scenario"], row["pilot"] = job.scenario, config.pilot.label
        row["seed"] = job.seed  # a mesh file's summary has none, yet its episodes pair by it
        row["trial"] = job.trial
        rows.append(row)
    if write:
        write_results(folder, rows, meta)
    return rows

"""The Ray executor says what went wrong: a head it cannot reach, workers that die.

Starting a Ray cluster costs 10-14 s, so these tests put a stand-in `ray` module in its
place (the executor imports Ray when it runs) and script what each episode meets: a
row, a task that fails, an actor that dies, a folder that cannot be written. The one
sweep on a real local cluster is `test_sweep.test_a_small_grid_runs_on_a_local_ray_instance`.
"""

from __future__ import annotations

import json
import sys
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from cavenav.core.errors import ConfigError, DependencyError, RecordingError
from cavenav.evaluation.executors import RayCluster
from cavenav.evaluation.sweep import EpisodeJob, SweepConfig, run_sweep

CONFIG = SweepConfig(scenarios=("S1",), seeds=(0, 1, 2, 3), steps=6, frames="none")
JOBS = [EpisodeJob("S1", seed) for seed in CONFIG.seeds]


class RayError(Exception):
    """Stand-ins for `ray.exceptions`: the executor tells them apart by class."""


class ActorDiedError(RayError):
    pass


class RayTaskError(RayError):
    def __init__(self, cause: BaseException):
        super().__init__(f"{type(cause).__name__}: {cause}\ntraceback follows")
        self.cause = cause


DIE = "die"  # a fate: the actor flying this episode dies (out of memory, node lost)


class FakeRay(types.ModuleType):
    """Enough of Ray for `RayCluster`: actors fly episodes as ``fates`` says.

    ``fates`` maps an episode to its fate: `DIE`, an exception the task raises, or
    nothing (the episode finishes). A dead actor fails every later call, as Ray's do.
    """

    def __init__(self, fates: dict[str, object] | None = None, cpus: int = 2, init_error=None):
        super().__init__("ray")
        self.fates = fates or {}
        self.cpus = cpus
        self.init_error = init_error
        self.initialized = False
        self.inits: list[str] = []
        self.shutdowns = 0
        self.flown: list[tuple[int, str]] = []  # (actor, episode), in launch order
        self.exceptions = types.SimpleNamespace(RayError=RayError, ActorDiedError=ActorDiedError)

    def is_initialized(self) -> bool:
        return self.initialized

    def init(self, address: str, **_: object) -> None:
        self.inits.append(address)
        if self.init_error:
            raise self.init_error
        self.initialized = True

    def shutdown(self) -> None:
        self.shutdowns += 1
        self.initialized = False

    def cluster_resources(self) -> dict[str, float]:
        return {"CPU": float(self.cpus)}

    def remote(self, **_: object) -> Callable[[type], Any]:
        ray = self

        class Actor:
            count = 0

            def __init__(self) -> None:
                self.number, Actor.count = Actor.count, Actor.count + 1
                self.dead = False
                self.fly = types.SimpleNamespace(remote=self._fly)

            @classmethod
            def remote(cls, config: SweepConfig, folder: str) -> Actor:
                return cls()

            def _fly(self, job: EpisodeJob) -> Callable[[], dict[str, Any]]:
                ray.flown.append((self.number, job.episode))

                def result() -> dict[str, Any]:
                    fate = ray.fates.get(job.episode)
                    if self.dead or fate == DIE:
                        self.dead = True
                        raise ActorDiedError("The actor died unexpectedly before finishing")
                    if isinstance(fate, BaseException):
                        raise RayTaskError(fate)
                    return {"episode": job.episode, "status": "finished"}

                return result

        return lambda cls: Actor

    def wait(self, refs: list, num_returns: int) -> tuple[list, list]:
        return refs[:num_returns], refs[num_returns:]

    def get(self, ref: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        return ref()


def fly(ray: FakeRay, folder: Path, monkeypatch: pytest.MonkeyPatch, **cluster) -> list[dict]:
    monkeypatch.setitem(sys.modules, "ray", ray)
    rows: list[dict] = []
    RayCluster("auto", **cluster).run(CONFIG, folder, JOBS, rows.append)
    return rows


def recorded_error(folder: Path, episode: str) -> str:
    summary = json.loads((folder / "episodes" / episode / "summary.json").read_text())
    assert summary["status"] == "crashed"
    return summary["error"]


def test_a_head_that_cannot_be_reached_is_one_line_naming_the_address(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ray = FakeRay(init_error=ConnectionError("ray client connection timeout"))
    monkeypatch.setitem(sys.modules, "ray", ray)
    rows: list[dict] = []
    with pytest.raises(ConfigError) as refused:
        RayCluster("ray://10.0.0.9:10001").run(CONFIG, tmp_path, JOBS, rows.append)
    assert str(refused.value) == (
        "cannot reach Ray at 'ray://10.0.0.9:10001': ray client connection timeout"
    )
    assert refused.value.__cause__ is None and refused.value.__suppress_context__
    assert rows == [] and ray.flown == [] and ray.shutdowns == 0


def test_an_unreachable_address_fails_at_once_with_real_ray(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray", reason="Ray is an extra: pip install 'cavenav[ray]'")
    # Port 1 has no Ray head. cavenav[ray] installs Ray without its client, which refuses
    # the ray:// form at once; where ray[client] is installed, Ray retries for tens of
    # seconds before its "connection timeout". Either way: one line, nothing flown.
    with pytest.raises(ConfigError, match=r"^cannot reach Ray at 'ray://127\.0\.0\.1:1': ") as e:
        RayCluster("ray://127.0.0.1:1").run(CONFIG, tmp_path, JOBS[:1], lambda row: None)
    assert "\n" not in str(e.value)
    assert not ray.is_initialized()
    assert not (tmp_path / "episodes").exists()  # nothing flown
    # A sweep reaches Ray before it writes anything: no sweep.json, no empty tables.
    with pytest.raises(ConfigError, match="cannot reach Ray"):
        run_sweep(CONFIG, tmp_path / "sweep", RayCluster("ray://127.0.0.1:1"))
    assert not (tmp_path / "sweep").exists()


def test_without_ray_installed_the_error_gives_the_install_command(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(DependencyError, match=r"pip install 'cavenav\[ray\]'"):
        RayCluster("auto").run(CONFIG, tmp_path, JOBS, lambda row: None)


def test_a_dying_worker_takes_only_its_episode_the_others_fly_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ray = FakeRay({"S1-seed0000": DIE}, cpus=2)
    rows = fly(ray, tmp_path, monkeypatch)
    assert [(r["episode"], r["status"]) for r in rows] == [
        ("S1-seed0000", "crashed"),
        ("S1-seed0001", "finished"),
        ("S1-seed0002", "finished"),
        ("S1-seed0003", "finished"),
    ]
    assert recorded_error(tmp_path, "S1-seed0000") == (
        "Ray: ActorDiedError: The actor died unexpectedly before finishing"
    )
    # The dead actor (0) is sent nothing more: actor 1 flies the rest.
    assert ray.flown == [(0, "S1-seed0000"), (1, "S1-seed0001"), (1, "S1-seed0002"),
                         (1, "S1-seed0003")]  # fmt: skip
    assert ray.inits == ["auto"] and ray.shutdowns == 1  # started here, stopped here


def test_when_every_worker_has_died_the_sweep_stops_and_says_how_many_are_left(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ray = FakeRay({"S1-seed0000": DIE, "S1-seed0001": DIE}, cpus=2)
    rows: list[dict] = []
    monkeypatch.setitem(sys.modules, "ray", ray)
    with pytest.raises(ConfigError) as stopped:
        RayCluster("auto").run(CONFIG, tmp_path, JOBS, rows.append)
    assert str(stopped.value) == "every Ray worker died; 2 episodes not flown"
    assert [r["status"] for r in rows] == ["crashed", "crashed"]
    assert not (tmp_path / "episodes" / "S1-seed0002").exists()  # left to a re-run
    assert ray.shutdowns == 1


def test_an_episode_that_fails_is_recorded_and_its_worker_flies_the_next(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ray = FakeRay({"S1-seed0001": ValueError("the cave has no exit")}, cpus=1)
    rows = fly(ray, tmp_path, monkeypatch, concurrency=2)
    assert [r["status"] for r in rows] == ["finished", "crashed", "finished", "finished"]
    # The first line only: no traceback in the results row.
    assert recorded_error(tmp_path, "S1-seed0001") == (
        "Ray: RayTaskError: ValueError: the cave has no exit"
    )
    assert {actor for actor, _ in ray.flown} == {0}


def test_a_folder_that_cannot_be_written_stops_the_sweep_with_the_recording_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    full = RecordingError.cannot_write(tmp_path, OSError(28, "No space left on device"))
    ray = FakeRay({"S1-seed0001": full}, cpus=1)
    rows: list[dict] = []
    with pytest.raises(RecordingError) as stopped:
        fly_into = RayCluster("auto")
        monkeypatch.setitem(sys.modules, "ray", ray)
        fly_into.run(CONFIG, tmp_path, JOBS, rows.append)
    assert stopped.value is full
    assert [r["episode"] for r in rows] == ["S1-seed0000"]
    assert not (tmp_path / "episodes" / "S1-seed0001").exists()  # not recorded as a crash
    assert ray.shutdowns == 1


def test_a_ray_session_already_open_is_joined_and_left_open(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ray = FakeRay(cpus=3)
    ray.initialized = True  # e.g. a notebook that called ray.init() itself
    rows = fly(ray, tmp_path, monkeypatch)
    assert len(rows) == 4
    assert ray.inits == [] and ray.shutdowns == 0
    assert {actor for actor, _ in ray.flown} == {0, 1, 2}  # one actor per CPU

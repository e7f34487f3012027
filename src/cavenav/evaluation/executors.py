"""Where sweep episodes fly: this process, a pool of local processes, or a Ray cluster.

All three keep ``workers x concurrency`` episodes in flight. A worker is a process that
lives for the whole sweep (kernels compiled once, caves kept); ``concurrency`` episodes
share it on threads, which pays off for model pilots: a VLM step is mostly waiting on the
server, and a server (vLLM, SGLang, a hosted API) answers many requests at once.

A sweep folder that cannot be written (`RecordingError` from `EpisodeWorker.fly`) stops
every executor: the error reaches `run_sweep` wherever the episode flew.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import queue
import signal
import sys
import threading
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, TypeVar, cast

import numba

from cavenav.core.errors import ConfigError, DependencyError, RecordingError
from cavenav.evaluation.results import ResultRow, episode_row
from cavenav.evaluation.sweep import (
    EpisodeJob,
    EpisodeWorker,
    SweepConfig,
    hold_episodes,
    record_error,
)
from cavenav.sensors.kernels import KERNELS_RUN_CONCURRENTLY

__all__ = ["InProcess", "LocalPool", "RayCluster", "deal"]

Done = Callable[[ResultRow], None]
Worker = TypeVar("Worker")


def deal(waiting: deque[EpisodeJob], load: Mapping[Worker, int], most: int) -> list:
    """Jobs from ``waiting`` for the free slots, each to the worker with the fewest in
    flight (``load``), up to ``most`` each: a sweep smaller than workers x concurrency is
    shared out evenly, not handed whole to the first worker. Returns (worker, job) pairs."""
    counts, dealt = dict(load), []
    while waiting:
        free = [w for w, n in counts.items() if n < most]
        if not free:
            break
        worker = min(free, key=counts.__getitem__)
        dealt.append((worker, waiting.popleft()))
        counts[worker] += 1
    return dealt


@dataclass(frozen=True)
class InProcess:
    """Fly in this process, ``concurrency`` episodes at a time on threads.

    The threads are daemons: on Ctrl-C the process leaves at once, and the episodes in
    flight stay recorded as running (a re-run flies them again). Once the sweep stops
    (Ctrl-C, a full disk), no thread starts another episode.
    """

    concurrency: int = 1

    def run(
        self, config: SweepConfig, folder: Path, jobs: Sequence[EpisodeJob], done: Done
    ) -> None:
        worker = EpisodeWorker(config, folder)
        if self.concurrency == 1:
            for job in jobs:
                done(worker.fly(job))
            return
        todo: queue.Queue = queue.Queue()
        for job in jobs:
            todo.put(job)
        rows: queue.Queue = queue.Queue()
        stop = threading.Event()  # the sweep stopped: its folder is no longer held

        def fly() -> None:
            _share_the_cores(self.concurrency)
            while not stop.is_set():
                try:
                    job = todo.get_nowait()
                except queue.Empty:
                    return
                try:
                    rows.put(worker.fly(job))
                except BaseException as exc:  # noqa: BLE001 - raised where the sweep waits
                    stop.set()
                    rows.put(exc)
                    return

        for k in range(self.concurrency):
            threading.Thread(target=fly, name=f"cavenav-episodes-{k}", daemon=True).start()
        try:
            for _ in jobs:
                row = rows.get()
                if isinstance(row, BaseException):
                    raise row
                done(row)
        finally:
            stop.set()


def _share_the_cores(threads: int) -> None:
    """Shade this thread's frames on its share of Numba's threads, for one of ``threads``
    threads that fly episodes at once: the kernels let go of the GIL, so frames in flight
    together fill the cores between them, and each thread splitting its own over every
    core would start an OpenMP team a thread and oversubscribe the cores. A frame is the
    same bits on any number of threads (`cavenav.sensors.rig.grid_mean`). Where kernels
    take turns (`KERNELS_RUN_CONCURRENTLY`), each keeps every thread."""
    if KERNELS_RUN_CONCURRENTLY:
        numba.set_num_threads(max(1, numba.get_num_threads() // threads))


# prctl(2) option: the signal this process gets when the thread that started it ends.
_PR_SET_PDEATHSIG = 1


def _die_with(parent: int) -> None:
    """End this process when ``parent`` does, however it ends (SIGKILL included).

    On Linux the kernel sends SIGKILL (PR_SET_PDEATHSIG) when the *thread* that started
    this process ends: `LocalPool.run` starts its workers from the thread that runs the
    sweep, which returns only after stopping them (a spawned child is started directly by
    the calling thread, not by a helper thread or a fork server). A parent that died
    before the request is caught by its pid; elsewhere the pipe's end watches
    (`_pool_worker`).
    """
    if sys.platform == "linux":
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:
        os._exit(1)


def _pool_worker(
    config: SweepConfig, folder: Path, concurrency: int, conn: Connection, parent: int
) -> None:
    """A pool process: flies the jobs its pipe brings, ``concurrency`` at a time, and sends
    back (episode, row) for each, or (episode, RecordingError) when the folder cannot be
    written; a None means no more. Ctrl-C and SIGTERM are the parent's to handle: sent to
    the whole process group (a terminal's Ctrl-C, Slurm, ``kill -- -PGID``), they stop
    the parent, which stops its workers; a worker that died of them first would have its
    episodes recorded as errors instead of in flight.

    The worker never outlives the sweep: it dies with its parent (`_die_with`), or at
    once when the pipe closes, leaving its episodes in flight "running" for a rerun, and
    it holds the sweep's episodes/ while it lives (`hold_episodes`).
    """
    _die_with(parent)
    for stop in (signal.SIGINT, signal.SIGTERM):
        signal.signal(stop, signal.SIG_IGN)
    hold_episodes(folder)  # until the process ends
    worker = EpisodeWorker(config, folder)
    jobs: queue.Queue = queue.Queue()
    sending = threading.Lock()

    def fly() -> None:
        _share_the_cores(concurrency)
        while (job := jobs.get()) is not None:
            try:
                row: Any = worker.fly(job)
            except RecordingError as exc:  # the parent stops the sweep
                row = exc
            with sending:
                conn.send((job.episode, row))

    threads = [threading.Thread(target=fly) for _ in range(concurrency)]
    for thread in threads:
        thread.start()
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):  # the parent is gone: no episode flies unsupervised
            os._exit(1)
        if job is None:
            break
        jobs.put(job)
    for _ in threads:
        jobs.put(None)
    for thread in threads:
        thread.join()


@contextlib.contextmanager
def _environment(**values: str) -> Iterator[None]:
    """Set environment variables for the processes started inside the block."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                del os.environ[key]
            else:
                os.environ[key] = value


@dataclass(frozen=True)
class LocalPool:
    """``workers`` processes on this machine, each flying ``concurrency`` episodes.

    Each worker has a pipe of its own and is sent a job only when it has a free slot, so
    this process always knows which episodes a worker holds: a worker that dies (out of
    memory, killed) takes only those with it. They are recorded as errors and the other
    workers go on; nothing is shared that a dying process could leave locked.
    """

    workers: int
    concurrency: int = 1

    def run(
        self, config: SweepConfig, folder: Path, jobs: Sequence[EpisodeJob], done: Done
    ) -> None:
        if not jobs:
            return
        # spawn, not fork: a forked child inherits the parent's threads' locks half-held.
        context = multiprocessing.get_context("spawn")
        waiting = deque(jobs)
        flying: dict[Connection, dict[str, EpisodeJob]] = {}
        processes: dict[Connection, Any] = {}
        workers = min(self.workers, len(jobs))
        # A spawned child starts from this environment: share the cores out between them.
        threads = str(max(1, len(os.sched_getaffinity(0)) // workers))
        with _environment(CAVENAV_THREADS=os.environ.get("CAVENAV_THREADS", threads)):
            for _ in range(workers):
                here, there = context.Pipe()
                process = context.Process(
                    target=_pool_worker,
                    args=(config, folder, self.concurrency, there, os.getpid()),
                    daemon=True,
                )
                process.start()
                there.close()
                flying[here], processes[here] = {}, process

        def feed() -> None:
            load = {conn: len(held) for conn, held in flying.items()}
            for conn, job in deal(waiting, load, self.concurrency):
                conn.send(job)
                flying[conn][job.episode] = job

        try:
            feed()
            while any(flying.values()):
                ready = wait([c for c in flying if flying[c]], timeout=1.0)
                for conn in cast("list[Connection]", ready):  # the connections given
                    try:
                        episode, row = conn.recv()
                    except (EOFError, OSError):
                        self._bury(processes[conn], flying.pop(conn), folder, done)
                        continue
                    del flying[conn][episode]
                    if isinstance(row, RecordingError):
                        raise row
                    done(row)
                    feed()
        except BaseException:  # Ctrl-C, a full disk: stop now; those in flight stay "running"
            for process in processes.values():
                process.kill()  # SIGKILL: the workers ignore SIGTERM (`_pool_worker`)
            raise
        finally:
            for conn, process in processes.items():
                with contextlib.suppress(OSError):
                    conn.send(None)
                process.join(timeout=5)
                if process.is_alive():
                    process.kill()
                    process.join(timeout=5)

    @staticmethod
    def _bury(process: Any, lost: dict[str, EpisodeJob], folder: Path, done: Done) -> None:
        """Record the episodes of a worker that died as errors (a re-run flies them)."""
        process.join(timeout=5)
        for job in lost.values():
            run_dir = folder / "episodes" / job.episode
            record_error(run_dir, job, f"the worker process died (exit code {process.exitcode})")
            done(episode_row(run_dir, folder))


@dataclass(frozen=True)
class RayCluster:
    """The sweep on Ray: one actor per worker, ``concurrency`` episodes per actor.

    ``address`` is passed to ``ray.init``: "auto" joins the cluster this machine belongs
    to, "local" starts a private one here, "ray://HOST:10001" reaches a remote head. The
    sweep folder must be on a filesystem every node sees (run folders are written where
    the episode flies).
    """

    address: str
    workers: int | None = None
    concurrency: int = 1

    @contextlib.contextmanager
    def opened(self) -> Iterator[None]:
        """Ray, reached before the sweep writes anything (`run_sweep`): an address that
        answers nothing is refused with nothing written."""
        ray = _ray()
        if ray.is_initialized():
            yield
            return
        try:
            ray.init(
                address=self.address,
                include_dashboard=False,
                log_to_driver=False,
                configure_logging=False,
            )
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise ConfigError(f"cannot reach Ray at '{self.address}': {exc}") from None
        try:
            yield
        finally:
            ray.shutdown()

    def run(
        self, config: SweepConfig, folder: Path, jobs: Sequence[EpisodeJob], done: Done
    ) -> None:
        if not jobs:
            return
        with self.opened():
            self._run(_ray(), config, Path(folder).resolve(), jobs, done)

    def _run(
        self, ray: Any, config: SweepConfig, folder: Path, jobs: Sequence[EpisodeJob], done: Done
    ) -> None:
        workers = self.workers or max(int(ray.cluster_resources().get("CPU", 1)), 1)
        actor = ray.remote(
            num_cpus=1,
            max_concurrency=self.concurrency,
            runtime_env={"env_vars": {"CAVENAV_THREADS": "1"}},  # one core per actor
        )(_RayWorker)
        actors = [actor.remote(config, str(folder)) for _ in range(min(workers, len(jobs)))]
        waiting = deque(jobs)
        flying: dict[Any, tuple[EpisodeJob, Any]] = {}
        load = dict.fromkeys(actors, 0)

        def launch() -> None:
            for a, job in deal(waiting, load, self.concurrency):
                flying[a.fly.remote(job)] = (job, a)
                load[a] += 1

        launch()
        while flying:
            ready, _ = ray.wait(list(flying), num_returns=1)
            job, a = flying.pop(ready[0])
            try:
                row = ray.get(ready[0])
                load[a] -= 1
            except ray.exceptions.RayError as exc:  # the actor died or the task failed
                if isinstance(getattr(exc, "cause", None), RecordingError):
                    raise exc.cause from None  # the folder cannot be written: stop
                run_dir = folder / "episodes" / job.episode
                record_error(run_dir, job, f"Ray: {type(exc).__name__}: {exc}".splitlines()[0])
                row = episode_row(run_dir, folder)
                if isinstance(exc, ray.exceptions.ActorDiedError):
                    load.pop(a, None)
                else:
                    load[a] -= 1
            done(row)
            if not load and waiting:
                raise ConfigError(f"every Ray worker died; {len(waiting)} episodes not flown")
            launch()


class _RayWorker:
    """A Ray actor around an `EpisodeWorker` (made remote in `RayCluster._run`)."""

    def __init__(self, config: SweepConfig, folder: str):
        self.worker = EpisodeWorker(config, Path(folder))

    def fly(self, job: EpisodeJob) -> ResultRow:
        return self.worker.fly(job)


def _ray() -> Any:  # noqa: ANN401 - the ray module
    try:
        import ray
    except ImportError:
        raise DependencyError("--ray-address needs Ray: pip install 'cavenav[ray]'") from None
    return ray

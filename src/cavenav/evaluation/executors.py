"""Where sweep episodes fly: this process, a pool of local processes, or a Ray cluster.

All three keep ``workers x concurrency`` episodes in flight. A worker is a process that
lives for the whole sweep (kernels compiled once, caves kept); ``concurrency`` episodes
share it on threads, which pays off for model pilots: a VLM step is mostly waiting on the
server, and a server (vLLM, SGLang, a hosted API) answers many requests at once.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import queue
import signal
import threading
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

from cavenav.errors import ConfigError, DependencyError
from cavenav.evaluation.results import episode_row
from cavenav.evaluation.sweep import EpisodeJob, EpisodeWorker, SweepConfig, record_error

__all__ = ["InProcess", "LocalPool", "RayCluster"]

Done = Callable[[dict[str, Any]], None]


@dataclass(frozen=True)
class InProcess:
    """Fly in this process, ``concurrency`` episodes at a time on threads.

    The threads are daemons: on Ctrl-C the process leaves at once, and the episodes in
    flight stay recorded as running (a re-run flies them again).
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

        def fly() -> None:
            while True:
                try:
                    job = todo.get_nowait()
                except queue.Empty:
                    return
                rows.put(worker.fly(job))

        for _ in range(self.concurrency):
            threading.Thread(target=fly, daemon=True).start()
        for _ in jobs:
            done(rows.get())


def _pool_worker(config: SweepConfig, folder: Path, concurrency: int, conn: Connection) -> None:
    """A pool process: flies the jobs its pipe brings, ``concurrency`` at a time, and sends
    back (episode, row) for each; a None means no more. Ctrl-C is the parent's to handle."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    worker = EpisodeWorker(config, folder)
    jobs: queue.Queue = queue.Queue()
    sending = threading.Lock()

    def fly() -> None:
        while (job := jobs.get()) is not None:
            row = worker.fly(job)
            with sending:
                conn.send((job.episode, row))

    threads = [threading.Thread(target=fly) for _ in range(concurrency)]
    for thread in threads:
        thread.start()
    while True:
        try:
            job = conn.recv()
        except EOFError:  # the parent is gone
            job = None
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
                    args=(config, folder, self.concurrency, there),
                    daemon=True,
                )
                process.start()
                there.close()
                flying[here], processes[here] = {}, process

        def feed(conn: Connection) -> None:
            while waiting and len(flying[conn]) < self.concurrency:
                job = waiting.popleft()
                conn.send(job)
                flying[conn][job.episode] = job

        try:
            for conn in flying:
                feed(conn)
            while any(flying.values()):
                for conn in wait([c for c in flying if flying[c]], timeout=1.0):
                    try:
                        episode, row = conn.recv()  # type: ignore[union-attr]
                    except (EOFError, OSError):
                        self._bury(processes[conn], flying.pop(conn), folder, done)
                        continue
                    del flying[conn][episode]
                    done(row)
                    feed(conn)
        except BaseException:  # Ctrl-C: stop now; the episodes in flight stay "running"
            for process in processes.values():
                process.terminate()
            raise
        finally:
            for conn, process in processes.items():
                with contextlib.suppress(OSError):
                    conn.send(None)
                process.join(timeout=5)
                if process.is_alive():
                    process.terminate()
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

    def run(
        self, config: SweepConfig, folder: Path, jobs: Sequence[EpisodeJob], done: Done
    ) -> None:
        if not jobs:
            return
        try:
            import ray
        except ImportError:
            raise DependencyError("--ray-address needs Ray: pip install 'cavenav[ray]'") from None
        started_here = not ray.is_initialized()
        if started_here:
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
            self._run(ray, config, Path(folder).resolve(), jobs, done)
        finally:
            if started_here:
                ray.shutdown()

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
        waiting = list(jobs)
        flying: dict[Any, tuple[EpisodeJob, Any]] = {}
        load = dict.fromkeys(actors, 0)

        def launch() -> None:
            for a in list(load):
                while waiting and load[a] < self.concurrency:
                    job = waiting.pop(0)
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

    def fly(self, job: EpisodeJob) -> dict[str, Any]:
        return self.worker.fly(job)

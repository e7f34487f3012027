"""How fast sweeps run: episodes per minute by workers, VLM steps per second by concurrency.

    .venv/bin/python benchmarks/sweep.py            # both parts (about 6 minutes on 2 cores)
    .venv/bin/python benchmarks/sweep.py --part vlm

Part 1 flies the geometric pilot over the same grid with 1 and 2 workers (processes) and
prints episodes per minute and their ratio, the share of the machine's CPU time the sweep
used (its own and its workers', over wall time x cores; target: 90% or more), and its
rate against the bound: the cores divided by the CPU-seconds an episode costs alone (in
the one-worker sweep; target: 85% of it or more). Part 2
flies the VLM pilot against a local OpenAI-compatible server that answers every request
after a fixed delay (1.0 s), with --concurrency 1, 4 and 16 in one worker, and prints
steps per second and the ratio to concurrency 1 (targets: 8 at least 6.5x faster, 16 at
least 10x), then the pilot's own CPU time per step outside the wait for the server (its
thread's CPU time in `decide`, one episode at concurrency 1; target: 60 ms or less). The
server runs in a process of its own, as a real one would: in the sweep's process it
would take the GIL to read every request.

Every ratio is measured within one run. Caves are built before the clock starts (the
mesh cache), worker start-up is inside it. Frames are off (--frames none) in both parts,
so the figures are the simulator's and the pilot's, not the disk's.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import resource
import statistics
import tempfile
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.executors import InProcess, LocalPool
from cavenav.evaluation.sweep import SweepConfig, run_sweep
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.world.scenarios import load_scenario

REPLY = (
    "Let me think step by step.\n(a) Situation: the passage is open ahead.\n"
    "(b) Constraints: nothing within the standoff.\n(c) Action: turn to look along it.\n"
    '{"turn left 10 deg": "look along the passage before moving"}'
)


def serve(delay_s: float) -> ThreadingHTTPServer:
    """An OpenAI-compatible server on 127.0.0.1 that answers after ``delay_s``; GET
    /arrivals answers (and forgets) when each request since the last arrived."""
    arrivals: list[float] = []

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

        def _send(self, payload: dict) -> None:
            data = json.dumps(payload).encode()
            self.send_response(200)
            self.send_header("content-type", "application/json")
            self.send_header("content-length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def do_GET(self) -> None:  # noqa: N802 - http.server's naming
            if self.path.endswith("/arrivals"):
                self._send({"arrivals": arrivals.copy()})
                arrivals.clear()
                return
            self._send({"object": "list", "data": [{"id": "bench", "object": "model"}]})

        def do_POST(self) -> None:  # noqa: N802
            arrivals.append(time.monotonic())
            body = json.loads(self.rfile.read(int(self.headers["content-length"])))
            time.sleep(delay_s)
            message = {"role": "assistant", "content": REPLY}
            self._send(
                {
                    "id": "bench",
                    "object": "chat.completion",
                    "created": int(time.time()),
                    "model": body["model"],
                    "choices": [{"index": 0, "finish_reason": "stop", "message": message}],
                    "usage": {"prompt_tokens": 1000, "completion_tokens": 60, "total_tokens": 1060},
                }
            )

    class Server(ThreadingHTTPServer):
        request_queue_size = 128  # 32 requests may arrive at once
        daemon_threads = True

    server = Server(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def _serve_in(port: multiprocessing.Queue, delay_s: float) -> None:
    port.put(serve(delay_s).server_address[1])
    threading.Event().wait()  # until the benchmark ends this process


def serve_elsewhere(delay_s: float) -> tuple[multiprocessing.Process, str]:
    """`serve` in a process of its own; the process and the server's base URL."""
    spawn = multiprocessing.get_context("spawn")
    port: multiprocessing.Queue = spawn.Queue()
    process = spawn.Process(target=_serve_in, args=(port, delay_s), daemon=True)
    process.start()
    return process, f"http://127.0.0.1:{port.get(timeout=60)}/v1"


def pilot_cpu_ms(spec: PilotSpec, steps: int) -> float:
    """The median CPU time of the pilot's thread in `decide`, over one episode of S4."""
    pilot = spec.build()
    cpu, decide = [], pilot.decide

    def timed(observation):  # noqa: ANN001, ANN202
        start = time.thread_time()
        decision = decide(observation)
        cpu.append(1e3 * (time.thread_time() - start))
        return decision

    pilot.decide = timed  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as folder:
        config = EpisodeConfig(max_steps=steps, save_frames=False, plots=False)
        run_episode(load_scenario("S4"), pilot, config, Path(folder) / "run")
    return statistics.median(cpu)


def arrivals(url: str) -> list[float]:
    """When each request reached the server since the last call, in order."""
    import urllib.request

    with urllib.request.urlopen(f"{url}/arrivals", timeout=10) as answer:
        return sorted(json.loads(answer.read())["arrivals"])


def steady_rate(times: list[float]) -> float:
    """Requests a second at the server over the middle of a sweep, its 20th to 80th
    percentile of arrivals: while every slot is flying, before the last episodes fly
    alone (a grid rarely divides evenly among the slots) and after the first caves load."""
    first, last = int(0.2 * len(times)), int(0.8 * len(times))
    return (last - first) / (times[last] - times[first])


def grid(n: int) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """n episodes: S1..S5 with as many seeds as needed (seeds 0..)."""
    seeds = tuple(range(-(-n // 5)))
    return ("S1", "S2", "S3", "S4", "S5"), seeds


def build_caves(scenarios: tuple[str, ...], seeds: tuple[int, ...]) -> None:
    for name in scenarios:
        for seed in seeds:
            load_scenario(name, seed)


def _cpu_s() -> float:
    """CPU seconds of this process and its finished workers, user and system."""
    own, workers = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + workers.ru_utime + workers.ru_stime


def timed(config: SweepConfig, executor: object) -> tuple[float, list[dict]]:
    wall, _, rows = timed_cpu(config, executor)
    return wall, rows


def timed_cpu(config: SweepConfig, executor: object) -> tuple[float, float, list[dict]]:
    """Wall seconds, CPU seconds (the workers' included) and the rows of a sweep."""
    with tempfile.TemporaryDirectory() as folder:
        started, cpu = time.perf_counter(), _cpu_s()
        rows = run_sweep(config, Path(folder) / "sweep", executor)  # type: ignore[arg-type]
        return time.perf_counter() - started, _cpu_s() - cpu, rows


def geometric_part(episodes: int) -> None:
    scenarios, seeds = grid(episodes)
    build_caves(scenarios, seeds)
    config = SweepConfig(scenarios, seeds, frames="none")
    print(f"geometric pilot, {len(scenarios) * len(seeds)} episodes (S1-S5 x seeds {seeds})")
    rates, cores, bound = {}, len(os.sched_getaffinity(0)), 0.0
    for workers in (1, 2):
        executor = InProcess() if workers == 1 else LocalPool(workers)
        wall, cpu, rows = timed_cpu(config, executor)
        steps = sum(int(r["steps"]) for r in rows)
        rates[workers] = 60.0 * len(rows) / wall
        bound = bound or 60.0 * cores / (cpu / len(rows))  # from the one-worker sweep
        print(
            f"  {workers} worker{'s' if workers > 1 else ' '}: {wall:6.1f} s, "
            f"{rates[workers]:5.1f} episodes/min, {steps / wall:5.1f} steps/s, "
            f"CPU {cpu / len(rows):.1f} s an episode, {cpu / (wall * cores):.0%} of the "
            f"machine's CPU time (target >= 90%), {rates[workers] / bound:.0%} of the bound "
            f"{bound:.1f} episodes/min (target >= 85%)"
        )
    print(f"  ratio 2 workers / 1 worker: {rates[2] / rates[1]:.2f}")


def vlm_part(delay_s: float, steps: int, workers: int) -> None:
    server, url = serve_elsewhere(delay_s)
    pilot = PilotSpec("vlm", VLMOptions(model="bench", base_url=url, api_key_env="BENCH_KEY"))
    os.environ.setdefault("BENCH_KEY", "local")
    levels = (1, 4, 8, 16)
    scenarios, seeds = grid(2 * max(levels) * workers)
    build_caves(scenarios, seeds)
    print(
        f"VLM pilot against a local server answering after {delay_s:.1f} s, "
        f"{workers} worker{'s' if workers > 1 else ''}, episodes of {steps} steps"
    )
    rates, steady = {}, {}
    arrivals(url)  # forget the requests of the checks before
    for concurrency in levels:
        # Twice as many episodes as can fly at once, so that K stay in flight most of the time.
        sc, se = grid(max(2 * concurrency * workers, 5))
        config = SweepConfig(sc, se, pilot=pilot, steps=steps, frames="none")
        executor = InProcess(concurrency) if workers == 1 else LocalPool(workers, concurrency)
        wall, rows = timed(config, executor)
        flown = sum(int(r["steps"] or 0) for r in rows)
        for r in rows:
            if r["outcome"] in ("error", "pilot_failure"):
                print(f"    {r['episode']}: {r['outcome']}: {r.get('error')}")
        rates[concurrency], steady[concurrency] = flown / wall, steady_rate(arrivals(url))
        print(
            f"  --concurrency {concurrency:2d}: {flown:4d} steps in {wall:5.1f} s = "
            f"{rates[concurrency]:5.2f} steps/s ({rates[concurrency] / rates[1]:.1f}x); "
            f"in the middle of the sweep {steady[concurrency]:5.2f} steps/s "
            f"({steady[concurrency] / steady[1]:.1f}x)"
        )
    for name, rate in (("whole sweeps", rates), ("middles", steady)):
        print(
            f"  {name}: ratio 8 / 1 {rate[8] / rate[1]:.1f} (target >= 6.5), "
            f"16 / 1 {rate[16] / rate[1]:.1f} (target >= 10)"
        )
    cpu = pilot_cpu_ms(pilot, steps)
    print(f"  pilot CPU per step outside the wait: {cpu:.1f} ms (target <= 60)")
    server.terminate()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("all", "geometric", "vlm"), default="all")
    parser.add_argument("--episodes", type=int, default=20, help="geometric grid size")
    parser.add_argument("--delay", type=float, default=1.0, help="server delay, seconds")
    parser.add_argument("--vlm-steps", type=int, default=20, help="step budget, VLM episodes")
    parser.add_argument("--vlm-workers", type=int, default=1, help="worker processes, VLM part")
    args = parser.parse_args()
    if args.part in ("all", "geometric"):
        geometric_part(args.episodes)
    if args.part in ("all", "vlm"):
        vlm_part(args.delay, args.vlm_steps, args.vlm_workers)


if __name__ == "__main__":
    main()

"""The three pilot designs over the same caves, with the project's stand-in model server.

    .venv/bin/python benchmarks/designs.py --out designs    # about 5 minutes on 2 cores

One worker flies the episodes one after the other, so that the stand-in answers them in
the same order every run: its direct-design pilot remembers an episode's earlier
requests, and its wording alternates from one reply to the next.

Flies the VLM pilot with ``--design direct``, ``arrows`` and ``waypoint`` over S1-S5
(seed 0 by default) against the tests' stand-in OpenAI-compatible server
(tests/vlm_server.py), which reads each request's depth image with the geometric pilot
and answers in the design's form: an action string, the offered number nearest the
heading it would take, or that candidate as a number or a point on the image. It bills a
token per 4 characters of text and 85 per image; the prices (--price, default $0.15 and
$0.60 per million prompt and completion tokens) make the dollars an illustration only.

Prints, in one run: each design's success, collisions, SPL, model calls per metre,
tokens and USD per success, and the share of steps flown without a call, as the README's
table; the ratio of direct's calls per metre to waypoint's (target: 3 or more); and the
pilot's CPU time per decision outside the wait for the model (its thread's CPU time in
`decide`, S4 at 640x480; target: 60 ms or less with arrows drawn). Then it writes
`cavenav compare` of the three sweeps to OUT/compare.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.comparison import load_sweeps
from cavenav.evaluation.results import group
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.world.scenarios import load_scenario

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.vlm_server import FakeVLM  # noqa: E402 - the project's stand-in model server

DESIGNS = ("direct", "arrows", "waypoint")
CAVENAV = str(Path(sys.executable).with_name("cavenav"))


def fly(design: str, base_url: str, args: argparse.Namespace) -> Path:
    out = args.out / design
    command = [CAVENAV, "eval", "--pilot", "vlm", "--model", "stand-in", "--base-url", base_url,
               "--design", design, "--scenarios", args.scenarios, "--seeds", args.seeds,
               "--workers", "1", "--frames", "none", "--price", args.price,
               "--out", str(out)]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"{design}: {done.stderr.strip()}")
    return out


def cpu_per_decision(design: str, base_url: str) -> tuple[float, float, float | None]:
    """The pilot thread's CPU time in `decide`, ms: median and 95th percentile over the
    steps that asked the model, and the median over those its planner flew (None: none)."""
    spec = PilotSpec("vlm", VLMOptions(model="stand-in", base_url=base_url, design=design))
    pilot = spec.build()
    asked, planned, decide = [], [], pilot.decide

    def timed(observation):  # noqa: ANN001, ANN202
        start = time.thread_time()
        decision = decide(observation)
        (asked if decision.exchanges else planned).append(1e3 * (time.thread_time() - start))
        return decision

    pilot.decide = timed  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as folder:
        config = EpisodeConfig(save_frames=False, plots=False)
        run_episode(load_scenario("S4"), pilot, config, Path(folder) / "run")
    p95 = statistics.quantiles(asked, n=20)[-1]
    return statistics.median(asked), p95, statistics.median(planned) if planned else None


def _cell(value: float | None, form: str) -> str:
    return "-" if value is None else format(value, form)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--scenarios", default="S1,S2,S3,S4,S5")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--price", default="0.15,0.60")
    args = parser.parse_args()
    with FakeVLM() as server:
        sweeps = [fly(design, server.base_url, args) for design in DESIGNS]
        cpu = {design: cpu_per_decision(design, server.base_url) for design in DESIGNS}
    print("| design | success | collisions | SPL | model calls per m | tokens per success | "
          "USD per success | steps without a call | CPU per decision (median / p95) |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    standings = {}
    for design, sweep in zip(DESIGNS, load_sweeps(sweeps), strict=True):
        g = standings[design] = group("all", sweep.label, sweep.rows)
        median, p95, planned = cpu[design]
        planner = f"; planner steps {planned:.0f} ms" if planned is not None else ""
        print(
            f"| {design} | {g['successes']}/{g['completed']} | {g['collisions']} | "
            f"{_cell(g['spl'], '.3f')} | {_cell(g['calls_per_m'], '.2f')} | "
            f"{_cell(g['tokens_per_success'], ',.0f')} | "
            f"{_cell(g['cost_per_success_usd'], '.4f')} | "
            f"{_cell(g['steps_without_call_share'], '.0%')} | "
            f"{median:.0f} / {p95:.0f} ms{planner} |"
        )
    ratio = standings["direct"]["calls_per_m"] / standings["waypoint"]["calls_per_m"]
    print(f"\ncalls per metre, direct / waypoint: {ratio:.1f}x (target: 3x or more)")
    print(f"CPU per decision with arrows drawn at 640x480: {cpu['arrows'][0]:.0f} ms median, "
          f"{cpu['arrows'][1]:.0f} ms p95 (target: 60 ms or less)")  # fmt: skip
    compare = [CAVENAV, "compare", *map(str, sweeps), "--out", str(args.out / "compare")]
    subprocess.run(compare, check=True, capture_output=True)
    print(f"comparison page: {args.out / 'compare' / 'index.html'}")


if __name__ == "__main__":
    main()

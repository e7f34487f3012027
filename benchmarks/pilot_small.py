"""What one decision of the shipped small VLM (`models/cavenav-pilot-small`) costs on the
CPU, beside the simulator step it decides on: issue 43's target is 100 ms or less a
decision on 2 cores, at the model's own image size.

Flies S1's held-out cave 1000 for ``--steps`` steps with the model (greedy, through the
transformers backend, as `cavenav run` flies it) and prints, per step, the median and
95th percentile of the model's own time (its generation), the pilot's whole
time (encoding the images and building the request too), the simulator's sensing, and
the tokens read and written. Then the same decisions asked on a thread other than the
main one, as a sweep asks them (`cavenav eval`: each episode flies on a thread).

Run: python benchmarks/pilot_small.py [--steps N] [--model DIR]  (DIR: the shipped model)
"""

from __future__ import annotations

import argparse
import statistics
import threading
from pathlib import Path

from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.world.scenarios import load_scenario

MODEL = Path(__file__).resolve().parents[1] / "models" / "cavenav-pilot-small"


def _fly(steps: int, model: Path) -> list[dict]:
    options = VLMOptions(model=str(model), backend="transformers", temperature=0.0)
    pilot = PilotSpec("vlm", options.for_model()).build()
    config = EpisodeConfig(max_steps=steps, plots=False, save_frames=False)
    return run_episode(load_scenario("S1", 1000), pilot, config, None).steps


def _row(name: str, values: list[float], unit: str = "ms") -> str:
    values = sorted(values)
    p95 = values[min(len(values) - 1, round(0.95 * (len(values) - 1)))]
    return f"  {name:<28} median {statistics.median(values):7.1f} {unit}   p95 {p95:7.1f} {unit}"


def _report(title: str, steps: list[dict]) -> None:
    asked = [s for s in steps[1:] if s.get("vlm")]  # the first decision loads the model
    print(f"{title}: {len(asked)} decisions")
    print(_row("model (generation)", [1e3 * s["vlm"]["model_s"] for s in asked]))
    print(_row("pilot (request + model)", [s["timing_ms"]["pilot"] for s in asked]))
    print(_row("simulator sensing", [s["timing_ms"]["sense"] for s in asked]))
    print(_row("prompt tokens", [s["vlm"]["prompt_tokens"] for s in asked], "tok"))
    print(_row("reply tokens", [s["vlm"]["completion_tokens"] for s in asked], "tok"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--model", type=Path, default=MODEL, help="a model folder")
    args = parser.parse_args()
    _report("main thread (cavenav run)", _fly(args.steps, args.model))
    flown: list[list[dict]] = []
    worker = threading.Thread(target=lambda: flown.append(_fly(args.steps, args.model)))
    worker.start()
    worker.join()
    _report("a sweep's episode thread (cavenav eval)", flown[0])


if __name__ == "__main__":
    main()

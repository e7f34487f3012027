"""How fast flights become training data (`cavenav dataset`), against issue 43's target of
1,000 decisions a second.

Prints, in one run, decisions exported a second for:

- a geometric sweep flown without frames (S1-S5, seeds 0..N-1), whose requests are made
  again by flying each episode once more (`cavenav.training.replay`), at the camera's
  640x480 and at a 160x120 camera, with the images sent at 128x96 either way; beside
  each, the same episodes' sensing alone (the environment stepped through the same
  moves with no request built), which bounds any export that renders;
- a model pilot's run, whose requests are read from its run folder (no rendering).

Run: python benchmarks/dataset_export.py [--seeds N]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from cavenav.episode.loop import make_env, run_episode
from cavenav.episode.records import read_steps, read_summary
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.executors import InProcess
from cavenav.evaluation.sweep import SweepConfig, run_sweep
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.training.dataset import DatasetOptions, export_dataset
from cavenav.training.replay import recorded_cave, recorded_config
from cavenav.world.scenarios import load_scenario

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.pilots.test_vlm import pilot_for  # noqa: E402 - the tests' model server and pilot
from tests.vlm_server import FakeVLM  # noqa: E402

SMALL = VLMOptions(image_size="128x96")


def sensing_alone(sweep: Path) -> float:
    """Steps a second of the sweep's episodes stepped again with nothing asked."""
    steps, started = 0, time.perf_counter()
    for run_dir in sorted((sweep / "episodes").iterdir()):
        summary = read_summary(run_dir / "summary.json")
        env = make_env(recorded_cave(summary["scenario"], summary), recorded_config(summary))
        env.reset(seed=summary["config"]["seed"])
        for step in read_steps(run_dir / "steps.jsonl"):
            env.step(step["action"])
            steps += 1
        env.close()
    return steps / (time.perf_counter() - started)


def geometric(root: Path, seeds: int, resolution: tuple[int, int] | None) -> None:
    sweep = root / f"sweep-{resolution}"
    config = SweepConfig(("S1", "S2", "S3", "S4", "S5"), tuple(range(seeds)), PilotSpec(),
                         frames="none", resolution=resolution)  # fmt: skip
    run_sweep(config, sweep, InProcess())
    options = DatasetOptions(episodes="all", vlm=SMALL)
    done = export_dataset([sweep], root / f"data-{resolution}", options)
    rows = sum(done.rows.values())
    camera = "640x480" if resolution is None else "x".join(map(str, resolution))
    print(f"geometric sweep, camera {camera}, images 128x96: {rows} decisions in "
          f"{done.seconds:.1f} s = {done.decisions_per_s:,.0f}/s; sensing alone "
          f"{sensing_alone(sweep):,.0f} steps/s")  # fmt: skip


def recorded(root: Path) -> None:
    run_dir = root / "vlm"
    with FakeVLM() as server:
        config = EpisodeConfig(max_steps=60, save_frames=False, plots=False)
        run_episode(load_scenario("S4"), pilot_for(server), config, run_dir)
    done = export_dataset([run_dir], root / "data-vlm", DatasetOptions(episodes="all"))
    rows = sum(done.rows.values())
    print(f"model pilot's run (640x480 PNG requests read back): {rows} decisions in "
          f"{done.seconds:.2f} s = {done.decisions_per_s:,.0f}/s")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2, help="caves of each of S1-S5")
    seeds = parser.parse_args().seeds
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        recorded(root)
        geometric(root, seeds, (160, 120))
        geometric(root, seeds, None)
    print("target (issue 43): 1,000 decisions/s")


if __name__ == "__main__":
    main()

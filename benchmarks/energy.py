"""The energy a flight's summary gives, against the range the T200's published data gives
for the same path.

    .venv/bin/python benchmarks/energy.py runs/20261127-231000_S4_geometric_seed0

A 4S pack runs from 16.8 V full to about 12 V empty, and Blue Robotics publishes the
T200's performance at 12 V and 16 V. This re-flies every move of the run folder's
steps.jsonl through the water (still water: a current's gusts are not recorded) with
each published curve in turn, the drag held at the model's (the body does not change with
the pack's voltage), and prints the energy each curve gives beside the summary's
`energy_wh`, which the model takes at the pack's nominal 14.8 V. The thrust is spread over
the thrusters as a BlueROV2 spreads it: four vectored at 45 degrees, two vertical.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cavenav.core.types import Cruise, Pose
from cavenav.motion.actions import parse_action
from cavenav.motion.energy import KGF_N, PowerModel, Thruster, thrusters_w
from cavenav.motion.kinematics import apply
from cavenav.world.current import carry

PUBLISHED = {"12 V": Thruster(3.71 * KGF_N, 205.0), "16 V": Thruster(5.25 * KGF_N, 390.0)}


def flown_wh(steps: list[dict], thruster: Thruster, model: PowerModel) -> float:
    """The moves of ``steps`` against ``model``'s drag, with ``thruster`` on every mount, Wh."""
    total = 0.0
    for step in steps:
        if step.get("action") is None:
            continue
        action = parse_action(step["action"])
        pose = Pose.from_dict(step["pose"])
        passage = carry(None, pose, action, apply(pose, action), 0.0, Cruise())
        watts = thrusters_w(model.drag_n(passage.through_water), thruster)
        total += float(((watts + model.hotel_w + model.lamps_w) * passage.dt).sum())
    return total / 3600.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_folder", type=Path)
    run = parser.parse_args().run_folder
    summary = json.loads((run / "summary.json").read_text())
    steps = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
    model = PowerModel()
    print(f"{run.name}: {summary['steps']} steps, {summary['path_length_m']:.1f} m flown, "
          f"{summary['moving_s']:.0f} s of moves")  # fmt: skip
    for name, thruster in PUBLISHED.items():
        print(f"  T200 at {name}: {flown_wh(steps, thruster, model):.3f} Wh")
    energy = summary["energy_wh"]
    hotel = (model.hotel_w + model.lamps_w) * summary["moving_s"] / 3600.0
    print(f"  summary energy_wh (14.8 V): {energy:.3f} Wh "
          f"(electronics and lamps {hotel:.3f} Wh, thrusters {energy - hotel:.3f})")  # fmt: skip


if __name__ == "__main__":
    main()

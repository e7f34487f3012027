"""What one action costs on an ArduSub vehicle through the MAVLink bridge, by mode.

    .venv/bin/python benchmarks/mavlink_action.py      # about a minute

Flies a fixed list of actions against the simulated autopilot (`cavenav fake-sub`'s
defaults, which move as ArduSub's SITL does: inertia and coasting, dead bands, a turn's
lag, a guided planner slow to set off; execution noise 0.05), the bridge at its defaults
(closed-loop moves, tuned on the SITL), in `manual` and in `guided` mode, and prints for
each the wall time of the action, the time its segments would take at the stick rates
or the guided speed and turn rate, the difference (the closed loop's slow final approach
and the wait until the vehicle is still) and the drift between the pose commanded and
the pose reached. All from one run on one machine.
"""

from __future__ import annotations

import math
import socket
import statistics
import time

from cavenav.core.types import Pose
from cavenav.motion.actions import parse_action
from cavenav.motion.kinematics import apply
from cavenav.vehicle.fake_sub import FakeSub, FakeSubConfig
from cavenav.vehicle.mavlink import ArduSubMotion, BridgeConfig, plan

ACTIONS = (
    "forward 0.5 m",
    "forward 1 m, turn left 15 deg",
    "strafe right 0.2 m",
    "ascend 0.3 m, turn right 45 deg",
    "forward 0.2 m, descend 0.5 m",
    "turn left 90 deg",
)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def fly(mode: str) -> list[tuple[str, float, float, float]]:
    """(action, wall s, planned s, drift m) for each of ACTIONS."""
    port = free_udp_port()
    sub_config = FakeSubConfig(
        address=f"udpout:127.0.0.1:{port}", noise=0.05, start_ned=(0.0, 0.0, 30.0)
    )
    bridge = BridgeConfig(connect=f"udpin:127.0.0.1:{port}", mode=mode)
    rows = []
    with FakeSub(sub_config):
        motion = ArduSubMotion(bridge)
        pose = motion.start(Pose(0.0, 0.0, 0.0))
        try:
            for text in ACTIONS:
                action = parse_action(text)
                planned = sum(s.duration_s for s in plan(action, bridge))
                started = time.perf_counter()
                reached = motion.move(pose, action)
                wall = time.perf_counter() - started
                drift = math.dist(reached.position, apply(pose, action).position)
                rows.append((text, wall, planned, drift))
                pose = reached
        finally:
            motion.close()
    return rows


def main() -> None:
    for mode in ("manual", "guided"):
        rows = fly(mode)
        print(f"\n{mode} mode")
        print(f"{'action':34} {'wall s':>7} {'segments s':>10} {'overhead s':>10} {'drift m':>8}")
        for text, wall, planned, drift in rows:
            print(f"{text:34} {wall:7.2f} {planned:10.2f} {wall - planned:10.2f} {drift:8.3f}")
        overheads = [wall - planned for _, wall, planned, _ in rows]
        print(
            f"median overhead {statistics.median(overheads):.2f} s per action; "
            f"mean drift {statistics.fmean(r[3] for r in rows):.3f} m"
        )


if __name__ == "__main__":
    main()

"""The bridge against ArduSub's own software-in-the-loop build, the real autopilot with its
own vehicle physics (issue 46). cavenav does not ship it (ArduPilot is GPLv3): the test
runs where ``CAVENAV_ARDUSUB`` names the binary (or its folder, with ArduPilot's sub.parm)
and is skipped elsewhere. benchmarks/ardusub_sitl.py flies whole caves against it."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from cavenav.core.types import Pose
from cavenav.episode.run_folder import read_jsonl
from cavenav.motion.actions import parse_action
from cavenav.motion.kinematics import apply, wrap_angle
from cavenav.vehicle.mavlink import ArduSubMotion, BridgeConfig
from cavenav.vehicle.sitl import ARDUSUB_ENV, ardusub_binary, ardusub_sitl

MOVES = ("forward 0.5 m", "turn right 10 deg", "forward 0.2 m, ascend 0.2 m", "turn left 5 deg")


@pytest.mark.slow
@pytest.mark.sitl
def test_from_the_surface_ardusub_dives_then_flies_each_move_where_it_was_meant(
    tmp_path: Path,
) -> None:
    binary = ardusub_binary()
    if binary is None:
        pytest.skip(f"no ArduSub SITL: set {ARDUSUB_ENV} to its binary (about 70 s)")
    log = tmp_path / "mavlink.jsonl"
    with ardusub_sitl(binary, instance=7, workdir=tmp_path / "sitl") as address:
        motion = ArduSubMotion(BridgeConfig(connect=address, start_depth_m=2.0), log)
        try:
            pose = motion.start(Pose(0.0, 0.0, 0.0, 0.0))
            assert motion.start_report is not None
            assert motion.start_report["from_depth_m"] < 0.3  # it floated at the surface
            assert motion.start_report["depth_m"] == pytest.approx(2.0, abs=0.1)
            for text in MOVES:
                meant = apply(pose, parse_action(text))
                pose = motion.move(pose, parse_action(text))
                assert motion.last_move is not None and motion.last_move.ended == "reached"
                assert math.dist(pose.position, meant.position) < 0.15, text
                assert math.degrees(abs(wrap_angle(pose.psi - meant.psi))) < 1.5, text
        finally:
            motion.close()
    heartbeats = [
        r for r in read_jsonl(log)
        if r["dir"] == "received" and r.get("mavpackettype") == "HEARTBEAT" and r["type"] == 12
    ]  # fmt: skip
    assert not heartbeats[-1]["base_mode"] & 128  # it ended disarmed

"""The acoustic instruments (imaging sonar, DVL): their cost, their accuracy, and what the
DVL does for dead reckoning.

1. Cost, per scenario S1-S5 (seed 0), at poses along the geometric pilot's path, the
   median of timings interleaved at each pose:
   - full step: the sensor rig's observation (forward colour, depth, both sounders);
   - ping360:   one observation of the scanning sonar, over a 2 s move (its default
                sector and range: the angles swept in those 2 s);
   - multibeam: one observation of the forward multibeam (all 512 beams);
   - dvl:       one DVL reading (four beams ranged);
   each as a share of the full step (targets: a sonar frame 15% or less, the DVL 2% or less).
2. Accuracy, in clear water: for every beam whose axis meets rock within the range, the
   bin of its strongest return against the bin of the axis's ray-cast distance; the share
   within one bin (target: 95% or more); and, of the beams whose axis meets the rock
   within 30 degrees of square on, the share whose strongest return lies within the
   pulse's length behind the wall: a pulse spans several bins (8 cm, five of a Ping360's
   at 20 m) and speckle puts the strongest sample anywhere along it, and a tall beam
   meets floor and ceiling nearer than the wall its axis meets.
3. Reckoning over S4 (seed 0), flown by the geometric pilot: dead reckoning from the DVL
   and from the commands alone, in still water and in a current, as the error at the end
   over the distance flown (target with the DVL: 2% or less).

Run: python benchmarks/acoustic.py [--poses N] [--repeats N]
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import numpy as np

from cavenav.core.types import Pose
from cavenav.motion.kinematics import apply
from cavenav.pilots.geometric import GeometricPilot
from cavenav.safety.reckoning import ReckonedPose
from cavenav.sensors.config import SensorConfig
from cavenav.sensors.dvl import DopplerLog
from cavenav.sensors.rig import SensorRig
from cavenav.sensors.sonar import MULTIBEAM, PING360, Sonar
from cavenav.sim.env import CaveNavEnv
from cavenav.world.current import Current
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import SCENARIOS, load_scenario


def _ms(fn) -> float:  # noqa: ANN001
    start = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - start)


def _path(name: str, poses: int) -> tuple[RayCaster, list[Pose]]:
    """The cave's caster and the geometric pilot's first ``poses`` poses in it."""
    scenario = load_scenario(name, seed=0)
    caster = RayCaster(scenario.mesh)
    rig, pilot, pose, path = SensorRig(caster, SensorConfig()), GeometricPilot(), scenario.start, []
    for _ in range(poses):
        path.append(pose)
        pose = apply(pose, pilot.decide(rig.observe(pose)).action)
    return caster, path


def cost(name: str, poses: int, repeats: int) -> dict[str, float]:
    caster, path = _path(name, poses)
    rig = SensorRig(caster, SensorConfig())
    ping360, multibeam, dvl = Sonar(caster, PING360), Sonar(caster, MULTIBEAM), DopplerLog(caster)
    timed: dict[str, list[float]] = {"full": [], "ping360": [], "multibeam": [], "dvl": []}
    for before, pose in zip(path, path[1:], strict=False):
        for _ in range(repeats):
            timed["full"].append(_ms(lambda pose=pose: rig.observe(pose)))
            timed["ping360"].append(_ms(lambda pose=pose: ping360.observe(pose, 2.0)))
            timed["multibeam"].append(_ms(lambda pose=pose: multibeam.observe(pose, 2.0)))
            timed["dvl"].append(_ms(lambda b=before, p=pose: dvl.measure(b, p, 2.0)))
    return {key: statistics.median(values) for key, values in timed.items()}


def accuracy(name: str, poses: int) -> np.ndarray:
    """Over both sonars, counts of beams: whose axis hits rock in range; of those, whose
    strongest return lies within one bin of the axis's ray-cast distance; whose axis meets
    the rock square on (within 30 degrees of its normal); and of those, whose strongest
    return lies within the pulse's length behind the wall (from a bin before it)."""
    caster, path = _path(name, poses)
    counts = np.zeros(4, int)
    for config in (PING360, MULTIBEAM):
        sonar = Sonar(caster, config)
        bearings = config.bearings_deg()
        pulse_bins = round(config.sound_speed_m_s * config.pulse_s / 2 / config.bin_m)
        for pose in path:
            echoes = sonar.ping(pose, bearings)
            angle = np.radians(bearings)[:, None]
            axes = np.cos(angle) * pose.forward + np.sin(angle) * pose.right
            rays = np.hstack([np.tile(pose.position, (len(axes), 1)), axes]).astype(np.float32)
            cast = caster.cast_raw_rays(rays)
            distance, normals = cast["t_hit"], cast["primitive_normals"]
            hit = (
                np.isfinite(distance) & (distance < config.range_m) & (distance > config.blanking_m)
            )
            error = echoes[hit].argmax(axis=1) - np.floor(distance[hit] / config.bin_m)
            square = np.abs(np.sum(normals[hit] * axes[hit], axis=1)) > np.cos(np.radians(30))
            behind = (error >= -1) & (error <= pulse_bins)
            counts += (hit.sum(), np.sum(np.abs(error) <= 1), square.sum(), behind[square].sum())
    return counts


def reckoning(current: Current) -> dict[str, float]:
    """The end error of dead reckoning over S4, with and without the DVL, over the path."""
    env = CaveNavEnv(scenario="S4", sensors=SensorConfig(dvl=True), current=current)
    observation_dict, info = env.reset(seed=0)
    pilot, start = GeometricPilot(), info["vehicle_pose"]
    with_dvl = ReckonedPose.launched(start.x, start.y, start.z, start.psi)
    commanded, last, flown, position = with_dvl, None, 0.0, start.position
    for _ in range(150):
        observation = info["observation"]
        with_dvl = with_dvl.after(observation, last)
        blind = replace(observation, dvl=None)
        commanded = commanded.after(blind, last)
        decision = pilot.decide(observation)
        observation_dict, _, ended, _, info = env.step(decision.action)
        last = decision.action
        now = info["vehicle_pose"].position
        flown += float(np.linalg.norm(now - position))
        position = now
        if ended:
            break
    observation = info["observation"]
    with_dvl = with_dvl.after(observation, last)
    commanded = commanded.after(replace(observation, dvl=None), last)
    return {
        "flown_m": flown,
        "dvl_error_m": float(np.linalg.norm(with_dvl.position - position)),
        "dvl_sigma_m": with_dvl.sigma_m,
        "commanded_error_m": float(np.linalg.norm(commanded.position - position)),
        "commanded_sigma_m": commanded.sigma_m,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--poses", type=int, default=8, help="poses per scenario")
    parser.add_argument("--repeats", type=int, default=5, help="timings per pose")
    args = parser.parse_args()
    columns = ("full step ms", "ping360 ms", "multibeam ms", "dvl ms")
    print(f"{'scenario':<9} " + " ".join(f"{c:>13}" for c in columns))
    shares: dict[str, list[float]] = {"ping360": [], "multibeam": [], "dvl": []}
    for name in SCENARIOS:
        t = cost(name, args.poses, args.repeats)
        for key in shares:
            shares[key].append(t[key] / t["full"])
        print(f"{name:<9} " + " ".join(f"{t[k]:>13.2f}" for k in ("full", *shares)))
    print(
        "median share of the full step: "
        + ", ".join(f"{k} {100 * statistics.median(v):.1f}%" for k, v in shares.items())
        + " (targets: sonar <= 15%, dvl <= 2%)"
    )
    counts = np.zeros(4, int)
    for name in SCENARIOS:
        counts += accuracy(name, args.poses)
    hits, within, square, behind = counts
    share = 100 * behind / max(square, 1)
    print(f"strongest return within one bin of the wall: {within}/{hits} beams "
          f"({100 * within / max(hits, 1):.1f}%, target >= 95%); of the {square} beams "
          f"square on, within the pulse behind it: {behind} ({share:.1f}%)")  # fmt: skip
    for label, current in (("still water", Current()), ("current 2 m3/s", Current(2.0, 0.2))):
        r = reckoning(current)
        flown = max(r["flown_m"], 1e-9)
        dvl, blind = r["dvl_error_m"], r["commanded_error_m"]
        print(
            f"S4 reckoning, {label}: flown {flown:.1f} m; DVL error {dvl:.2f} m "
            f"({100 * dvl / flown:.2f}%, sigma {r['dvl_sigma_m']:.2f} m; target <= 2%); "
            f"commands alone {blind:.2f} m ({100 * blind / flown:.2f}%, "
            f"sigma {r['commanded_sigma_m']:.2f} m)"
        )


if __name__ == "__main__":
    main()

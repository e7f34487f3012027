"""Silt-out: thrust near a silt floor raises a cloud that hangs, spreads and blinds the
camera, and only the camera."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cavenav.core.types import Action, Pose
from cavenav.sensors.image_stats import frame_stats
from cavenav.sensors.optics import Optics
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.sim.env import CaveNavEnv
from cavenav.world import silt as silt_module
from cavenav.world.raycast import RayCaster
from cavenav.world.silt import MAX_PUFFS, WASH_REACH_M, Puff, SiltCloud
from tests.conftest import box_room, cavenav

LEVEL = Pose(0.0, 0.0, 0.0, 0.0)
FORWARD, DESCEND = Action(forward=1.0), Action(up=-0.5)


# ------------------------------------------------------------------ stirring and hanging


def test_thrust_far_above_the_floor_raises_nothing() -> None:
    assert SiltCloud().stirred(LEVEL, DESCEND, WASH_REACH_M + 0.1).puffs == ()
    assert SiltCloud().stirred(LEVEL, DESCEND, np.inf).puffs == ()
    assert SiltCloud().stirred(LEVEL, Action(), 0.3).puffs == ()  # holding still


def test_more_silt_rises_the_nearer_the_floor_and_the_more_the_thrust_points_at_it() -> None:
    def grams(action: Action, floor: float) -> float:
        return SiltCloud().stirred(LEVEL, action, floor).mass_g

    assert grams(DESCEND, 0.3) > grams(DESCEND, 0.8) > grams(DESCEND, 1.4) > 0
    assert grams(DESCEND, 0.5) > grams(FORWARD, 0.5) > 0


def test_a_puff_rises_below_the_vehicle_and_drifts_aft_of_the_move() -> None:
    cloud = SiltCloud().stirred(LEVEL, FORWARD, 0.6)
    (puff,) = cloud.puffs
    assert puff.centre[2] == pytest.approx(-0.6 + 0.25)
    assert puff.centre[1] > 0  # heading -y, so aft is +y
    later = cloud.stirred(LEVEL, Action(), 5.0)  # a step of hanging, no new silt
    (after,) = later.puffs
    assert after.centre[1] > puff.centre[1]
    assert after.sigma > puff.sigma and after.mass_g == puff.mass_g
    assert after.peak_g_m3 < puff.peak_g_m3


def test_a_current_carries_the_cloud_downstream() -> None:
    cloud = SiltCloud().stirred(LEVEL, FORWARD, 0.6)
    still = cloud.stirred(LEVEL, Action(), 5.0)
    flowing = cloud.stirred(LEVEL, Action(), 5.0, lambda at: np.array([0.1, 0.0, 0.0]))
    (a,), (b,) = still.puffs, flowing.puffs
    assert np.subtract(b.centre, a.centre) == pytest.approx([0.1 * silt_module.STEP_SECONDS, 0, 0])


def test_the_cloud_keeps_its_silt_when_its_oldest_puffs_merge() -> None:
    cloud = SiltCloud()
    for k in range(MAX_PUFFS + 6):
        cloud = cloud.stirred(Pose(0.0, -0.5 * k, 0.0, 0.0), DESCEND, 0.4)
    assert len(cloud.puffs) == MAX_PUFFS
    grams = silt_module.STIR_G * 1.0 * (1.0 - 0.4 / WASH_REACH_M) ** 2
    assert cloud.mass_g == pytest.approx((MAX_PUFFS + 6) * grams)


def test_a_puff_too_thin_to_see_is_dropped() -> None:
    faint = SiltCloud((Puff((0.0, 0.0, 0.0), 3.0, 0.5),))
    assert faint.stirred(LEVEL, Action(), np.inf).puffs == ()


def test_concentration_is_the_sum_of_the_puffs_gaussians() -> None:
    cloud = SiltCloud((Puff((0.0, 0.0, 0.0), 0.5, 10.0), Puff((3.0, 0.0, 0.0), 0.5, 10.0)))
    centre, between = cloud.concentration(np.array([[0.0, 0, 0], [1.5, 0, 0]]))
    assert centre == pytest.approx(cloud.puffs[0].peak_g_m3, rel=1e-6)
    assert between == pytest.approx(2 * centre * np.exp(-0.5 * 9.0), rel=1e-6)


# ------------------------------------------------------------------ what the camera sees


@pytest.fixture(scope="module")
def rig() -> SensorRig:
    return SensorRig(RayCaster(box_room()), SensorConfig(seed=3))


def test_a_cloud_in_front_of_the_camera_hides_the_room_but_never_the_depth(rig) -> None:
    pose = Pose(0.0, 8.0, 0.0, 0.0)
    clear = rig.render(pose, radiance=True)
    ahead = SiltCloud((Puff((0.0, 6.5, 0.0), 0.8, 40.0),))  # 1.3 m ahead of the lens
    silted = rig.render(pose, radiance=True, silt=ahead)
    assert np.array_equal(clear.depth_m, silted.depth_m)
    assert frame_stats(silted.rgb).contrast < 0.6 * frame_stats(clear.rgb).contrast
    # The far wall's light is lost in it, and the lamps light the cloud instead.
    middle = (slice(200, 280), slice(280, 360))
    assert silted.radiance[middle].mean() > clear.radiance[middle].mean()
    behind = SiltCloud((Puff((0.0, 12.0, 0.0), 0.8, 40.0),))  # behind the camera
    assert np.array_equal(rig.render(pose, silt=behind).rgb, clear.rgb)


# ------------------------------------------------------------------ in the environment


@pytest.mark.slow
def test_the_crawl_silts_out_by_default_and_the_setting_turns_it_off() -> None:
    env = CaveNavEnv(scenario="crawl", cave_seed=0, resolution=(160, 120))
    _, info = env.reset(seed=0)
    assert info["silt_g"] == 0.0
    _, _, _, _, info = env.step("descend 0.2 m")
    assert info["silt_g"] > 0
    off = CaveNavEnv(
        scenario="crawl",
        cave_seed=0,
        sensors=SensorConfig(optics=Optics(silt_out=False)).with_resolution(160, 120),
    )
    off.reset(seed=0)
    assert off.step("descend 0.2 m")[4]["silt_g"] is None
    s1 = CaveNavEnv(scenario="S1", cave_seed=0, resolution=(160, 120))
    s1.reset(seed=0)
    assert s1.step("descend 0.2 m")[4]["silt_g"] is None


def test_silt_out_is_an_optics_setting_with_a_flag() -> None:
    from cavenav.cli.episode_flags import episode_settings
    from cavenav.sensors.optics import optics_from_table

    assert Optics().silt_out is None  # the cave decides
    assert optics_from_table({"silt_out": True}).silt_out is True
    assert episode_settings(silt_out=False).optics == {"silt_out": False}
    assert "silt_out" not in episode_settings().optics
    assert replace(Optics(), silt_out=True).silt_out


@pytest.mark.slow
def test_steps_record_the_silt_hanging_in_the_water(tmp_path) -> None:
    done = cavenav("run", "crawl", "--steps", "3", "--no-frames", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    (run_dir,) = tmp_path.iterdir()
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    assert all("silt_g" in step for step in steps)

"""Depth as a stereo camera gives it, and what the pilots read where it gives none."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cavenav.core.types import Pose
from cavenav.sensors.config import SensorConfig
from cavenav.sensors.depth import denormalise_depth
from cavenav.sensors.fusion import UNKNOWN_AS_M, readable_depth
from cavenav.sensors.rig import SensorRig
from cavenav.sensors.sonar import MULTIBEAM, Sonar
from cavenav.sensors.stereo import StereoCamera, stereo_depth
from cavenav.world.raycast import RayCaster
from cavenav.world.silt import Puff, SiltCloud
from tests.conftest import box_room, synthetic_observation

START = Pose(0.0, 8.0, 0.0, 0.0)
FLAT = np.full((48, 64, 3), 90, np.uint8)


def textured(seed: int = 0) -> np.ndarray:
    """A frame of rock grain: contrast in every window."""
    return np.random.default_rng(seed).integers(40, 200, (48, 64, 3)).astype(np.uint8)


def test_no_texture_no_depth() -> None:
    depth = np.full((48, 64), 3.0, np.float32)
    assert np.isnan(stereo_depth(depth, FLAT, 64.0, StereoCamera(min_region_px=1), 0)).all()
    seen = stereo_depth(depth, textured(), 64.0, StereoCamera(min_region_px=1), 0)
    assert np.isfinite(seen).mean() > 0.95


def test_range_noise_grows_with_the_square_of_the_distance() -> None:
    camera = StereoCamera(min_region_px=1)
    errors = {}
    for z in (2.0, 8.0):
        depth = np.full((48, 64), z, np.float32)
        seen = stereo_depth(depth, textured(), 640.0, camera, 1)
        errors[z] = float(np.nanstd(seen - z))
    expected = 8.0**2 * camera.disparity_sigma_px / (640.0 * camera.baseline_m)
    assert errors[8.0] == pytest.approx(expected, rel=0.2)
    assert errors[8.0] / errors[2.0] == pytest.approx(16.0, rel=0.3)


def test_depth_edges_leave_holes() -> None:
    depth = np.full((48, 64), 10.0, np.float32)
    depth[:, :32] = 2.0  # a rock's edge in front of the far wall
    seen = stereo_depth(depth, textured(), 640.0, StereoCamera(min_region_px=1, speckle=0.0), 0)
    assert np.isnan(seen[:, 30:34]).all()
    assert np.isfinite(seen[:, :28]).mean() > 0.98 and np.isfinite(seen[:, 36:]).mean() > 0.98


@pytest.fixture(scope="module")
def caster() -> RayCaster:
    return RayCaster(box_room())


def test_silt_blinds_the_stereo_camera_not_the_exact_one(caster: RayCaster) -> None:
    stereo = SensorConfig(depth_source="stereo").with_optics({"water": "clear"})
    rig, exact = SensorRig(caster, stereo), SensorRig(caster, replace(stereo, depth_source="exact"))
    cloud = SiltCloud((Puff((0.0, 7.0, 0.0), 0.6, 400.0, (0.0, 0.0, 0.0)),))
    clear, silted = rig.observe(START), rig.observe(START, silt=cloud)
    assert clear.depth_source == "stereo"
    assert np.isfinite(clear.depth_m).mean() > 0.5
    assert np.isfinite(silted.depth_m).mean() < 0.1
    assert (silted.depth_png[np.isnan(silted.depth_m)] == 0).all()  # unknown reads near
    assert np.isfinite(exact.observe(START, silt=cloud).depth_m).all()
    blind = SensorRig(caster, replace(stereo, depth_source="none")).observe(START)
    assert not blind.has_depth and np.isnan(blind.depth_m).all()


def test_unknown_depth_is_never_free_water() -> None:
    depth = np.full((480, 640), np.nan, np.float32)
    observation = synthetic_observation(depth, depth_source="stereo")
    png, guessed = readable_depth(observation)
    assert guessed is not None and guessed.all()
    assert denormalise_depth(png, 0.0, 20.0) == pytest.approx(
        np.full(png.shape, UNKNOWN_AS_M), abs=0.05
    )
    exact = synthetic_observation(5.0)
    assert readable_depth(exact)[0] is exact.depth_png  # the exact image passes unchanged


def test_the_sonar_ranges_what_the_camera_cannot() -> None:
    # A hall 14 m high: the beam's aperture meets the far wall before floor or ceiling.
    sonar = Sonar(RayCaster(box_room(extents=(4.0, 20.0, 14.0))), MULTIBEAM).observe(START, 0.5)
    depth = np.full((480, 640), np.nan, np.float32)
    observation = synthetic_observation(depth, depth_source="stereo", sonar=sonar)
    png, guessed = readable_depth(observation)
    read = denormalise_depth(png, 0.0, 20.0)
    # Straight ahead the far wall is 18 m off; the camera sits 0.2 m ahead of the sonar.
    assert read[240, 320] == pytest.approx(17.8, abs=0.5)
    assert not guessed[240, 320]
    # Above the beam's aperture, no farther than where the ray meets the ceiling the
    # sounders give (3 m up in the synthetic observation).
    top = read[0, 320]
    assert top <= 3.0 / np.tan(np.radians(20.0)) + 0.2

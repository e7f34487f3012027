"""Camera, depth, echo sounders and clearance against geometry known by hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.depth import denormalise_depth, normalise_depth, read_exr, write_exr
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.types import Pose
from cavenav.world.collision import clearance
from cavenav.world.mesh import make_mesh
from cavenav.world.raycast import RayCaster

from .conftest import box_room


def test_forward_camera_matches_the_spec() -> None:
    cam = CameraIntrinsics()
    assert (cam.width, cam.height) == (640, 480)
    assert cam.focal_px == 640
    assert cam.hfov_deg == pytest.approx(53.13, abs=0.01)


def test_depth_normalisation_is_dark_near_bright_far_and_no_hit_is_dmax() -> None:
    depth = np.array([[0.0, 10.0, 20.0, 35.0, np.inf]], np.float32)
    png = normalise_depth(depth, 0.0, 20.0)
    assert png.tolist() == [[0, 128, 255, 255, 255]]
    assert denormalise_depth(png)[0, 1] == pytest.approx(10.0, abs=0.05)


def test_depth_range_is_user_settable() -> None:
    assert normalise_depth(np.array([[2.0, 6.0]]), 2.0, 6.0).tolist() == [[0, 255]]


def test_exr_round_trip_is_exact(tmp_path: Path) -> None:
    depth = np.random.default_rng(0).uniform(0, 30, (48, 64)).astype(np.float32)
    depth[0, 0] = np.inf
    write_exr(tmp_path / "d.exr", depth)
    assert np.array_equal(read_exr(tmp_path / "d.exr"), depth)


def test_the_rendered_depth_png_is_the_normalised_raw_depth() -> None:
    # The renderer's compiled kernel re-implements normalise_depth; they must agree.
    obs = SensorRig(RayCaster(box_room())).observe(Pose(0.5, 3, 0.2, 0.3))
    assert np.array_equal(obs.depth_png, normalise_depth(obs.depth_m, *obs.depth_range))


def test_depth_of_a_wall_ahead_is_its_planar_distance() -> None:
    # Room walls at y = -10; vehicle at y = 0 heading -y; camera 0.2 m ahead of centre.
    rig = SensorRig(RayCaster(box_room()))
    depth, _, rgb = rig.forward_frame(Pose(0, 0, 0, 0))
    assert depth.shape == (480, 640) and rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
    # The central pixels see the far wall 9.8 m away; planar depth is the same off-axis.
    assert depth[240, 320] == pytest.approx(9.8, abs=1e-3)
    assert depth[230, 300] == pytest.approx(9.8, abs=1e-3)


@pytest.mark.parametrize("sounder", ["camera", "beam"])
def test_echo_sounders_read_ceiling_and_floor(sounder: str) -> None:
    rig = SensorRig(RayCaster(box_room(extents=(8, 20, 4))), SensorConfig(sounder=sounder))
    d_top, d_bottom = rig.echo_sounders(Pose(0, 0, 0.5, 0.3))
    assert d_top == pytest.approx(1.5, abs=1e-3)
    assert d_bottom == pytest.approx(2.5, abs=1e-3)


def test_clearance_is_the_exact_distance_to_the_nearest_surface() -> None:
    caster = RayCaster(box_room())  # side walls at x = +-2
    assert clearance(caster, Pose(1.25, 0, 0, 0)) == pytest.approx(0.75, abs=1e-4)


def test_brighter_when_the_wall_is_closer() -> None:
    rig = SensorRig(RayCaster(box_room()))
    *_, far = rig.forward_frame(Pose(0, 5, 0, 0))
    *_, near = rig.forward_frame(Pose(0, -7, 0, 0))
    assert near[200:280, 280:360].mean() > far[200:280, 280:360].mean()


def test_rays_that_leave_the_cave_see_open_water() -> None:
    floor_only = make_mesh(
        np.array([[-50, -50, -1], [50, -50, -1], [0, 50, -1]], float), np.array([[0, 1, 2]])
    )
    depth, _, rgb = SensorRig(RayCaster(floor_only)).forward_frame(Pose(0, 0, 0, 0))
    assert np.isinf(depth[0]).all()  # the top row looks above the horizon
    assert rgb[0, 0, 2] > rgb[0, 0, 0]  # blue-green water, red absorbed


def test_rendering_is_deterministic() -> None:
    rig = SensorRig(RayCaster(box_room()))
    a = rig.observe(Pose(0.3, 1, 0.2, 0.4))
    b = rig.observe(Pose(0.3, 1, 0.2, 0.4))
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth_m, b.depth_m)

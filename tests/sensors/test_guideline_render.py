"""The cave line in the camera: a few pixels where it lies in view, at its true size."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from cavenav.core.types import Pose
from cavenav.sensors.camera import camera_to_world
from cavenav.sensors.rig import Frame, SensorConfig, SensorRig
from cavenav.world.guideline import Guideline
from cavenav.world.raycast import RayCaster
from tests.conftest import box_room

# A 4 x 20 x 4 m corridor (walls at x = +-2, floor at z = -2), the camera near one end
# looking down it (-y); a line tied across it 2 m ahead, half a metre below the camera,
# then along the right wall down the corridor, and along its floor.
POSE = Pose(0.0, 6.0, 0.0, 0.0)
TIES = np.array([[-1.99, 4.0, -0.5], [1.99, 4.0, -0.5], [1.99, -6.0, -1.0], [-1.0, -9.0, -1.99]])
ARROW = np.array([0.5, 4.0, -0.5])  # on the first span, facing the camera


def line(ties: np.ndarray = TIES, arrows: int = 0, colour: str = "white") -> Guideline:
    """A guideline through ``ties``, with an arrow at `ARROW` facing the camera when
    ``arrows``."""
    points = np.array([ARROW] * arrows).reshape(-1, 3)
    along = np.array([[1.0, 0.0, 0.0]] * arrows).reshape(-1, 3)
    facing = np.array([[0.0, 1.0, 0.0]] * arrows).reshape(-1, 3)
    return Guideline(np.asarray(ties, np.float64), points, along, facing, colour)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def caster() -> RayCaster:
    return RayCaster(box_room(extents=(4.0, 20.0, 4.0)))


def render(caster: RayCaster, guideline: Guideline | None) -> Frame:
    return SensorRig(caster, SensorConfig(seed=3), guideline).render(POSE, radiance=True)


def changed(on: Frame, off: Frame) -> np.ndarray:
    """(H, W) where the line changed the light reaching the lens."""
    assert on.radiance is not None and off.radiance is not None
    return np.abs(on.radiance - off.radiance).max(axis=2) > 0


def projected(rig_config: SensorConfig, points: np.ndarray) -> np.ndarray:
    """(n, 2) image (column, row) of world ``points`` (n, 3) in front of the camera."""
    camera = rig_config.camera
    origin = POSE.position + rig_config.camera_offset_m * POSE.forward
    local = (points - origin) @ camera_to_world(POSE)
    return camera.focal_px * local[:, :2] / local[:, 2:] + [camera.width / 2, camera.height / 2]


def along_line(ties: np.ndarray, step: float = 0.005) -> np.ndarray:
    """Points every ``step`` metres along the line through ``ties``."""
    parts = []
    for a, b in zip(ties[:-1], ties[1:], strict=True):
        count = int(np.linalg.norm(b - a) / step) + 1
        parts.append(a + np.linspace(0.0, 1.0, count)[:, None] * (b - a))
    return np.concatenate(parts)


def test_the_line_shows_as_a_thin_line_of_pixels_where_it_projects(caster: RayCaster) -> None:
    on, off = render(caster, line()), render(caster, None)
    mask = changed(on, off)
    rows, cols = np.nonzero(mask)
    image = projected(SensorConfig(), along_line(TIES))
    gap = np.min(np.hypot(cols[:, None] + 0.5 - image[None, :, 0], rows[:, None] + 0.5 - image[None, :, 1]), axis=1)  # fmt: skip  # noqa: E501
    assert gap.max() < 2.5  # nothing changes away from the line
    assert 400 < mask.sum() < 4000  # a line of pixels, not a band
    # A few pixels across at most, wherever it runs: never a band.
    assert mask.sum(axis=0).max() <= 6 or mask.sum(axis=1).max() <= 40
    # A white line over dark rock: brighter than the rock it hides.
    assert on.radiance is not None and off.radiance is not None
    assert (on.radiance[mask] - off.radiance[mask]).sum(axis=1).mean() > 0
    # The colour image shows it, and nothing else changes there but what the camera's
    # compression carries a few pixels around it.
    colour = np.abs(on.rgb.astype(int) - off.rgb.astype(int)).max(axis=2) > 0
    assert colour[mask].mean() > 0.5
    near = np.zeros_like(mask)
    for r, c in zip(rows, cols, strict=True):
        near[max(r - 16, 0) : r + 17, max(c - 16, 0) : c + 17] = True
    assert not colour[~near].any()


def test_without_a_line_in_view_the_frame_is_the_plain_one(caster: RayCaster) -> None:
    off = render(caster, None)
    behind = line(TIES + [0.0, 10.0, 0.0])  # every tie behind the camera
    through_rock = line(np.array([[-1.0, -12.0, -1.0], [1.0, -14.0, -1.0]]))  # past the end wall
    for hidden in (behind, through_rock):
        frame = render(caster, hidden)
        assert np.array_equal(frame.rgb, off.rgb)
        assert np.array_equal(frame.depth_m, off.depth_m)
    assert SensorRig(caster)._line is None  # off: no renderer, no buffers, no pass


def test_the_depth_image_takes_the_line_only_where_it_covers_half_a_pixel(
    caster: RayCaster,
) -> None:
    on, off = render(caster, line()), render(caster, None)
    deeper = on.depth_m != off.depth_m
    assert deeper.any()
    assert not (deeper & ~changed(on, off)).any()  # only where the line is
    assert (on.depth_m[deeper] < off.depth_m[deeper]).all()  # the line, in front of the rock
    # A 3 mm line covers half a 640-pixel-wide pixel out to 3.8 m: here only the span
    # across the corridor, 1.8 m from the lens, whose planar depth the pixels take; the
    # rest of its 20 m shows in colour alone.
    np.testing.assert_allclose(on.depth_m[deeper], 1.8, atol=1e-3)
    assert 300 < deeper.sum() < changed(on, off).sum() / 2
    assert not (on.depth_png != off.depth_png)[~deeper].any()


def test_an_arrow_is_drawn_as_a_small_triangle(caster: RayCaster) -> None:
    plain, arrowed = render(caster, line()), render(caster, line(arrows=1))
    added = changed(arrowed, plain)
    rows, cols = np.nonzero(added)
    centre = projected(SensorConfig(), ARROW[None])[0]
    # a triangle 10 cm long and 5 cm wide, 1.8 m away: some 36 x 18 pixels
    assert np.hypot(cols - centre[0], rows - centre[1]).max() < 20
    assert 200 < added.sum() < 500


def test_a_yellow_line_reflects_little_blue(caster: RayCaster) -> None:
    on, off = render(caster, line(colour="yellow")), render(caster, None)
    assert on.radiance is not None and off.radiance is not None
    mask = changed(on, off)
    red, green, blue = (on.radiance[mask] - off.radiance[mask]).sum(axis=0)
    assert blue < 0.5 * green and blue < 0.5 * red


def test_the_frame_does_not_depend_on_the_number_of_threads(caster: RayCaster) -> None:
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = render(caster, line(arrows=1))
        numba.set_num_threads(before)
        many = render(caster, line(arrows=1))
    finally:
        numba.set_num_threads(before)
    assert np.array_equal(one.rgb, many.rgb) and np.array_equal(one.depth_m, many.depth_m)


def test_an_observation_says_which_line_the_cave_has(caster: RayCaster) -> None:
    assert SensorRig(caster, guideline=line(colour="yellow")).observe(POSE).guideline == "yellow"
    assert SensorRig(caster).observe(POSE).guideline is None

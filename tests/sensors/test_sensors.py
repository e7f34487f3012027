"""Camera, depth, echo sounders and clearance against geometry known by hand."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cavenav.core.errors import ConfigError
from cavenav.core.types import Pose
from cavenav.sensors.camera import CameraIntrinsics, parse_resolution
from cavenav.sensors.depth import (
    EXR_COMPRESSIONS,
    denormalise_depth,
    normalise_depth,
    read_exr,
    save_png,
    write_exr,
)
from cavenav.sensors.rig import SensorConfig, SensorRig, grid_mean
from cavenav.world.collision import clearance
from cavenav.world.mesh import make_mesh
from cavenav.world.raycast import RayCaster
from tests.conftest import box_room


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


@pytest.mark.parametrize("compression", ["none", "zip", "htj2k"])
def test_exr_round_trip_is_exact_with_every_compression(tmp_path: Path, compression) -> None:
    import OpenEXR

    depth = np.random.default_rng(0).uniform(0, 30, (48, 64)).astype(np.float32)
    depth[0, 0] = np.inf
    write_exr(tmp_path / "d.exr", depth, compression)
    assert np.array_equal(read_exr(tmp_path / "d.exr"), depth)
    with OpenEXR.File(str(tmp_path / "d.exr")) as f:
        assert f.header()["compression"].name == EXR_COMPRESSIONS[compression]


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


ROOT = Path(__file__).resolve().parents[2]
THREAD_COUNTS = """
import numba, numpy as np
from cavenav.sensors.rig import SensorRig, grid_mean
from cavenav.core.types import Pose
from cavenav.world.raycast import RayCaster
from tests.conftest import box_room

rig = SensorRig(RayCaster(box_room()))
seen = []
for threads in (1, 2, 3):
    numba.set_num_threads(threads)
    frame = rig.render(Pose(0.3, 1, 0.2, 0.4), radiance=True)
    mean = grid_mean(rig._row_sums, rig._grid.shape[1])
    seen.append((frame.rgb, frame.depth_png, frame.radiance, mean))
for other in seen[1:]:
    assert all(np.array_equal(a, b) for a, b in zip(seen[0], other)), "differs"
"""


def test_a_frame_is_the_same_bits_on_one_two_or_three_threads() -> None:
    """A 640x480 frame, its kernels split over 1, 2 or 3 threads (in a fresh process
    given three, whatever this machine has): the same bits, and the same mean metered for
    its exposure. A batched environment shades each frame on one thread, a lone one on
    all; a sum over the threads' shares would differ in its last bits between them."""
    subprocess.run(
        [sys.executable, "-c", THREAD_COUNTS],
        cwd=ROOT,  # where `tests` imports from
        env={**os.environ, "NUMBA_NUM_THREADS": "3"},
        check=True,
        timeout=300,
    )


WORK_QUEUE = """
import threading
import numba, numpy as np
from cavenav.sensors import kernels
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.core.types import Pose
from cavenav.sim.vector_env import CaveNavVectorEnv
from cavenav.world.raycast import RayCaster
from tests.conftest import box_room

assert not kernels.KERNELS_RUN_CONCURRENTLY

def fly():  # a sweep's episode in flight beside others: its own tables, its own frames
    rig = SensorRig(RayCaster(box_room()), SensorConfig().with_resolution(160, 120))
    for step in range(10):
        rig.render(Pose(0.3, 1.0 - 0.2 * step, 0.2, 0.4))

threads = [threading.Thread(target=fly) for _ in range(4)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
assert numba.threading_layer() == "workqueue"
vector = CaveNavVectorEnv(4, resolution=(32, 24), action_format="vector", cave_seed=0,
                          workers=2)
vector.reset(seed=0)
for _ in range(3):
    vector.step(np.zeros((4, 4), np.float32))
print("flown")
"""


def test_where_numbas_threading_layer_cannot_launch_from_many_threads_frames_take_turns():
    """Numba's work queue (its layer where OpenMP cannot be loaded) aborts the process
    when two threads launch parallel kernels at once, as frames shaded on several
    threads would; there the kernels take turns, and nothing aborts."""
    done = subprocess.run(
        [sys.executable, "-c", WORK_QUEUE],
        cwd=ROOT,
        env={**os.environ, "NUMBA_THREADING_LAYER": "workqueue"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0 and done.stdout.strip() == "flown", done.stderr[-2000:]


FORKED = """
import os
import numpy as np
import cavenav.sim.env, cavenav.evaluation.executors, cavenav.sim.vector_env
from cavenav.sensors import kernels

pid = os.fork()
if pid == 0:  # as Gymnasium's async vector environment's workers are made
    rays = np.empty((100, 6), np.float32)
    kernels.fill_rays(np.ones((100, 3), np.float32), np.eye(3, dtype=np.float32),
                      np.zeros(3, np.float32), rays)
    os._exit(0)
assert os.waitpid(pid, 0)[1] == 0, "the forked child died"
"""


def test_a_process_forked_after_importing_cavenav_runs_the_kernels() -> None:
    """Finding the threading layer must not start Numba's OpenMP threads: a child forked
    after they have started is killed at its first parallel kernel."""
    subprocess.run([sys.executable, "-c", FORKED], check=True, timeout=300)


def test_the_metered_mean_is_the_exact_sum_whatever_the_order_of_the_rows() -> None:
    rows = np.random.default_rng(0).uniform(0, 1e3, (121, 3)) * np.logspace(-8, 8, 121)[:, None]
    assert np.array_equal(grid_mean(rows, 161), grid_mean(rows[::-1], 161))
    assert not np.array_equal(rows.sum(axis=0), rows[::-1].sum(axis=0))  # as sums are not


# ------------------------------------------------------------------ resolution


def test_a_smaller_camera_keeps_the_horizontal_field_of_view_with_square_pixels() -> None:
    paper = CameraIntrinsics()
    for width, height in [(160, 120), (84, 84), (33, 17)]:
        small = paper.with_resolution(width, height)
        assert small.hfov_deg == pytest.approx(paper.hfov_deg, abs=1e-9)
        assert small.focal_px == width  # square pixels: one focal length for both axes
    assert paper.with_resolution(160, 120).vfov_deg == pytest.approx(paper.vfov_deg)
    assert paper.with_resolution(84, 84).vfov_deg == pytest.approx(53.13, abs=0.01)


@pytest.mark.parametrize("size", [(0, 480), (640, -1), (84.5, 84), (True, 84), ("84", 84)])
def test_a_resolution_that_is_not_two_positive_whole_numbers_is_refused_in_one_line(
    size: tuple,
) -> None:
    with pytest.raises(ConfigError, match="camera resolution") as refused:
        SensorConfig().with_resolution(*size)
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("size", [(0, 6), (8,), (8, 6.5), "8x6", (100_000, 1), (8193, 8)])
def test_a_bad_sounder_resolution_is_refused_in_one_line(size: object) -> None:
    with pytest.raises(ConfigError, match="sounder resolution") as refused:
        SensorConfig(sounder_pixels=size)  # type: ignore[arg-type]
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize(("text", "size"), [("160x120", (160, 120)), ("84X84", (84, 84))])
def test_the_command_line_form_of_a_resolution_is_width_x_height(text: str, size: tuple) -> None:
    assert parse_resolution(text) == size


# Beyond 8192 a side, 100000x1 crashed the JPEG encoder and 30000x30000 ran out of memory.
@pytest.mark.parametrize(
    "text", ["160", "0x10", "axb", "160x120x3", "-5x5", "", "100000x1", "30000x30000", "8193x8"]
)
def test_text_that_is_not_a_resolution_is_refused_naming_it(text: str) -> None:
    with pytest.raises(ConfigError, match=f"'{text}' is not a resolution"):
        parse_resolution(text)


@given(st.integers(1, 8192), st.integers(1, 8192))
def test_every_positive_width_and_height_round_trip_through_the_text_form(w: int, h: int) -> None:
    assert parse_resolution(f"{w}x{h}") == (w, h)


@pytest.mark.parametrize("size", [(640, 480), (160, 120), (84, 84), (33, 17)])
def test_the_end_wall_spans_the_same_fraction_of_the_width_at_every_resolution(
    size: tuple[int, int],
) -> None:
    # Walls at x = +-2 and y = -10; the camera, 9.8 m from the end wall, sees it within
    # atan(2 / 9.8) either side of the axis: 2 * 2 / 9.8 = 40.8% of the width of a
    # 53-degree view (whose half-width is 0.5 focal lengths), whatever the pixel count.
    width, height = size
    rig = SensorRig(RayCaster(box_room()), SensorConfig().with_resolution(width, height))
    depth, _, rgb = rig.forward_frame(Pose(0, 0, 0, 0))
    assert depth.shape == (height, width) and rgb.shape == (height, width, 3)
    end_wall = np.isclose(depth[height // 2], 9.8, atol=1e-3)
    assert end_wall.mean() == pytest.approx(2 * 2 / 9.8, abs=1.5 / width)
    assert depth[height // 2, width // 2] == pytest.approx(9.8, abs=1e-3)


@pytest.mark.parametrize("size", [(160, 120), (84, 84), (33, 17)])
def test_small_and_odd_frames_are_shaded_to_their_last_row_and_column(
    size: tuple[int, int],
) -> None:
    # The shading works in blocks of 4 pixels; a size that is no multiple of 4 must not
    # leave the edge blocks black or read past the image.
    width, height = size
    rig = SensorRig(RayCaster(box_room()), SensorConfig().with_resolution(width, height))
    frame = rig.render(Pose(0.5, 3, 0.2, 0.3), radiance=True)
    assert frame.radiance is not None and frame.radiance.shape == (height, width, 3)
    assert np.isfinite(frame.depth_m).all()  # a closed room: every pixel sees a wall
    assert np.array_equal(frame.depth_png, normalise_depth(frame.depth_m))
    brightness = frame.radiance.astype(float).sum(axis=-1)  # before the camera's black clamp
    assert (brightness > 0).all()
    for edge, inside in [(0, 1), (-1, -2)]:  # first and last rows, then columns
        assert brightness[edge].mean() > 0.5 * brightness[inside].mean()
        assert brightness[:, edge].mean() > 0.5 * brightness[:, inside].mean()


def test_the_sounder_resolution_is_a_setting_and_reads_the_same_ranges(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    caster = RayCaster(box_room(extents=(8, 20, 4)))
    config = SensorConfig().with_resolution(84, 84).with_sensors({"sounder_resolution": [8, 6]})
    assert config.sounder_pixels == (8, 6) and config.resolution == (84, 84)
    rig = SensorRig(caster, config)
    casts: list[int] = []
    cast = caster.cast_raw_rays

    def counted(rays: np.ndarray) -> dict[str, np.ndarray]:
        casts.append(len(rays))
        return cast(rays)

    monkeypatch.setattr(caster, "cast_raw_rays", counted)
    obs = rig.observe(Pose(0, 0, 0.5, 0.3))
    assert (obs.d_top, obs.d_bottom) == (pytest.approx(1.5, abs=1e-3), pytest.approx(2.5, abs=1e-3))
    assert casts == [84 * 84 + 2 * 8 * 6]  # one cast: the frame, then both sounders


def test_a_sensors_table_with_an_unknown_key_names_it_and_the_keys() -> None:
    with pytest.raises(ConfigError, match=r"S1: \[sensors\]: unknown key\(s\) 'fov'"):
        SensorConfig().for_scenario("S1", {}, {}, {"fov": 60})


def test_the_run_options_override_the_scenario_sensors_table() -> None:
    table, options = (
        {"resolution": [160, 120], "sounder_resolution": [8, 6]},
        {"resolution": (84, 84)},
    )
    config = SensorConfig().for_scenario("S1", {}, {}, table, options)
    assert config.resolution == (84, 84) and config.sounder_pixels == (8, 6)
    assert SensorConfig().for_scenario("S1", {}, {}).resolution == (640, 480)


def test_frames_are_standard_pngs_that_common_readers_open_pixel_for_pixel(
    tmp_path: Path,
) -> None:
    import io

    import imageio.v3 as iio
    from PIL import Image

    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    save_png(colour[:, ::-1], tmp_path / "colour.png")  # a view, as a flipped image is
    save_png(depth, tmp_path / "depth.png")
    in_memory = io.BytesIO()
    save_png(colour, in_memory)
    with Image.open(tmp_path / "colour.png") as image:
        assert image.format == "PNG" and image.mode == "RGB"
        assert np.array_equal(np.asarray(image), colour[:, ::-1])
    with Image.open(tmp_path / "depth.png") as image:
        assert image.mode == "L" and np.array_equal(np.asarray(image), depth)
    assert np.array_equal(iio.imread(in_memory.getvalue()), colour)

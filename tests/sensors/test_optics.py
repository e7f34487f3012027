"""The colour image obeys the physics of light under water (SPEC section 2, issue 4).

Scenes are built by hand so the answers are known: a flat wall straight ahead at a
chosen distance, and a tube open at one end onto daylight. Physical claims are checked on
the linear radiance at the lens (`Frame.radiance`), before the camera's own processing.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from cavenav.core.errors import ConfigError
from cavenav.core.types import Pose
from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.kernels import spread_halo
from cavenav.sensors.lighting import backscatter_table, face_normals, rock_albedo, surface_table
from cavenav.sensors.optics import (
    CAVE_WATERS,
    FORWARD_CONE_DEG,
    HALO_SIGMA_DEG,
    JERLOV_KD,
    WATER_TYPES,
    Lamp,
    Optics,
    Water,
    jerlov_water,
    optics_from_table,
)
from cavenav.sensors.rig import (
    HALO_CELL,
    Frame,
    SensorConfig,
    SensorRig,
    camera_response,
    halo_weights,
)
from cavenav.world.mesh import CaveMesh, make_mesh
from cavenav.world.raycast import RayCaster

HEAD_MINUS_Y = Pose(0.0, 0.0, 0.0, 0.0)
CENTRE = (240, 320)  # pixel on the optical axis
# Lamps, water and rock only: no daylight, specks or noise unless a test asks for them,
# and the camera as a linear sensor with a soft curve that never clips (no black clamp,
# noise filter or compression: `test_camera_and_lamps` tests those), so that the linear
# signal can be read back from the image.
BARE = Optics(
    daylight=0.0, particles=0.0, noise=0.0, black_level=0.0, tone="soft", denoise=0.0,
    compression=0,
)  # fmt: skip


def box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> CaveMesh:
    solid = trimesh.creation.box(extents=extents)
    return make_mesh(solid.vertices + np.asarray(centre), solid.faces, "box")


def wall_ahead(distance: float) -> CaveMesh:
    """A 40 m box whose -y wall faces the camera ``distance`` metres ahead of the lens."""
    camera_y = -0.2  # SensorConfig.camera_offset_m ahead of the vehicle, heading -y
    return box((40.0, 40.0, 40.0), (0.0, camera_y - distance + 20.0, 0.0))


def open_tube(length: float = 20.0, radius: float = 2.5, segments: int = 48) -> CaveMesh:
    """A round passage along y, closed at +y, open at -y onto open water."""
    ys = np.arange(length / 2, -length / 2 - 1e-9, -0.5)
    angles = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    rings = [
        np.column_stack([radius * np.cos(angles), np.full(segments, y), radius * np.sin(angles)])
        for y in ys
    ]
    vertices = np.vstack([*rings, [[0.0, length / 2, 0.0]]])
    faces = []
    for k in range(len(ys) - 1):
        for j in range(segments):
            a, b = k * segments + j, k * segments + (j + 1) % segments
            faces += [[a, b, a + segments], [b, b + segments, a + segments]]
    cap = len(vertices) - 1
    faces += [[cap, (j + 1) % segments, j] for j in range(segments)]
    return make_mesh(vertices, np.array(faces), "open-tube")


def water_side(tube: CaveMesh) -> np.ndarray:
    """(m,) 0 where a tube triangle's normal points into the passage, else 1."""
    tri = tube.vertices[tube.faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = -tri.mean(axis=1) * np.array([1.0, 0.0, 1.0])  # toward the y axis
    return (np.einsum("ij,ij->i", normal, inward) < 0).astype(int)


def render(mesh: CaveMesh, optics: Optics = BARE, pose: Pose = HEAD_MINUS_Y, **cfg) -> Frame:
    return SensorRig(RayCaster(mesh), SensorConfig(optics=optics, **cfg)).render(
        pose, radiance=True
    )


def centre_radiance(distance: float, optics: Optics = BARE) -> np.ndarray:
    return render(wall_ahead(distance), optics).radiance[CENTRE].astype(np.float64)


# ------------------------------------------------------------------ attenuation


def test_a_wall_twice_as_far_is_darker_in_every_channel():
    near, far = centre_radiance(2.0), centre_radiance(4.0)
    assert np.all(far < near)
    # Inverse square and the lamps' geometry alone, in water that takes nothing:
    lossless = replace(BARE, water=Water((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    geometric = centre_radiance(4.0, lossless) / centre_radiance(2.0, lossless)
    assert np.all(far / near < geometric)  # the water takes more


def test_attenuation_grows_with_distance_and_is_strongest_in_red():
    distances = [1.5, 3.0, 6.0]
    radiance = np.array([centre_radiance(d) for d in distances])
    red_over_green = radiance[:, 0] / radiance[:, 1]
    assert np.all(np.diff(red_over_green) < 0)  # rock turns blue-green with distance
    loss = radiance[-1] / radiance[0]  # what each channel keeps from 1.5 m to 6 m
    assert loss[0] < loss[1] and loss[0] < loss[2]


def test_forward_scatter_keeps_four_fifths_of_the_light_the_water_scatters():
    turbid = WATER_TYPES["turbid"]
    assert turbid.forward_fraction == pytest.approx(0.80, abs=0.01)  # g = 0.92, 20 degrees
    assert np.all(np.asarray(turbid.absorption) < turbid.kept_attenuation)
    assert np.all(turbid.kept_attenuation < turbid.attenuation)
    isotropic = Water(turbid.absorption, turbid.scattering, phase_g=0.0)
    cone = (1.0 - np.cos(np.radians(FORWARD_CONE_DEG))) / 2.0  # its share of the sphere
    assert isotropic.forward_fraction == pytest.approx(cone)


def test_forward_scatter_spreads_light_into_a_halo_of_its_angle_and_keeps_it():
    camera = CameraIntrinsics()
    grid = np.zeros((121, 161, 3), np.float32)  # a 640x480 frame's shading grid's points
    grid[60, 80] = 1.0
    field, shading = grid.copy(), np.zeros((121, 161, 8), np.float32)
    spread_halo(field, HALO_CELL, halo_weights(camera.focal_px), shading)
    assert np.array_equal(shading[:, :, 4:7], field)  # the grid's light carries it
    assert field[:, :, 1].sum() == pytest.approx(1.0, rel=0.02)  # none is lost
    rows = np.arange(field.shape[0]) * 4.0  # the grid's points are 4 pixels apart
    weight = field[:, :, 1].sum(axis=1)
    centre = np.average(rows, weights=weight)
    spread = np.sqrt(np.average((rows - centre) ** 2, weights=weight))
    sigma_px = np.radians(HALO_SIGMA_DEG) * camera.focal_px
    assert spread == pytest.approx(sigma_px, rel=0.15)


@pytest.mark.parametrize("water", [*CAVE_WATERS, "jerlov-I", "jerlov-III", "jerlov-1C"])
def test_clear_and_ocean_waters_lose_red_first(water: str):
    k = WATER_TYPES[water].kept_attenuation
    assert k[0] > k[1] and k[0] > k[2]


@pytest.mark.parametrize("water", ["jerlov-3C", "jerlov-5C", "jerlov-7C", "jerlov-9C"])
def test_coastal_waters_lose_blue_before_green(water: str):
    k = WATER_TYPES[water].kept_attenuation  # dissolved organic matter absorbs the blue
    assert k[2] > k[1]


@pytest.mark.parametrize("name", list(JERLOV_KD))
def test_a_jerlov_water_loses_daylight_as_jerlov_measured(name: str):
    water = jerlov_water(name)  # Kd = a + b_b: molecules scatter half back, particles 1.83%
    molecules = np.array([0.0029 * (500 / nm) ** 4.32 for nm in (625.0, 537.5, 462.5)])
    particles = np.asarray(water.scattering) - molecules
    kd = np.asarray(water.absorption) + 0.5 * molecules + 0.0183 * particles
    table = np.array(JERLOV_KD[name])  # 450, 475, ..., 650 nm
    bands = [table[6:9].mean(), table[3:5].mean(), table[0:2].mean()]  # R, G, B
    assert kd == pytest.approx(bands, abs=2e-4)
    assert np.all(particles >= -1e-4)
    assert np.all(np.asarray(water.absorption) > 0)


def test_jerlov_waters_grow_murkier_and_their_load_scatters_more_as_it_grows():
    waters = [jerlov_water(name) for name in JERLOV_KD]
    green = np.array([w.attenuation[1] for w in waters])
    assert np.all(np.diff(green) > 0)
    albedo = np.array([w.scattering[1] / w.attenuation[1] for w in waters])
    assert albedo[0] < 0.05  # the clearest: pure seawater, which mostly absorbs
    assert albedo[-1] == pytest.approx(0.83, abs=0.03)  # as Petzold's turbid harbour: 0.83
    assert waters[0].phase_g == 0.0  # molecules scatter evenly
    assert waters[-1].phase_g == pytest.approx(0.924, abs=0.002)  # particles, forward
    with pytest.raises(ConfigError, match="Jerlov water type 'XI'"):
        jerlov_water("XI")


def test_the_muddiest_water_renders_far_rock_black_and_the_veil_without_gaps():
    # Its kept attenuation regains e^(0.8 b r) of the lost light: past 30 m that overflowed
    # float32 and made NaN, which the camera developed as black holes in the veil.
    hall = box((200.0, 200.0, 200.0), (0.0, -0.2 - 60.0 + 100.0, 0.0))  # rock 60 m ahead
    frame = render(hall, replace(BARE, water="jerlov-9C"))
    assert np.all(np.isfinite(frame.radiance))
    veil = frame.radiance[..., 1]
    assert veil.min() > 0.5 * np.median(veil)


# ------------------------------------------------------------------ backscatter


def test_backscatter_rises_with_turbidity():
    black_rock = replace(
        BARE, rock_colour=(0.0, 0.0, 0.0), sediment_colour=(0.0, 0.0, 0.0), specular=0.0
    )
    veil = [
        centre_radiance(8.0, replace(black_rock, water=water))[1]
        for water in ("clear", "ocean", "coastal", "turbid")
    ]
    assert veil[0] > 0.0
    assert np.all(np.diff(veil) > 0)


def test_backscatter_grows_along_the_ray_and_levels_off():
    table = backscatter_table(CameraIntrinsics(), Optics(water="coastal"))
    centre = table.values[table.values.shape[0] // 2, table.values.shape[1] // 2, :, 1]
    assert centre[0] == 0.0
    assert np.all(np.diff(centre) >= 0)
    knots = table.far * (np.arange(table.bins + 1) / table.bins) ** 2
    assert np.interp(10.0, knots, centre) > 0.95 * centre[-1]  # the lamps' beams fade out


def test_offset_lamps_leave_the_water_next_to_the_lens_dark():
    # Lamps beside the camera light the water at the lens only obliquely and from 0.2 m
    # off, while the water a metre out lies in their beams.
    table = backscatter_table(CameraIntrinsics(), Optics(water="turbid"))
    centre = table.values[table.values.shape[0] // 2, table.values.shape[1] // 2, :, 1]
    knots = table.far * (np.arange(table.bins + 1) / table.bins) ** 2
    assert np.interp(0.05, knots, centre) < 0.05 * centre[-1]
    assert np.interp(1.0, knots, centre) > 0.5 * centre[-1]


# ------------------------------------------------------------------ lamps and daylight


def test_a_lamp_lights_only_its_cone():
    narrow = replace(
        BARE, lamps=(Lamp(position=(0.0, 0.0, 0.0), beam_deg=10.0, hot_spot=0.0, share=1.0),)
    )
    frame = render(wall_ahead(3.0), narrow)
    green = frame.radiance[..., 1]
    assert green[CENTRE] > 0.0
    assert green[240, 620] < 1e-6 * green[CENTRE]  # 25 degrees off the axis: outside the beam


def test_turning_the_lamps_off_in_a_closed_cave_leaves_darkness():
    frame = render(wall_ahead(3.0), replace(BARE, light_power=0.0, daylight=1.0, particles=5.0))
    assert frame.radiance.max() == 0.0
    assert frame.rgb.max() == 0


def test_with_the_lamps_off_only_the_exit_daylight_remains():
    tube = open_tube()
    dark = replace(BARE, light_power=0.0, daylight=1.0)
    facing_exit = render(tube, dark, Pose(0.0, -4.0, 0.0, 0.0))
    exit_pixels = ~np.isfinite(facing_exit.depth_m)
    assert exit_pixels[CENTRE]
    walls = facing_exit.radiance[~exit_pixels]
    assert facing_exit.radiance[exit_pixels, 1].min() > 0.0
    assert walls[:, 1].max() > 0.0  # rock near the opening is lit by it
    # Bright blue-green water, not red.
    water = facing_exit.radiance[CENTRE]
    assert water[1] > water[0] and water[2] > water[0]
    facing_back = render(tube, dark, Pose(0.0, 6.0, 0.0, np.pi))
    assert facing_back.radiance[..., 1].mean() < 0.02 * facing_exit.radiance[..., 1].mean()
    no_daylight = render(tube, replace(dark, daylight=0.0), Pose(0.0, -4.0, 0.0, 0.0))
    assert no_daylight.radiance.max() == 0.0


def test_walls_near_an_opening_receive_more_daylight_than_walls_deep_inside():
    tube = open_tube()
    table = surface_table(RayCaster(tube), Optics())
    centres = tube.vertices[tube.faces].mean(axis=1)
    daylight = table[np.arange(len(centres)), water_side(tube), 4]
    wall = np.hypot(centres[:, 0], centres[:, 2]) > 2.0  # not the end cap
    near_exit = daylight[wall & (centres[:, 1] < -8.0)]
    deep = daylight[wall & (centres[:, 1] > 6.0)]
    assert near_exit.mean() > 20 * deep.mean()


def test_the_exit_is_brighter_the_closer_it_is():
    tube = open_tube(length=40.0)
    dark = replace(BARE, light_power=0.0, daylight=1.0)
    near = render(tube, dark, Pose(0.0, -14.0, 0.0, 0.0)).radiance[CENTRE]
    far = render(tube, dark, Pose(0.0, 10.0, 0.0, 0.0)).radiance[CENTRE]
    assert np.all(far < near)


def test_a_new_process_reads_the_lighting_table_from_disk_and_renders_the_same_frame(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from cavenav.sensors import lighting

    def new_process() -> None:  # nothing held in memory
        monkeypatch.setattr(lighting, "_SURFACE_CACHE", type(lighting._SURFACE_CACHE)())

    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path))
    new_process()
    tube = open_tube()
    pose = Pose(0.0, -4.0, 0.0, 0.0)
    cold = render(tube, Optics(), pose)
    (stored,) = (tmp_path / "lighting").glob("*.npy")
    new_process()
    monkeypatch.setattr(lighting, "_surface_table", None)  # as a new process: no computing
    warm = render(tube, Optics(), pose)
    np.testing.assert_array_equal(warm.rgb, cold.rgb)
    # Other parameters are another table; a file cut short is computed anew.
    stored.write_bytes(stored.read_bytes()[:100])
    monkeypatch.undo()
    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path))
    new_process()
    np.testing.assert_array_equal(render(tube, Optics(), pose).rgb, cold.rgb)
    assert np.load(stored).shape == (len(tube.faces), 2, 6)
    render(tube, Optics(rock_colour=(0.3, 0.3, 0.3)), pose)
    render(tube, Optics(), pose, seed=1)
    render(tube, Optics(water="turbid"), pose)
    assert len(list((tmp_path / "lighting").glob("*.npy"))) == 4
    # Code that computes tables differently (a new albedo, a new kernel) never reads the
    # tables the old code stored: it computes and stores its own.
    new_process()
    monkeypatch.setattr(lighting, "_source_digest", lambda: "changed code")
    compute, computed = lighting._surface_table, []

    def counted(*args: object) -> np.ndarray:
        computed.append(args)
        return compute(*args)

    monkeypatch.setattr(lighting, "_surface_table", counted)
    np.testing.assert_array_equal(render(tube, Optics(), pose).rgb, cold.rgb)
    assert len(computed) == 1
    assert len(list((tmp_path / "lighting").glob("*.npy"))) == 5


# ------------------------------------------------------------------ rock, snow, camera


def test_floors_carry_sediment_and_crevices_are_darker():
    tube = open_tube()
    table = surface_table(RayCaster(tube), Optics(sediment_colour=(0.5, 0.4, 0.25)))
    centres = tube.vertices[tube.faces].mean(axis=1)
    floor = (centres[:, 2] < -2.3) & (np.abs(centres[:, 1]) < 8.0)
    albedo = table[floor, water_side(tube)[floor], :3].mean(axis=0)
    assert albedo[0] > albedo[2] * 1.4  # silt is yellow-brown

    def darkening(mesh: CaveMesh) -> float:
        """The table's albedo of the walls (not floors) over the rock's own colour."""
        table = surface_table(RayCaster(mesh), Optics())
        walls = np.abs(face_normals(mesh)[0][:, 2]) < 0.5
        rock = rock_albedo(mesh)[mesh.faces].mean(axis=1)[walls]
        return float((table[walls, :, :3] / rock[:, None, :]).mean())

    small = box((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))  # every face of a small box meets others
    assert darkening(small) < darkening(wall_ahead(3.0))


def test_marine_snow_adds_lamp_lit_specks_fixed_in_the_world():
    mesh = wall_ahead(6.0)
    clean = render(mesh, BARE)
    snowy = render(mesh, replace(BARE, particles=30.0))
    assert snowy.particles > 10
    brighter = snowy.radiance[..., 1] > clean.radiance[..., 1] * 1.05
    assert 0 < brighter.mean() < 0.2
    again = render(mesh, replace(BARE, particles=30.0))
    assert np.array_equal(snowy.radiance, again.radiance)


def test_the_same_seed_gives_the_same_image_bit_for_bit():
    mesh = wall_ahead(4.0)
    busy = Optics(particles=5.0, noise=1.0)
    first = render(mesh, busy, seed=3)
    second = render(mesh, busy, seed=3)
    assert np.array_equal(first.rgb, second.rgb)
    assert np.array_equal(first.radiance, second.radiance)
    other = render(mesh, busy, seed=4)
    assert not np.array_equal(first.rgb, other.rgb)


def test_a_rig_renders_a_pose_alike_whatever_it_rendered_before():
    rig = SensorRig(RayCaster(wall_ahead(4.0)), SensorConfig(optics=Optics(particles=20.0)))
    first = rig.render(HEAD_MINUS_Y, radiance=True)
    rig.render(Pose(0.3, 0.5, -0.2, 0.4))  # other specks in the rig's reused buffers
    again = rig.render(HEAD_MINUS_Y)
    assert first.particles > 0
    assert np.array_equal(first.rgb, again.rgb)
    assert again.radiance is None  # only kept when asked for


def test_sensor_noise_is_zero_mean_and_can_be_switched_off():
    mesh = wall_ahead(4.0)
    quiet = render(mesh, replace(BARE, exposure=4.0))
    noisy = render(mesh, replace(BARE, exposure=4.0, noise=1.0))
    assert np.array_equal(quiet.radiance, noisy.radiance)  # noise is in the camera
    diff = noisy.rgb.astype(float) - quiet.rgb.astype(float)
    assert diff.std() > 0.5
    assert abs(diff.mean()) < 0.5


def test_vignetting_darkens_the_corners():
    mesh = wall_ahead(3.0)
    flat = replace(
        BARE,
        lamps=(Lamp(position=(0.0, 0.0, 0.0), beam_deg=170.0, hot_spot=0.0, share=1.0),),
        exposure=4.0,
    )
    plain = render(mesh, replace(flat, vignetting=0.0)).rgb[..., 1].astype(int)
    vignetted = render(mesh, replace(flat, vignetting=0.8)).rgb[..., 1].astype(int)
    assert vignetted[CENTRE] == plain[CENTRE]
    assert vignetted[5, 5] < plain[5, 5]


def test_auto_exposure_keeps_a_dim_scene_visible():
    far = render(wall_ahead(9.0), BARE).rgb[..., 1]
    near = render(wall_ahead(2.0), BARE).rgb[..., 1]
    assert 60 < np.median(far) < 200 and 60 < np.median(near) < 200


# ------------------------------------------------------------------ white balance, gain, exposure
# The camera's own processing, checked on what it develops. `developed` undoes the tone
# curve (Reinhard L / (1 + L), then sRGB), giving back the linear signal after white
# balance and gain; 8-bit levels make it good to about 1% in the mid-tones.

# A neutral grey rock, no vignetting: the wall's colour is the water's doing alone.
GREY_WALL = replace(BARE, rock_colour=(0.4, 0.4, 0.4), vignetting=0.0)
LUMINANCE = (0.25, 0.5, 0.25)  # the weights the camera meters with (R, G, B)


def developed(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) float64 linear signal behind 8-bit sRGB through the camera's tone curve."""
    srgb = rgb.astype(np.float64) / 255.0
    mapped = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return mapped / (1.0 - mapped)


def frame_mean(image: np.ndarray) -> np.ndarray:
    """(3,) mean colour of an (H, W, 3) image."""
    return image.reshape(-1, 3).astype(np.float64).mean(axis=0)


def test_white_balance_gains_move_the_frame_mean_toward_grey_by_their_strength():
    blue_green = np.array([0.02, 0.08, 0.07])  # distant rock in clear water
    luminance = blue_green @ LUMINANCE
    for strength in (0.0, 0.4, 1.0):
        gains, _ = camera_response(blue_green, replace(BARE, white_balance=strength))
        balanced = blue_green * gains
        # Each channel keeps (1 - strength) of its log-distance from the mean luminance.
        np.testing.assert_allclose(
            balanced, luminance * (blue_green / luminance) ** (1 - strength), rtol=1e-5
        )
    gains, _ = camera_response(blue_green, replace(BARE, white_balance=1.0))
    assert gains[0] > 1.0 > gains[1]  # red lifted, green lowered


def test_a_grey_wall_seen_through_water_comes_out_grey_with_full_white_balance():
    raw = render(wall_ahead(3.0), replace(GREY_WALL, white_balance=0.0))
    full = render(wall_ahead(3.0), replace(GREY_WALL, white_balance=1.0))
    np.testing.assert_array_equal(raw.radiance, full.radiance)  # balance is the camera's
    red, green, blue = frame_mean(raw.radiance)
    assert red < 0.3 * green  # the water took the red
    balanced = frame_mean(developed(full.rgb))
    assert balanced[0] == pytest.approx(balanced[1], rel=0.02)
    assert balanced[2] == pytest.approx(balanced[1], rel=0.02)
    unbalanced = frame_mean(developed(raw.rgb))
    assert unbalanced[0] < 0.3 * unbalanced[1]  # off: the sensor's raw colours


def test_grey_world_at_the_old_default_of_70_percent_corrects_part_of_the_way():
    strength = 0.7  # the camera's white balance before it was the BlueROV2 camera's own
    frame = render(wall_ahead(3.0), replace(GREY_WALL, white_balance=strength))
    raw_red_over_green = frame_mean(frame.radiance)[0] / frame_mean(frame.radiance)[1]
    colour = frame_mean(developed(frame.rgb))
    # Grey world at strength s leaves 1 - s of the colour cast (in log terms).
    assert colour[0] / colour[1] == pytest.approx(raw_red_over_green ** (1 - strength), rel=0.03)


def test_a_fixed_gain_multiplies_the_linear_signal_once():
    signal = {}
    for gain in (1.0, 2.0):
        frame = render(wall_ahead(3.0), replace(GREY_WALL, white_balance=0.0, exposure=gain))
        patch = (slice(200, 280), slice(280, 360))  # the lit centre, in the mid-tones
        signal[gain] = developed(frame.rgb[patch]).mean(axis=(0, 1))
        expected = gain * frame.radiance[patch].astype(np.float64).mean(axis=(0, 1))
        np.testing.assert_allclose(signal[gain], expected, rtol=0.03)
    np.testing.assert_allclose(signal[2.0] / signal[1.0], 2.0, rtol=0.03)


@pytest.mark.parametrize("key", [0.25, 0.5])
def test_auto_exposure_brings_the_frame_mean_to_its_key(key: float):
    optics = replace(GREY_WALL, white_balance=0.0, exposure_key=key, gain_range=(0.02, 1e3))
    frame = render(wall_ahead(12.0), optics)
    radiance = frame_mean(frame.radiance) @ LUMINANCE
    assert radiance < key / 2  # the scene itself is darker than the key: a gain of 2 or more
    assert frame_mean(developed(frame.rgb)) @ LUMINANCE == pytest.approx(key, rel=0.03)


def test_auto_exposure_stays_within_its_gain_range():
    floor = replace(GREY_WALL, white_balance=0.0, gain_range=(1.0, 16.0))
    bright = render(wall_ahead(2.0), floor)
    assert frame_mean(bright.radiance) @ LUMINANCE > 0.25  # brighter than the key
    np.testing.assert_allclose(  # at the least gain, here 1, a bright frame is not darkened
        frame_mean(developed(bright.rgb)), frame_mean(bright.radiance), rtol=0.03
    )
    dim = render(wall_ahead(3.0), replace(GREY_WALL, white_balance=0.0, light_power=0.01))
    high = GREY_WALL.gain_range[1]
    np.testing.assert_allclose(  # the ceiling at most: a nearly dark frame stays dark
        frame_mean(developed(dim.rgb)), high * frame_mean(dim.radiance), rtol=0.03
    )


def test_a_fixed_exposure_ignores_the_frame_and_auto_exposure_follows_it():
    dim, bright = np.array([0.005, 0.02, 0.02]), np.array([0.02, 0.08, 0.08])  # gains 11, 3
    fixed = replace(BARE, exposure=3.0, white_balance=0.0)
    assert camera_response(dim, fixed)[1] == camera_response(bright, fixed)[1] == 3.0
    auto = replace(BARE, white_balance=0.0)
    key = auto.exposure_key
    assert camera_response(dim, auto)[1] == pytest.approx(key / (dim @ LUMINANCE))
    assert camera_response(bright, auto)[1] == pytest.approx(key / (bright @ LUMINANCE))
    # With white balance on, the camera meters the balanced colours.
    gains, gain = camera_response(bright, replace(BARE, white_balance=0.4))
    assert gain * (bright * gains) @ LUMINANCE == pytest.approx(key)
    assert gain != pytest.approx(key / (bright @ LUMINANCE), rel=0.01)


# ------------------------------------------------------------------ depth degradation


def test_depth_is_exact_unless_degradation_is_asked_for():
    mesh = wall_ahead(5.0)
    frame = render(mesh, Optics(water="turbid"))
    assert frame.depth_m[CENTRE] == pytest.approx(5.0, abs=1e-3)


def test_depth_drops_out_where_too_little_lamp_light_returns():
    dim = Optics(water="turbid", depth_dropout=0.002, noise=0.0, particles=0.0, daylight=0.0)
    assert np.isinf(render(wall_ahead(12.0), dim).depth_m[CENTRE])
    assert render(wall_ahead(2.0), dim).depth_m[CENTRE] == pytest.approx(2.0, abs=1e-3)
    assert render(wall_ahead(12.0), dim).depth_png[CENTRE] == 255  # no return reads as far


def test_depth_noise_grows_with_distance():
    noisy = replace(BARE, depth_noise_m=0.1)
    spread = []
    for distance in (2.0, 8.0):
        depth = render(wall_ahead(distance), noisy).depth_m[200:280, 280:360]
        planar_truth = distance  # the wall is perpendicular to the optical axis
        spread.append(float(np.std(depth - planar_truth)))
    assert spread[0] < spread[1]
    assert spread[1] == pytest.approx(0.1 * 0.64, rel=0.2)  # 0.1 m at 10 m, times (8/10)^2


# ------------------------------------------------------------------ configuration


def test_optics_tables_layer_and_reject_unknown_keys():
    scenario_table = optics_from_table({"water": "coastal", "particles": 1.0})
    layered = optics_from_table({"particles": 8.0, "noise": None}, scenario_table)
    assert layered.water == "coastal" and layered.particles == 8.0
    with pytest.raises(ConfigError, match="'fog'"):
        optics_from_table({"fog": 1.0})
    with pytest.raises(ConfigError, match="unknown water type 'swamp'"):
        optics_from_table({"water": "swamp"})
    with pytest.raises(ConfigError, match="'light_power'"):
        optics_from_table({"light_power": -1})
    assert optics_from_table({"exposure": "auto"}, Optics(exposure=3.0)).exposure is None


def test_unknown_water_in_code_is_a_config_error():
    with pytest.raises(ConfigError, match="choose one of clear, ocean, coastal, turbid"):
        Optics(water="swamp")

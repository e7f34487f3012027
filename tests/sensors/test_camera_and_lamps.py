"""The vehicle's lamps and its camera behave as real ones do (issue 25).

Lamps are rated as a data sheet rates them (lumens, beam angle, colour temperature), and
the camera has a gain ceiling, a black clamp, a curve that clips, a noise filter and
lossy compression. Scenes are built by hand (a flat wall at a known distance, see
`test_optics`), so each answer is known.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import simplejpeg
import trimesh
from scipy import integrate

from cavenav.core.errors import ConfigError
from cavenav.sensors import kernels
from cavenav.sensors import rig as rig_module
from cavenav.sensors.image_stats import noise_sigma
from cavenav.sensors.optics import (
    FULL_SCALE_NITS,
    LUMA,
    Lamp,
    Optics,
    black_clamp,
    bluerov2_lamps,
    camera_curve,
    lamp_colour,
    optics_from_table,
)
from cavenav.sensors.rig import camera_response, compress
from cavenav.world.mesh import CaveMesh, make_mesh
from tests.sensors.test_optics import BARE, CENTRE, render, wall_ahead

LINEAR = BARE  # the camera as a linear sensor: no clamp, soft curve, no filter or coding
CAMERA = Optics(daylight=0.0, particles=0.0, noise=0.0)  # the default camera, no noise


# ------------------------------------------------------------------ lamps


def profile_of(lamp: Lamp) -> np.ndarray:
    """(1, n) the lamp's beam as the kernels read it."""
    return kernels.beam_profile(*lamp.exponents, lamp.hot_spot)[None, :]


@pytest.mark.parametrize("beam", [60.0, 90.0, 135.0])
def test_a_lamps_wide_lobe_falls_to_half_at_half_its_beam_angle(beam: float):
    profile = profile_of(Lamp(position=(0.0, 0.0, 0.0), beam_deg=beam, hot_spot=0.0))
    edge = math.cos(math.radians(beam / 2))
    assert kernels._curve(profile, 0, edge) == pytest.approx(0.5, rel=1e-3)
    assert kernels._curve(profile, 0, 1.0) == pytest.approx(1.0)
    assert kernels._curve(profile, 0, -0.1) == 0.0  # nothing behind the lamp


def test_a_lamps_flux_is_its_on_axis_intensity_times_its_solid_angle():
    lamp = Lamp(position=(0.0, 0.0, 0.0), beam_deg=90.0, hot_spot=0.35, hot_spot_deg=30.0)
    profile = profile_of(lamp)

    def intensity(theta: float) -> float:
        return kernels._curve(profile, 0, math.cos(theta)) * math.sin(theta)

    flux, _ = integrate.quad(intensity, 0.0, math.pi / 2, points=[math.radians(15)])
    assert 2 * math.pi * flux == pytest.approx(lamp.solid_angle_sr, rel=1e-3)


def test_lamp_power_follows_the_lumens_and_light_power_overrides_the_total():
    two = Optics()
    green = two.lamp_power[:, 1]
    lamp = two.fitted_lamps[0]
    # Two Lumen lights: 1,500 lm each over the profile's solid angle, a white wall's
    # radiance I0 / pi at 1 m, in units of the camera's full scale.
    expected = 1500.0 / lamp.solid_angle_sr / math.pi / FULL_SCALE_NITS
    np.testing.assert_allclose(green, [expected, expected], rtol=1e-5)
    doubled = replace(two, lamp_lumens=3000.0).lamp_power
    np.testing.assert_allclose(doubled, 2 * two.lamp_power, rtol=1e-6)
    assert Optics(light_power=20.0).lamp_power[:, 1].sum() == pytest.approx(20.0)
    assert not Optics(light_power=0.0).lit and Optics().lit


def test_four_lamps_light_a_wall_ahead_about_twice_as_much_as_two():
    two = render(wall_ahead(3.0), LINEAR).radiance[CENTRE]
    four = render(wall_ahead(3.0), replace(LINEAR, lamp_count=4)).radiance[CENTRE]
    np.testing.assert_allclose(four / two, 2.0, rtol=0.1)


def test_a_vehicle_carries_one_to_four_lamps():
    assert len(bluerov2_lamps(4)) == 4 and sum(lamp.share for lamp in bluerov2_lamps(3)) == 1
    with pytest.raises(ConfigError, match="1 to 4"):
        bluerov2_lamps(5)
    with pytest.raises(ConfigError, match="'lamp_count'"):
        optics_from_table({"lamp_count": 5})
    with pytest.raises(ConfigError, match="1 to 4"):
        Optics(lamp_count=0)
    assert len(replace(Optics(), lamp_count=3).fitted_lamps) == 3  # refitted, not kept


def test_a_narrower_beam_of_the_same_lumens_lights_the_centre_more_and_the_edges_less():
    def light(beam: float) -> np.ndarray:
        lamp = Lamp(position=(0.0, 0.0, 0.0), beam_deg=beam, hot_spot=0.0, share=1.0)
        return render(wall_ahead(2.0), replace(LINEAR, lamps=(lamp,))).radiance[..., 1]

    narrow, wide = light(30.0), light(130.0)
    assert narrow[CENTRE] > 5 * wide[CENTRE]
    assert narrow[0, 0] < 0.5 * wide[0, 0]  # the corner, 33 degrees off the axis


def test_daylight_white_is_6500_kelvin_and_warmer_lamps_light_redder():
    np.testing.assert_allclose(lamp_colour(6500.0), 1.0, rtol=1e-6)
    warm, cool = lamp_colour(3000.0), lamp_colour(9000.0)
    assert warm[0] > 1.0 > warm[2] and cool[2] > 1.0 > cool[0]
    grey = replace(LINEAR, rock_colour=(0.4, 0.4, 0.4), sediment_colour=(0.4, 0.4, 0.4))
    warm_wall = render(wall_ahead(1.0), replace(grey, lamp_kelvin=3000.0)).radiance[CENTRE]
    cool_wall = render(wall_ahead(1.0), replace(grey, lamp_kelvin=9000.0)).radiance[CENTRE]
    assert warm_wall[0] / warm_wall[2] > cool_wall[0] / cool_wall[2]


def test_wet_rock_adds_a_highlight_in_the_lamps_colour_where_they_face_it():
    matte = render(wall_ahead(1.0), replace(LINEAR, specular=0.0)).radiance[CENTRE]
    wet = render(wall_ahead(1.0), replace(LINEAR, specular=0.1)).radiance[CENTRE]
    assert np.all(wet > matte)
    # The glint is not tinted by the rock: it follows the lamps' light after the water,
    # whose colour differs from the warm grey rock's.
    glint = wet - matte
    rock = np.asarray(Optics().rock_colour)
    assert not np.allclose(glint / glint[1], matte / matte[1], rtol=0.05)
    assert glint[2] / glint[1] > (matte[2] / rock[2]) / (matte[1] / rock[1]) * 0.9


# ------------------------------------------------------------------ the camera


def test_the_camera_clamps_black_then_its_curve_is_linear_to_the_knee_and_clips_white():
    signal = np.array([0.0, 0.03, 0.04, 0.5, 0.8, 1.1, 1.2, 5.0])
    grey = np.repeat(signal[:, None], 3, axis=1)  # luma equals the signal
    out = camera_curve(black_clamp(grey, 0.04)[:, 1])
    assert out[0] == out[1] == out[2] == 0.0  # at or below the clamp: black
    assert out[3] == pytest.approx((0.5 - 0.04) / 0.96)  # linear below the knee
    assert out[-2] == out[-1] == 1.0  # clipped
    assert np.all(np.diff(out) >= 0)
    soft = camera_curve(signal, tone="soft")
    assert soft.max() < 1.0  # the older curve never clips


def test_highlights_clip_on_a_near_wall_and_not_under_the_soft_curve():
    near = wall_ahead(0.6)
    clipped = render(near, replace(LINEAR, tone="camera", exposure=2.0)).rgb
    soft = render(near, replace(LINEAR, tone="soft", exposure=2.0)).rgb
    assert clipped[CENTRE].max() == 255
    assert soft[CENTRE].max() < 255


def near_and_far() -> CaveMesh:
    """A wall 25 m ahead, and a rock 2 m ahead that fills the left of the view."""
    far = wall_ahead(25.0)
    near = trimesh.creation.box(extents=(2.0, 1.0, 3.0))
    near.apply_translation((1.4, -0.2 - 2.0 - 0.5, 0.0))  # +x is left, heading -y
    vertices = np.vstack([far.vertices, near.vertices])
    return make_mesh(vertices, np.vstack([far.faces, near.faces + len(far.vertices)]), "two")


def test_rock_beyond_the_lamps_reach_goes_black_when_the_camera_exposes_for_the_lit_rock():
    # Clear water: the far wall returns under a thousandth of the near rock's lamp light.
    frame = render(near_and_far(), CAMERA)
    far = frame.depth_m > 20.0
    near = frame.depth_m < 3.0
    assert far[240, 500] and near[240, 100]
    assert np.median(frame.rgb[far].max(axis=1)) < 16
    assert np.median(frame.rgb[near].max(axis=1)) > 100


def test_below_the_black_level_a_pixel_is_black_whatever_the_white_balance_lifts(
    monkeypatch: pytest.MonkeyPatch,
):
    # White balance can lift the red channel several times over (the water took the
    # red); a clamp on each channel would leave the unlit passage's veil maroon.
    def red_lifted(mean: np.ndarray, optics: Optics) -> tuple[np.ndarray, float]:
        return np.array([6.0, 1.0, 1.0], np.float32), 2.0

    monkeypatch.setattr(rig_module, "camera_response", red_lifted)
    frame = render(wall_ahead(25.0), replace(CAMERA, noise=1.0))
    raw_red = 6.0 * 2.0 * np.median(frame.radiance[..., 0])
    assert raw_red > CAMERA.black_level  # a clamp of the red channel alone would keep it
    assert np.median(frame.rgb.max(axis=2)) == 0


def test_the_black_clamp_scales_every_channel_by_what_it_takes_from_luma():
    red = np.array([[0.30, 0.05, 0.02]])  # reddish: its luma is 0.121
    luma = red @ np.asarray(LUMA)
    clamped = black_clamp(red, 0.04)
    np.testing.assert_allclose(clamped, red * (luma - 0.04) / (0.96 * luma))
    assert black_clamp(np.array([[0.10, 0.01, 0.01]]), 0.04).max() == 0.0  # luma 0.037


def test_the_black_clamp_darkens_without_changing_hue():
    def developed(black: float) -> np.ndarray:
        optics = replace(CAMERA, black_level=black, exposure=0.3, white_balance=0.0)
        rgb = render(wall_ahead(3.0), optics).rgb[200:280, 280:360].astype(float) / 255.0
        linear = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
        return linear.reshape(-1, 3).mean(axis=0)

    plain, clamped = developed(0.0), developed(0.1)
    assert clamped[1] < plain[1]
    np.testing.assert_allclose(clamped / clamped[1], plain / plain[1], rtol=0.03)


def test_facing_only_the_far_wall_the_gain_stops_at_its_ceiling_and_shows_the_veil():
    # With nothing lit in view, auto exposure raises the gain to its ceiling and the
    # water's own backscatter, a grey-blue haze, is what the frame shows; with no ceiling
    # the camera would lift it to the exposure key.
    optics = replace(CAMERA, white_balance=0.0)
    frame = render(wall_ahead(25.0), optics)
    assert camera_response(frame.radiance.reshape(-1, 3).mean(axis=0), optics)[1] == 16.0
    haze = np.median(frame.rgb.max(axis=2))
    unbounded = render(wall_ahead(25.0), replace(optics, gain_range=(0.02, 1e4)))
    assert 16 < haze < np.median(unbounded.rgb.max(axis=2))


def test_the_noise_filter_removes_most_of_the_noise_of_flat_rock():
    """Rock 12 m off, where the exposure's gain makes the noise far stronger than the
    rock's photographed detail (at 4 m the detail is stronger, and the filter keeps it:
    it only averages neighbours within the noise of each other).

    The rock is balanced toward grey (grey world at 70%): the filter smooths linear luma,
    and the statistic reads the luma of the 8-bit channels, which agree only where the
    channels are alike. The camera's own white balance leaves rock 12 m off in clear
    water blue-green (red a quarter of blue), and there the filter takes a third off."""
    mesh = wall_ahead(12.0)
    noisy = replace(LINEAR, noise=4.0, tone="camera", white_balance=0.7)  # auto exposure
    raw = render(mesh, noisy).rgb
    filtered = render(mesh, replace(noisy, denoise=1.0)).rgb
    assert noise_sigma(filtered) < 0.6 * noise_sigma(raw)
    patch = (slice(200, 280), slice(280, 360))
    assert abs(filtered[patch].mean() - raw[patch].mean()) < 1.0  # the level stays


def test_compression_is_a_real_jpeg_round_trip_close_to_its_input():
    rng = np.random.default_rng(0)
    smooth = np.clip(
        np.linspace(0, 255, 640)[None, :, None] + rng.normal(0, 4, (480, 640, 3)), 0, 255
    ).astype(np.uint8)
    assert compress(smooth, 0) is smooth
    coded = compress(smooth, 85)
    assert coded.shape == smooth.shape and coded.dtype == np.uint8
    assert not np.array_equal(coded, smooth)
    assert np.abs(coded.astype(int) - smooth).mean() < 4.0
    np.testing.assert_array_equal(compress(smooth, 85), coded)  # the same bits every time


@pytest.mark.parametrize("height", [480, 240, 121, 84, 30])
def test_compression_in_two_halves_gives_the_bits_of_one_round_trip(
    height: int, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setattr(rig_module.numba, "get_num_threads", lambda: 2)  # split, on any machine
    rng = np.random.default_rng(height)
    blocks = rng.integers(0, 256, (height // 4 + 1, 40, 3)).repeat(4, 0).repeat(4, 1)
    image = np.clip(blocks[:height] + rng.normal(0, 8, (height, 160, 3)), 0, 255)
    image = image.astype(np.uint8)  # sharp colour edges on every row of 4: the seam's test
    whole = simplejpeg.decode_jpeg(
        simplejpeg.encode_jpeg(image, quality=85, colorspace="RGB", colorsubsampling="420"),
        colorspace="RGB",
    )
    np.testing.assert_array_equal(compress(image, 85), whole)


def test_every_camera_stage_is_a_setting_of_the_optics_table():
    optics = optics_from_table(
        {"gain_max": 8, "black_level": 0.0, "tone": "soft", "denoise": 0.5, "compression": 0,
         "lamp_count": 4, "lamp_lumens": 1000, "lamp_beam_deg": 120, "lamp_kelvin": 4000,
         "specular": 0.0}
    )  # fmt: skip
    assert optics.gain_range == (Optics().gain_range[0], 8)
    assert (optics.black_level, optics.tone, optics.denoise, optics.compression) == (
        0.0, "soft", 0.5, 0,
    )  # fmt: skip
    assert len(optics.fitted_lamps) == 4 and optics.fitted_lamps[0].beam_deg == 120
    with pytest.raises(ConfigError, match="'tone'"):
        optics_from_table({"tone": "filmic"})

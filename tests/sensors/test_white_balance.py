"""The camera balances white as the BlueROV2's camera does (issue 49).

Its auto white balance picks a colour temperature, within its control's 2,800-6,500 K,
and applies that white point's gains: it corrects the colour of the light, not the
colour the water takes. Grey world, the white balance before it, stays for old scenario
files, and a fixed temperature is the camera's manual control. Scenes are built by hand
(`test_optics`: a flat wall at a known distance, the camera as a linear sensor).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cavenav.core.errors import ConfigError
from cavenav.sensors.optics import Optics, Water, lamp_colour, optics_from_table
from cavenav.sensors.rig import camera_response
from cavenav.sensors.white_balance import camera_kelvin, kelvin_gains, locus_kelvin
from tests.sensors.test_optics import GREY_WALL, developed, frame_mean, render, wall_ahead

CAMERA = Optics()  # the BlueROV2 camera's own auto white balance: the default
NO_WATER = Water((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # takes nothing: the lamps' light alone
BLUE_GREEN = np.array([0.02, 0.08, 0.07])  # distant rock in clear water: red taken
channel = st.floats(1e-4, 1.0)


def red_over_green(image: np.ndarray) -> float:
    red, green, _ = frame_mean(image)
    return float(red / green)


# ------------------------------------------------------------------ the camera's own


def test_the_default_is_the_camera_s_own_auto_white_balance_over_2800_to_6500_kelvin():
    assert CAMERA.white_balance_mode == "camera"
    assert CAMERA.white_balance_range == (2800.0, 6500.0)


@given(st.tuples(channel, channel, channel))
def test_the_camera_s_temperature_stays_within_its_range_however_coloured_the_frame(rgb):
    mean = np.array(rgb)
    kelvin = camera_kelvin(mean, CAMERA)
    assert 2800.0 <= kelvin <= 6500.0
    gains, _ = camera_response(mean, CAMERA)
    np.testing.assert_allclose(gains, kelvin_gains(kelvin), rtol=1e-6)


def test_a_blue_green_frame_pins_the_camera_at_daylight_a_red_one_at_incandescent():
    assert camera_kelvin(BLUE_GREEN, CAMERA) == 6500.0
    assert camera_kelvin(np.array([0.9, 0.1, 0.01]), CAMERA) == 2800.0


@pytest.mark.parametrize("kelvin", [3000.0, 4600.0, 6000.0])
def test_the_camera_finds_the_temperature_of_a_black_body_s_light_and_makes_it_white(kelvin):
    light = lamp_colour(kelvin).astype(np.float64)
    assert locus_kelvin(light) == pytest.approx(kelvin, rel=1e-3)
    balanced = light * camera_response(light, CAMERA)[0]
    np.testing.assert_allclose(balanced, balanced[1], rtol=1e-3)


def test_a_green_tint_no_black_body_has_stays_and_does_not_move_the_temperature():
    tinted = lamp_colour(4000.0) * np.array([0.8, 1.0, 0.8])  # green over magenta
    assert camera_kelvin(tinted, CAMERA) == pytest.approx(4000.0, rel=0.03)
    balanced = tinted * camera_response(tinted, CAMERA)[0]
    np.testing.assert_allclose(balanced / balanced[1], (0.8, 1.0, 0.8), rtol=0.03)


def test_a_grey_wall_under_warm_lamps_comes_out_grey():
    warm = replace(GREY_WALL, water=NO_WATER, lamp_kelvin=3200.0, white_balance=None)
    frame = render(wall_ahead(1.0), warm)
    assert red_over_green(frame.radiance) > 1.5  # the sensor sees the lamps' warmth
    colour = frame_mean(developed(frame.rgb))
    np.testing.assert_allclose(colour, colour[1], rtol=0.02)  # the camera takes it out


def test_lamps_warmer_than_its_range_leave_the_wall_warm():
    candle = replace(GREY_WALL, water=NO_WATER, lamp_kelvin=2000.0, white_balance=None)
    frame = render(wall_ahead(1.0), candle)
    assert camera_kelvin(frame_mean(frame.radiance), candle) == 2800.0
    red, green, blue = frame_mean(developed(frame.rgb))
    assert red > 1.2 * green > 1.2 * blue  # corrected only as far as 2,800 K


def test_near_rock_in_clear_water_keeps_the_cyan_the_water_gives_it():
    """Clear water takes red over the metre out and back and leaves green and blue: a
    colour off the black-body locus, beyond its 6,500 K end. The camera stays at daylight
    and shows the wall as its sensor sees it; grey world would have lifted the red."""
    wall = wall_ahead(1.0)
    camera = render(wall, replace(GREY_WALL, white_balance=None))
    seen = red_over_green(camera.radiance)
    assert seen < 0.75  # the water's doing: the rock is grey
    assert red_over_green(developed(camera.rgb)) == pytest.approx(seen, rel=0.03)
    grey_world = render(wall, replace(GREY_WALL, white_balance=0.7))
    assert red_over_green(developed(grey_world.rgb)) > 0.85


def test_a_deep_blue_green_cast_stays_where_grey_world_would_remove_it():
    gains, _ = camera_response(BLUE_GREEN, CAMERA)
    camera = BLUE_GREEN * gains
    assert camera[0] / camera[1] == pytest.approx(0.25, rel=0.01)  # the cast, as seen
    gains, _ = camera_response(BLUE_GREEN, replace(CAMERA, white_balance=1.0))
    grey = BLUE_GREEN * gains
    np.testing.assert_allclose(grey, grey[1], rtol=1e-6)


# ------------------------------------------------------------------ a fixed temperature


def test_a_fixed_temperature_gives_its_own_gains_whatever_the_frame():
    manual = replace(CAMERA, white_balance_kelvin=3200.0)
    assert manual.white_balance_mode == "manual"
    expected = 1.0 / lamp_colour(3200.0)  # a 3,200 K light made white
    for mean in (BLUE_GREEN, np.array([0.5, 0.3, 0.1]), np.array([0.2, 0.2, 0.2])):
        gains, _ = camera_response(mean, manual)
        np.testing.assert_allclose(gains, expected, rtol=1e-4)
    assert expected[2] > 1.0 > expected[0]  # tungsten's setting lifts blue, lowers red


def test_daylight_s_fixed_temperature_keeps_the_sensor_s_colours():
    daylight = replace(CAMERA, white_balance_kelvin=6500.0)
    np.testing.assert_allclose(camera_response(BLUE_GREEN, daylight)[0], 1.0, rtol=1e-6)


# ------------------------------------------------------------------ grey world, as before


@pytest.mark.parametrize("strength", [0.0, 0.4, 0.7, 1.0])
def test_grey_world_gives_the_gains_it_always_gave(strength):
    mean = np.maximum(BLUE_GREEN, 1e-9)
    luminance = float(mean @ (0.25, 0.5, 0.25))  # the camera before its own white balance
    old = np.clip((luminance / mean) ** strength, 0.25, 4.0).astype(np.float32)
    gains, _ = camera_response(BLUE_GREEN, replace(CAMERA, white_balance=strength))
    assert gains.dtype == np.float32 and np.array_equal(gains, old)


# ------------------------------------------------------------------ settings


def test_a_scenario_file_s_white_balance_keeps_its_meaning_and_names_the_new_ones():
    assert optics_from_table({"white_balance": 0.5}).white_balance_mode == "grey-world"
    manual = optics_from_table({"white_balance_kelvin": 4600})
    assert (manual.white_balance_mode, manual.white_balance_kelvin) == ("manual", 4600.0)
    ranged = optics_from_table({"white_balance_range": [2000, 10000]})
    assert ranged.white_balance_range == (2000.0, 10000.0)
    assert optics_from_table({"white_balance": "camera"}, manual).white_balance_mode == "camera"


def test_the_layer_that_sets_the_white_balance_decides_it():
    grey = optics_from_table({"white_balance": 0.7})
    manual = optics_from_table({"white_balance_kelvin": 3000}, grey)
    assert (manual.white_balance, manual.white_balance_kelvin) == (None, 3000.0)
    back = optics_from_table({"white_balance": 0.3}, manual)
    assert (back.white_balance, back.white_balance_kelvin) == (0.3, None)
    assert optics_from_table({"noise": 0.5}, manual).white_balance_mode == "manual"


@pytest.mark.parametrize(
    ("table", "says"),
    [
        ({"white_balance": 0.7, "white_balance_kelvin": 4000}, "both set"),
        ({"white_balance": "camera", "white_balance_kelvin": 4000}, "both set"),
        ({"white_balance_kelvin": 500}, "white_balance_kelvin"),
        ({"white_balance": 1.5}, "white_balance"),
        ({"white_balance_range": [6500, 2800]}, "least first"),
    ],
)
def test_a_white_balance_no_camera_has_is_refused_naming_it(table, says):
    with pytest.raises(ConfigError, match=says):
        optics_from_table(table)


def test_two_white_balances_at_once_are_refused_in_python_too():
    with pytest.raises(ConfigError, match="set one"):
        Optics(white_balance=0.7, white_balance_kelvin=4600.0)

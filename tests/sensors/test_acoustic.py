"""The imaging sonars and the DVL: echoes where the walls are, the devices' published
geometry, a scanning head that only sees what it swept, and velocity over the ground."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cavenav.core.errors import ConfigError
from cavenav.core.types import Pose
from cavenav.sensors.dvl import A50, DopplerLog, ping_rate_hz
from cavenav.sensors.sonar import MULTIBEAM, PING360, Sonar, SonarConfig, absorption_db_per_m
from cavenav.world.raycast import RayCaster
from cavenav.world.silt import Puff, SiltCloud
from tests.conftest import box_room

# The room: walls at x = +-2, y = +-10, z = +-2. Facing -y from (0, 8, 0), the wall
# ahead is 18 m away and the side walls 2 m either side.
START = Pose(0.0, 8.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def caster() -> RayCaster:
    return RayCaster(box_room())


def strongest_m(echoes: np.ndarray, bin_m: float) -> np.ndarray:
    return (echoes.argmax(axis=1) + 0.5) * bin_m


def test_absorption_follows_francois_garrison() -> None:
    # Fresh water at 15 C, 750 kHz: pure water's viscosity alone, 0.146 dB/m; sea water
    # adds the magnesium sulphate relaxation.
    assert absorption_db_per_m(750.0) == pytest.approx(0.146, abs=0.002)
    assert absorption_db_per_m(750.0, salinity_psu=35.0) == pytest.approx(0.214, abs=0.005)
    assert absorption_db_per_m(1200.0) > absorption_db_per_m(750.0)


def test_the_presets_carry_the_published_geometry() -> None:
    assert (PING360.frequency_khz, PING360.beam_width_deg, PING360.aperture_deg) == (750, 2, 25)
    assert len(PING360.bearings_deg()) == 400  # a gradian each
    assert (MULTIBEAM.fov_deg, MULTIBEAM.beams, MULTIBEAM.aperture_deg) == (130, 512, 20)
    with pytest.raises(ConfigError, match="sonar ping360: bad range_m"):
        replace(PING360, range_m=0.5)


@pytest.mark.parametrize("config", [PING360, MULTIBEAM], ids=["ping360", "multibeam"])
def test_a_beam_square_to_a_wall_peaks_at_its_distance(
    caster: RayCaster, config: SonarConfig
) -> None:
    sonar = Sonar(caster, config)
    echoes = sonar.ping(START, np.array([-90.0, 0.0, 90.0]))  # left wall, far wall, right wall
    assert echoes.shape == (3, config.samples)
    found = strongest_m(echoes, config.bin_m)
    assert found[0] == pytest.approx(2.0, abs=0.1)
    assert found[2] == pytest.approx(2.0, abs=0.1)
    assert found[1] == pytest.approx(18.0, abs=0.2)
    # Nothing comes back from inside the blanking distance, nor from behind the wall.
    assert not echoes[:, : int(config.blanking_m / config.bin_m)].any()
    assert echoes[0, int(2.5 / config.bin_m) :].mean() < 0.2 * echoes[0].max()


def test_speckle_is_the_same_for_the_same_seed_and_pose(caster: RayCaster) -> None:
    sonar = Sonar(caster, MULTIBEAM)
    bearings = MULTIBEAM.bearings_deg()
    first, again = sonar.ping(START, bearings, 3), sonar.ping(START, bearings, 3)
    assert np.array_equal(first, again)
    assert not np.array_equal(first, sonar.ping(START, bearings, 4))


def test_silt_hazes_the_image_but_does_not_hide_the_wall(caster: RayCaster) -> None:
    sonar = Sonar(caster, replace(PING360, snow_per_m3=0.0))
    ahead = np.array([0.0])
    cloud = SiltCloud((Puff((0.0, 5.0, 0.0), 0.8, 200.0, (0.0, 0.0, 0.0)),))
    clear, silted = sonar.ping(START, ahead)[0], sonar.ping(START, ahead, 0, cloud)[0]
    inside = slice(int(2.5 / PING360.bin_m), int(3.5 / PING360.bin_m))  # 3 m ahead: the puff
    assert silted[inside].mean() > clear[inside].mean() + 20
    assert abs(strongest_m(silted[None], PING360.bin_m)[0] - 18.0) < 0.3


def test_a_scanning_head_sees_only_what_it_swept(caster: RayCaster) -> None:
    sonar = Sonar(caster, PING360)  # a 120-degree sector ahead, one gradian a ping
    sweep = sonar.observe(START, sonar.sweep_s)
    sector = np.abs(PING360.bearings_deg()) <= 60.0
    assert sweep.fresh[sector].all() and not sweep.fresh[~sector].any()
    assert not sweep.echoes[~sector].any()  # never pinged: the disc is empty there
    moved = Pose(0.0, 7.0, 0.0, math.radians(30.0))
    step = sonar.observe(moved, 1.0)
    expected = round(1.0 / PING360.ping_s)
    assert expected - 1 <= step.fresh.sum() <= expected + 1
    old = ~step.fresh & sector
    assert step.age_s[old].min() >= 1.0 and np.all(step.age_s[step.fresh] == 0)
    assert step.turned_deg[old] == pytest.approx(np.full(old.sum(), 30.0))
    assert step.moved_m[old] == pytest.approx(np.ones(old.sum()))
    assert step.fan.shape == (400, 400) and step.fan.any()


def test_the_multibeam_fan_is_drawn_apex_down(caster: RayCaster) -> None:
    image = Sonar(caster, MULTIBEAM).observe(START, 0.5)
    height, width = image.fan.shape
    assert height == 400 and width > height  # 130 degrees: wider than tall
    assert not image.fan[-1, :10].any()  # outside the fan at the bottom corners
    assert image.fresh.all()


def test_the_dvl_measures_the_move_over_the_ground(caster: RayCaster) -> None:
    dvl = DopplerLog(caster)
    dvl.reset(7)
    after = Pose(0.0, 7.0, 0.0, 0.0)  # 1 m ahead (-y) in 2 s
    reading = dvl.measure(START, after, 2.0)
    assert reading.locked
    assert reading.velocity_m_s == pytest.approx([0.5, 0.0, 0.0], abs=0.02)
    # Four beams 22.5 degrees off vertical, 2 m above the floor.
    assert reading.beam_ranges_m == pytest.approx(
        np.full(4, 2.0 / math.cos(math.radians(22.5))), abs=0.01
    )
    assert reading.altitude_m == pytest.approx(2.0, abs=0.01)
    assert ping_rate_hz(reading.altitude_m) == 10.0  # range mode 1: 0.3-3 m


def test_the_dvl_loses_lock_with_nothing_in_range() -> None:
    dvl = DopplerLog(RayCaster(box_room(extents=(200.0, 200.0, 120.0))))
    reading = dvl.measure(Pose(0, 0, 0), Pose(0, -1, 0), 2.0)
    assert not reading.locked
    assert np.isnan(reading.velocity_m_s).all() and math.isnan(reading.altitude_m)
    assert A50.max_range_m == 50.0

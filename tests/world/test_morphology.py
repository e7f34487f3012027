"""Passage morphologies: each feature changes the cave the way its cave-science name says.

The section's terms are checked on the field itself (cheap, exact); one small cave per
feature is meshed and probed with rays, as the vehicle's sensors would see it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cavenav.world.morphology import Boulder, Section, Speleothem, carve_scallops, extent
from cavenav.world.procedural import PassageSpec, build_cave
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import SCENARIOS, Difficulty

# A straight passage along -y, 2 m half-width and half-height, its samples every 0.25 m.
Y = -np.arange(0.0, 16.01, 0.25)
N = len(Y)
AXIS = np.stack([np.zeros(N), Y, np.zeros(N)], axis=1)


def _section_field(section: Section, a: float, b: float, half: float = 2.0) -> tuple[float, float]:
    """(water, sediment) of ``section`` at sample 8, offset (a across, b up)."""
    one = np.ones(1)
    water, sediment = section.field(
        np.array([8]), a * one, b * one, 0 * one, half * one, half * one, 2.0 * one
    )
    return float(water[0]), float(sediment[0])


def _cave(section: Section | None = None, **spec) -> RayCaster:
    """The straight passage with ``section`` and smooth walls, meshed at 0.2 m."""
    options = {"roughness": 0.0, "seed": 1, "exit_index": N - 8, **spec}
    cave = PassageSpec(AXIS, np.full(N, 2.0), np.full(N, 2.0), section=section, **options)
    return RayCaster(build_cave(cave, name="morphology"))


def _hit(caster: RayCaster, origin: tuple[float, float, float], direction) -> float:
    return float(caster.first_hit(np.array([origin]), np.array([direction], float))[0])


PLAIN = Section.plain(N)
EVERYWHERE = np.ones(N)


# ------------------------------------------------------------------ the section's terms


def test_a_plain_section_is_the_ellipse_the_tube_always_had() -> None:
    assert _section_field(PLAIN, 0.5, 0.5)[0] < 0  # water near the axis
    assert _section_field(PLAIN, 1.9, 0.0)[0] < 0 < _section_field(PLAIN, 2.1, 0.0)[0]
    assert _section_field(PLAIN, 0.0, 1.9)[0] < 0 < _section_field(PLAIN, 0.0, 2.1)[0]
    assert _section_field(PLAIN, 0.0, 0.0)[1] == -np.inf  # no sediment


def test_squareness_fills_the_corners_a_bedding_plane_or_canyon_has() -> None:
    corner = (1.5, 1.5)  # outside the ellipse (1.5^2 + 1.5^2 > 2^2), inside the square
    assert _section_field(PLAIN, *corner)[0] > 0
    assert _section_field(replace(PLAIN, squareness=EVERYWHERE), *corner)[0] < 0
    assert extent(2.0, 0.75, 1.0) > extent(2.0, 0.75, 0.0)


def test_a_ledge_hides_what_lies_above_it_from_the_axis() -> None:
    """A cross-section with a ledge is not star-shaped about the axis: water above the
    shelf, rock between it and the axis."""
    ledge = replace(PLAIN, ledge=0.8 * EVERYWHERE, ledge_height=0.5 * EVERYWHERE)
    above_shelf = (1.55, 1.15)  # by the left wall, just over the shelf's top at 1.0 m
    assert _section_field(ledge, *above_shelf)[0] < 0
    on_the_way = (1.55 * 0.8, 1.15 * 0.8)
    assert _section_field(ledge, *on_the_way)[0] > 0
    assert _section_field(PLAIN, *on_the_way)[0] < 0  # without the shelf: water
    assert _section_field(ledge, -1.55, 0.8)[0] < 0  # the right wall has none


def test_a_notch_undercuts_the_wall_on_its_own_side() -> None:
    notch = replace(PLAIN, notch=-0.8 * EVERYWHERE, notch_height=-0.2 * EVERYWHERE)
    in_the_notch = (-2.4, -0.4)  # 0.4 m into the right wall's rock
    assert _section_field(PLAIN, *in_the_notch)[0] > 0
    assert _section_field(notch, *in_the_notch)[0] < 0
    assert _section_field(notch, 2.4, -0.4)[0] > 0


def test_sediment_lays_a_flat_floor_of_ripples_a_few_centimetres_high() -> None:
    silt = replace(PLAIN, sediment=0.5 * EVERYWHERE)
    tops = []
    for along in np.linspace(0.0, 5.0, 101):
        _, floor = silt.field(*(np.array([v]) for v in (8, 0.3, -1.5, 0.0, 2.0, 2.0, along)))
        tops.append(-1.5 + float(floor[0]))  # the sediment's top, relative to the axis
    assert min(tops) > -1.5 - 0.05 and max(tops) < -1.5 + 0.05  # -2 m + 0.5 m of silt
    assert max(tops) - min(tops) > 0.05  # and rippled


# ------------------------------------------------------------------ meshed and probed


@pytest.mark.slow
def test_each_section_feature_is_in_the_mesh_where_the_sensors_look() -> None:
    plain = _cave()
    down, up, left = (0, 0, -1), (0, 0, 1), (1, 0, 0)
    station = (0.0, -6.0, 0.0)
    assert abs(_hit(plain, station, down) - 2.0) < 0.1
    assert abs(_hit(plain, station, up) - 2.0) < 0.1

    keyhole = replace(PLAIN, canyon_width=0.9 * EVERYWHERE, canyon_depth=1.5 * EVERYWHERE)
    assert abs(_hit(_cave(keyhole), station, down) - 3.5) < 0.15  # the canyon's floor
    assert abs(_hit(_cave(keyhole), (0.0, -6.0, -2.8), left) - 0.9) < 0.15  # its wall

    channel = replace(PLAIN, ceiling_channel=0.5 * EVERYWHERE)
    assert abs(_hit(_cave(channel), station, up) - 2.5) < 0.15

    silted = replace(PLAIN, sediment=0.6 * EVERYWHERE)
    floor = [_hit(_cave(silted), (0.0, y, 0.0), down) for y in np.arange(-3.0, -12.0, -0.3)]
    assert abs(np.mean(floor) - 1.4) < 0.06 and np.ptp(floor) < 0.2  # flat, 0.6 m up


@pytest.mark.slow
def test_scallops_dimple_a_smooth_wall_by_centimetres() -> None:
    directions = [(np.cos(t), 0.0, np.sin(t)) for t in np.linspace(-1.2, 1.2, 25)]
    smooth, scalloped = _cave(), _cave(scallops=0.8)
    for station in np.arange(-3.0, -12.0, -0.5):
        origin = (0.0, station, 0.0)
        for d in directions:
            gap = _hit(scalloped, origin, d) - _hit(smooth, origin, d)
            assert -0.02 < gap < 0.8 / 8 + 0.06  # only ever cut into the rock, a dish deep
    walls = np.array(
        [_hit(scalloped, (0.0, s, 0.0), (1, 0, 0)) for s in np.arange(-3.0, -12.0, -0.1)]
    )
    assert walls.std() > 0.01


def test_scallops_of_no_size_leave_the_field_untouched() -> None:
    phi = np.linspace(-1, 1, 1000, dtype=np.float32).reshape(10, 10, 10)
    before = phi.copy()
    carve_scallops(phi, np.zeros(3), 0.2, 0.0, 0.0, np.random.default_rng(0))
    assert np.array_equal(phi, before)


# ------------------------------------------------------------------ rocks


def test_an_angular_boulder_is_a_block_of_flat_faces_within_its_reach() -> None:
    block = Boulder((0.0, 0.0, 0.0), (1.0, 1.2, 0.8), angular=7)
    rng = np.random.default_rng(0)
    sphere = rng.standard_normal((2000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    assert np.all(block.field(block.reach * sphere) > 0)
    assert block.field(np.zeros((1, 3)))[0] < 0
    # Flat faces: the field is linear between two points inside the same face's region.
    line = np.linspace(0.0, 3.0, 61)[:, None] * sphere[:1]
    second = np.diff(block.field(line), 2)
    assert np.mean(np.abs(second) < 1e-9) > 0.8  # kinks only where the nearest face changes
    other = Boulder((0.0, 0.0, 0.0), (1.0, 1.2, 0.8), angular=8)
    assert not np.allclose(block.field(sphere), other.field(sphere))
    smooth = Boulder((0.0, 0.0, 0.0), (1.0, 1.2, 0.8))
    assert np.allclose(smooth.field(np.array([[1.0, 0, 0], [0, 1.2, 0]])), 0.0)


def test_a_speleothem_is_a_cone_between_its_ends() -> None:
    stalactite = Speleothem(1.0, 2.0, bottom=-1.0, top=0.0, bottom_radius=0.0, top_radius=0.4)
    axis = np.array([[1.0, 2.0, z] for z in (-1.2, -0.9, -0.5, -0.1, 0.2)])
    inside = stalactite.field(axis) < 0
    assert inside.tolist() == [False, True, True, True, False]
    beside = np.array([[1.3, 2.0, -0.1], [1.3, 2.0, -0.5]])  # 0.3 m off its axis
    assert stalactite.field(beside)[0] < 0 < stalactite.field(beside)[1]  # 0.36 m, 0.2 m


# ------------------------------------------------------------------ in the families


def test_the_families_use_the_shapes_of_real_caves() -> None:
    s1, s2, s3, s4, s5 = (SCENARIOS[f"S{k}"].layout(0).spec for k in range(1, 6))
    assert s1.section.ceiling_channel.max() > 0 and s1.section.sediment.max() > 0
    assert s1.scallops > 0 and np.abs(s1.section.notch).max() > 0
    assert s2.section.canyon_width.max() > 0
    assert all(b.angular is not None for b in s3.boulders + s5.boulders)
    assert np.abs(s3.section.ledge).max() > 0
    assert s4.section.squareness.max() > 0 and s4.speleothems
    assert s5.breakdown and s5.speleothems
    crawl = SCENARIOS["crawl"].layout(0).spec
    assert crawl.section.sediment.min() > 0


@pytest.mark.parametrize("name", ["S3", "S5"])
def test_a_knob_leaves_the_shapes_it_does_not_govern_alone(name: str) -> None:
    """The shapes are drawn from generators of their own: more obstacles move no ledge,
    scallop or speleothem."""
    plain = SCENARIOS[name].layout(4).spec
    more = SCENARIOS[name].layout(4, Difficulty(obstacles=5)).spec
    assert len(more.boulders) != len(plain.boulders)
    assert np.array_equal(plain.section.ledge, more.section.ledge)
    assert plain.scallops == more.scallops and plain.speleothems == more.speleothems

"""No rings: relief along a passage must not repeat (issue 49), measured by
`cavenav.world.rings` on tubes whose relief is known, drawn here cell by cell."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from cavenav.world.mesh import CaveMesh, make_mesh
from cavenav.world.raycast import RayCaster
from cavenav.world.rings import RING_LIMIT, centred_axis, portal_axis, ring_spectra

LENGTH, RADIUS = 30.0, 2.5  # a tube along x, open at both ends
STEP, AROUND = 0.03, 180  # its vertices: every 3 cm along, every 2 degrees around
S = np.arange(0.0, LENGTH + 1e-9, STEP)
THETA = 2.0 * np.pi * np.arange(AROUND) / AROUND
ARC = RADIUS * 2.0 * np.pi / AROUND  # metres between vertices around
AXIS = np.array([[0.5, 0.0, 0.0], [LENGTH - 0.5, 0.0, 0.0]])


def tube(relief: np.ndarray) -> CaveMesh:
    """A tube of radius RADIUS plus ``relief`` (len(S), AROUND) metres, x along its axis."""
    r = RADIUS + relief
    s, theta = np.meshgrid(S, THETA, indexing="ij")
    vertices = np.stack([s, r * np.cos(theta), r * np.sin(theta)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(len(S) - 1), np.arange(AROUND), indexing="ij")
    a, b = i * AROUND + j, i * AROUND + (j + 1) % AROUND
    c, d = a + AROUND, b + AROUND
    faces = np.concatenate([np.stack(f, axis=-1).reshape(-1, 3) for f in ((a, b, d), (a, d, c))])
    return make_mesh(vertices, faces, "tube")


def rock(seed: int, rms: float = 0.05) -> np.ndarray:
    """Relief with no preferred scale: white noise smoothed at 5 cm to 0.8 m (isotropic on
    the wall), each scale weighted as rock's (amplitude growing with size)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((len(S), AROUND))
    for sigma in (0.05, 0.1, 0.2, 0.4, 0.8):
        noise = rng.standard_normal(out.shape)
        noise = ndimage.gaussian_filter(
            noise, (sigma / STEP, sigma / ARC), mode=("nearest", "wrap")
        )
        out += sigma**0.8 * noise / noise.std()
    return rms * out / out.std()


def lattice(seed: int, spacing: float = 0.8, rms: float = 0.05) -> np.ndarray:
    """Relief of lattice noise on a passage along a lattice axis: random heights on planes
    across the passage ``spacing`` apart, a cubic B-spline between them (as
    `cavenav.world.procedural` noise on a passage along x or y)."""
    rng = np.random.default_rng(seed)
    knots = np.arange(-3.0, LENGTH / spacing + 4.0)
    heights = rng.standard_normal((len(knots), AROUND))
    heights = ndimage.gaussian_filter1d(heights, 0.4 / ARC, axis=1, mode="wrap")
    t = np.abs(S[:, None] / spacing - knots[None, :])
    spline = np.where(t < 1, 2 / 3 - t**2 + t**3 / 2, np.where(t < 2, (2 - t) ** 3 / 6, 0.0))
    out = spline @ heights
    return rms * out / out.std()


def lathe(amplitude: float, wavelength: float) -> np.ndarray:
    """Grooves turned into the whole tube: the same sinusoid all the way round."""
    return np.repeat(amplitude * np.sin(2 * np.pi * S / wavelength)[:, None], AROUND, axis=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rock_with_no_preferred_scale_has_no_ring(seed: int) -> None:
    found = ring_spectra(RayCaster(tube(rock(seed))), AXIS)
    assert found.radius.peak_factor < RING_LIMIT
    assert found.crease.peak_factor < RING_LIMIT
    assert found.off_wall == 0.0 and found.angles == 64


def test_a_lathe_ring_of_a_centimetre_and_a_half_stands_far_above_the_limit() -> None:
    found = ring_spectra(RayCaster(tube(rock(0) + lathe(0.015, 1.0))), AXIS)
    assert found.radius.peak_factor > 2 * RING_LIMIT
    assert found.radius.peak_wavelength == pytest.approx(1.0, rel=0.03)
    assert found.radius.line_rms == pytest.approx(0.015 / np.sqrt(2), rel=0.2)
    # Crests and troughs both bend: the creases repeat at half the wavelength.
    assert found.crease.peak_factor > 2 * RING_LIMIT
    assert found.crease.peak_wavelength == pytest.approx(0.5, rel=0.03)


def test_lattice_noise_along_the_passage_rings_in_its_creases_not_its_heights() -> None:
    """Random heights on a lattice repeat nowhere in the radius, but the wall bends
    hardest on the lattice's planes: a ring every lattice spacing, which the eye sees."""
    found = ring_spectra(RayCaster(tube(lattice(0) + 0.1 * rock(1))), AXIS)
    assert found.crease.peak_factor > 2 * RING_LIMIT
    assert found.crease.peak_wavelength == pytest.approx(0.8, rel=0.03)


def test_ripples_on_the_floor_repeat_and_the_rock_around_them_is_told_apart() -> None:
    down = np.abs(THETA - 1.5 * np.pi) < np.radians(35)
    ripples = np.where(down[None, :], 0.02 * np.sin(2 * np.pi * S / 0.9)[:, None], 0.0)
    caster = RayCaster(tube(rock(1) + ripples))
    whole, rock_only = ring_spectra(caster, AXIS), ring_spectra(caster, AXIS, floor=False)
    assert whole.radius.peak_factor > RING_LIMIT
    assert whole.radius.peak_wavelength == pytest.approx(0.9, rel=0.05)
    assert rock_only.peak_factor < RING_LIMIT and rock_only.angles == 48


def test_objects_in_the_passage_are_left_out_not_counted_as_relief() -> None:
    relief = rock(2)
    block = (np.abs(S - 12.0) < 1.0)[:, None] & (np.abs(THETA - np.pi) < 0.6)[None, :]
    relief[block] -= 1.2  # a block 2 m long standing 1.2 m proud of one wall
    found = ring_spectra(RayCaster(tube(relief)), AXIS)
    assert 0.005 < found.off_wall < 0.05
    assert found.peak_factor < RING_LIMIT


def test_a_passage_shorter_than_one_window_is_refused() -> None:
    with pytest.raises(ValueError, match="under one"):
        ring_spectra(RayCaster(tube(rock(0))), np.array([[1.0, 0, 0], [9.0, 0, 0]]))


def test_a_guide_off_the_middle_is_brought_to_the_axis() -> None:
    caster = RayCaster(tube(rock(0)))
    guide = np.array([[2.0, 1.0, -0.8], [15.0, -0.9, 0.7], [28.0, 1.1, 0.6]])
    centred = centred_axis(caster, guide)
    assert np.abs(centred[:, 1:]).max() < 0.08


def test_a_mesh_without_a_centre_line_gets_one_from_portal_to_portal() -> None:
    mesh = tube(rock(0))
    axis = portal_axis(mesh)
    assert np.abs(axis[:, 1:]).max() < 0.08
    assert np.ptp(axis[:, 0]) > LENGTH - 2.5  # from 1.5 m inside one portal to the other

"""Photographed rock: the shipped photographs, credited and unchanged, read as the rock's
fine detail on every orientation of a wall, at the scale a pixel can carry."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from cavenav.sensors import kernels
from cavenav.sensors.lighting import PHOTOGRAPH_FILES, ROCK_PHOTOGRAPHS, rock_photographs

PHOTOS = rock_photographs().as_tuple()
TOWARD_CAMERA = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def factor_on_plane(axis: str, u: np.ndarray, v: np.ndarray, footprint: float) -> np.ndarray:
    """The factor on a flat wall facing the camera along ``axis`` at in-plane (u, v), m."""
    n = TOWARD_CAMERA[axis]
    out = np.empty(len(u))
    for k, (a, b) in enumerate(zip(u, v, strict=True)):
        hit = {"x": (0.0, a, b), "y": (a, 0.0, b), "z": (a, b, 0.0)}[axis]
        out[k] = kernels.photographed_rock(*PHOTOS, hit, n, n, footprint)
    return out


def test_the_shipped_photographs_are_the_credited_files_unchanged() -> None:
    sums = dict(
        reversed(line.split())
        for line in (ROCK_PHOTOGRAPHS / "SHA256SUMS").read_text().splitlines()
    )
    for name in PHOTOGRAPH_FILES:
        digest = hashlib.sha256((ROCK_PHOTOGRAPHS / name).read_bytes()).hexdigest()
        assert sums[name] == digest
    notice = (ROCK_PHOTOGRAPHS / "NOTICE.md").read_text()
    assert "Open Robotics / DARPA SubT (CC-BY-4.0), via LTU-RAI/SubTGraph" in notice


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_the_photographs_vary_the_rock_about_its_own_albedo_on_every_orientation(
    axis: str,
) -> None:
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-20, 20, (2, 4000))
    factor = factor_on_plane(axis, u, v, footprint=0.004)
    # Lit head-on the relief turns nothing away on average: the rock keeps its palette's
    # tone, and shows the photographs' contrast (raised, as wet rock shows it).
    assert factor.mean() == pytest.approx(1.0, abs=0.08)
    assert 0.3 < factor.std() < 1.0
    assert factor.min() >= 0.0


def test_walls_show_their_strata_level_and_floors_do_not() -> None:
    """Bedding runs horizontal on walls: the detail changes faster going up a wall than
    along it. A floor's photograph has no such direction."""
    step = 0.004
    along = np.arange(0.0, 2.0, step)

    def roughness(axis: str, vertical: bool) -> float:
        """The mean change from one 4 mm pixel to the next, over ten 2 m transects."""
        changes = []
        for offset in np.linspace(0.1, 1.9, 10):
            across = np.full_like(along, offset)
            u, v = (across, along) if vertical else (along, across)
            changes.append(np.abs(np.diff(factor_on_plane(axis, u, v, step))).mean())
        return float(np.mean(changes))

    for wall in ("x", "y"):
        assert roughness(wall, vertical=True) > 1.4 * roughness(wall, vertical=False)
    assert roughness("z", True) == pytest.approx(roughness("z", False), rel=0.2)


def test_rock_seen_from_afar_averages_its_detail_rather_than_aliasing_it() -> None:
    """A pixel 5 cm wide reads a mip level that has averaged the millimetres away: a row
    of such pixels varies far less from one to the next than a row of millimetre ones."""
    u = np.linspace(0.0, 3.0, 61)
    v = np.full_like(u, 0.41)
    near = factor_on_plane("x", u * 0.02, v, footprint=0.001)
    far = factor_on_plane("x", u, v, footprint=0.05)
    # Far: each sample 5 cm from the last, each a 5 cm average: neighbours agree more
    # than millimetre texels taken 5 cm apart would.
    sparse = factor_on_plane("x", u, v, footprint=0.001)
    assert np.std(np.diff(far)) < 0.6 * np.std(np.diff(sparse))
    assert np.isfinite(near).all()


def test_the_strata_run_on_from_a_wall_facing_x_to_one_facing_y() -> None:
    """Where a passage's wall turns from facing x to facing y, the photograph's projection
    changes plane; the beds stay at their heights, so the strata run on across the turn:
    the profile up the wall, averaged along it, is the same on both planes."""
    heights = np.arange(0.0, 1.0, 0.004)
    along = np.linspace(0.0, 2.0, 40, endpoint=False)

    def profile(axis: str) -> np.ndarray:
        u, v = np.meshgrid(along, heights)
        return factor_on_plane(axis, u.ravel(), v.ravel(), 0.004).reshape(u.shape).mean(axis=1)

    facing_x, facing_y = profile("x"), profile("y")
    assert np.corrcoef(facing_x, facing_y)[0, 1] > 0.9
    floor = profile("z")  # the plain photograph: no beds to continue
    assert abs(np.corrcoef(facing_x, floor)[0, 1]) < 0.5

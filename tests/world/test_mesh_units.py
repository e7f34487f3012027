"""A mesh's unit, read from the size of its passage, and set-up that scales to fine meshes.

Most mesh formats carry no unit: a cave drawn in centimetres and read as metres is flown
100 times too large without any error (every wall far away, every step safe). Loading a
scenario file therefore measures the passage at the start and warns, naming the likely
unit and the ``scale`` that fixes it.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cavenav.core.errors import CavenavWarning
from cavenav.sensors import lighting
from cavenav.sensors.optics import Optics
from cavenav.world.mesh import load_mesh, make_mesh
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import SCENARIOS, load_scenario
from cavenav.world.units import check_units, likely_scale

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
# One of the Open Robotics tiles (also in /work/shared/data/meshes): a 5 m tube along y,
# 20 m long, floor at z = -0.5 and ceiling at 4.5.
STRAIGHT = EXAMPLES / "meshes" / "cave_straight_20m.dae"


def cave_file(tmp_path: Path, unit: float, scale: float | None = None, start_in_metres=False):
    """A scenario file for the straight tile written out in ``unit`` metres per number,
    as a tool working in that unit exports it (PLY, which declares no unit)."""
    tile = load_mesh(STRAIGHT)
    trimesh.Trimesh(tile.vertices / unit, tile.faces, process=False).export(tmp_path / "cave.ply")
    to_file = 1.0 if start_in_metres else 1.0 / unit  # the numbers the user read off the mesh
    x, y, z = (v * to_file for v in (0.0, 8.5, 2.0))
    path = tmp_path / "cave.toml"
    path.write_text(
        'mesh = "cave.ply"\n'
        + (f"scale = {scale}\n" if scale is not None else "")
        + f"[start]\nposition = [{x}, {y}, {z}]\n"
        + f"[[exit]]\npoint = [0.0, {-10 * to_file}, {z}]\nnormal = [0.0, -1.0, 0.0]\n"
        + f"radius = {3.5 * to_file}\n"
    )
    return path


def unit_warnings(load) -> list[str]:  # noqa: ANN001 - any callable
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load()
    return [str(w.message) for w in caught if issubclass(w.category, CavenavWarning)]


@pytest.mark.parametrize("start_in_metres", [False, True])
def test_a_cave_in_centimetres_warns_and_names_the_scale(tmp_path: Path, start_in_metres) -> None:
    path = cave_file(tmp_path, unit=0.01, start_in_metres=start_in_metres)
    with pytest.warns(CavenavWarning) as caught:
        cave = load_scenario(str(path))
    (message,) = [str(w.message) for w in caught]
    assert "centimetres" in message and "`scale = 0.01`" in message
    assert "cave.ply" in message
    assert np.ptp(cave.mesh.vertices[:, 1]) == pytest.approx(2000.0, rel=0.01)  # as read


def test_the_same_cave_in_metres_loads_without_a_warning(tmp_path: Path) -> None:
    path = cave_file(tmp_path, unit=1.0)
    assert unit_warnings(lambda: load_scenario(str(path))) == []


def test_a_cave_in_millimetres_is_told_apart_from_centimetres(tmp_path: Path) -> None:
    (message,) = unit_warnings(lambda: load_scenario(str(cave_file(tmp_path, unit=0.001))))
    assert "millimetres" in message and "`scale = 0.001`" in message


def test_the_scale_that_fixes_it_is_given_for_the_file_not_relative_to_a_wrong_one(
    tmp_path: Path,
) -> None:
    # A mesh in metres, given the scale meant for a centimetre file: 100 times too small.
    path = cave_file(tmp_path, unit=1.0, scale=0.01)
    (message,) = unit_warnings(lambda: load_scenario(str(path)))
    assert "metres" in message and "`scale = 1`" in message


def test_the_applied_scale_silences_the_warning(tmp_path: Path) -> None:
    path = cave_file(tmp_path, unit=0.01, scale=0.01)
    assert unit_warnings(lambda: load_scenario(str(path))) == []


@pytest.mark.slow
@pytest.mark.parametrize("example", sorted(p.name for p in EXAMPLES.glob("*.toml")))
def test_no_shipped_example_warns(example: str) -> None:
    assert unit_warnings(lambda: load_scenario(str(EXAMPLES / example))) == []


@pytest.mark.slow
@pytest.mark.parametrize("family", sorted(SCENARIOS))
def test_no_cave_family_would_warn(family: str) -> None:
    cave = load_scenario(family, seed=0)
    assert unit_warnings(lambda: check_units(cave.mesh, cave.start.position)) == []


@pytest.mark.parametrize(
    ("size_m", "scale", "expected"),
    [
        (570.0, 1.0, (0.01, "centimetres")),  # a 5 m passage drawn in centimetres
        (5700.0, 1.0, (0.001, "millimetres")),
        (224.0, 1.0, (0.0254, "inches")),
        (45.0, 1.0, (0.3048, "feet")),  # a 12 m gallery drawn in feet
        (0.057, 0.01, (1.0, "metres")),  # a file in metres read as centimetres
        (6.0, 1.0, None),  # plausible: no advice
        (25.0, 1.0, None),
        (0.5, 1.0, None),
    ],
)
def test_the_likely_unit_brings_the_passage_to_an_ordinary_size(size_m, scale, expected) -> None:
    assert likely_scale(size_m, scale) == expected


# ------------------------------------------------------------------ fine meshes


def box_room(subdivisions: int = 0):  # noqa: ANN201 - CaveMesh
    """A 4 x 20 x 4 m closed room, each face split into 4**subdivisions."""
    box = trimesh.creation.box(extents=(4.0, 20.0, 4.0))
    for _ in range(subdivisions):
        box = box.subdivide()
    return make_mesh(np.asarray(box.vertices), np.asarray(box.faces), "box-room")


def test_vertex_averages_are_the_scatter_add_they_replace() -> None:
    mesh = load_mesh(STRAIGHT)
    per_face = np.random.default_rng(0).random((mesh.triangle_count, 2, 6)).astype(np.float32)
    _, area = lighting.face_normals(mesh)
    total = np.zeros((len(mesh.vertices), 2, 6))
    weight = np.zeros(len(mesh.vertices))
    for corner in range(3):
        np.add.at(total, mesh.faces[:, corner], per_face * area[:, None, None])
        np.add.at(weight, mesh.faces[:, corner], area)
    expected = (total / np.maximum(weight, 1e-12)[:, None, None]).astype(np.float32)
    assert np.array_equal(lighting.at_vertices(mesh, per_face), expected)  # bit for bit


def test_patches_cover_every_triangle_once_and_join_only_triangles_facing_alike() -> None:
    room = box_room(3)  # 768 triangles
    # A thin wall across the room, both faces: 1 cm apart, normals opposite.
    sheet = trimesh.creation.box(extents=(4.0, 0.01, 4.0)).subdivide().subdivide()
    mesh = make_mesh(
        np.vstack([room.vertices, sheet.vertices]),
        np.vstack([room.faces, sheet.faces + len(room.vertices)]),
    )
    normal, area = lighting.face_normals(mesh)
    centre = mesh.vertices[mesh.faces].mean(axis=1)
    assert lighting.surface_patches(centre, normal, area, limit=len(centre)) is None
    patch, representative = lighting.surface_patches(centre, normal, area, limit=100)
    assert len(representative) <= 115 and patch.shape == (len(centre),)
    assert (patch[representative] == np.arange(len(representative))).all()
    # Within 60 degrees of the patch's representative: no patch spans both faces of the
    # wall, or two walls of a corner.
    assert ((normal * normal[representative][patch]).sum(axis=1) >= 0.5 - 1e-9).all()


def test_patches_spend_the_rays_better_than_fewer_rays_per_triangle(monkeypatch) -> None:
    tile = load_mesh(STRAIGHT)  # 20,016 triangles, open at both portals: daylight comes in
    caster = RayCaster(tile)
    reference = lighting._surface_table(caster, Optics(), 0, 128)
    exact = lighting._surface_table(caster, Optics(), 0, 32)
    thin = lighting._surface_table(caster, Optics(), 0, 6)  # 32 rays per 5 triangles, too
    monkeypatch.setattr(lighting, "SURFACE_PATCHES", 4000)  # 5 triangles a patch
    grouped = lighting._surface_table(caster, Optics(), 0, 32)

    def error(table: np.ndarray) -> np.ndarray:
        """Per side and column, the mean deviation from the reference of what the renderer
        reads (the table smoothed over the vertices), relative to its mean."""
        smooth, truth = lighting.at_vertices(tile, table), lighting.at_vertices(tile, reference)
        return np.abs(smooth - truth).mean(axis=0) / np.abs(truth).mean(axis=0)

    assert reference[..., lighting.DAYLIGHT].mean() > 0.01  # there is daylight to get right
    # No bias: as much light over the whole cave, per side and colour, within 2%.
    bias = grouped.mean(axis=0) / exact.mean(axis=0) - 1.0
    assert np.abs(bias).max() < 0.02, bias
    # The daylight, which the rays find: less noisy than from the same number of rays
    # spread thinly over every triangle. The albedo, each triangle's own: within 0.2%.
    daylight = error(grouped)[..., lighting.DAYLIGHT]
    assert (daylight <= error(thin)[..., lighting.DAYLIGHT]).all(), daylight
    assert error(grouped)[..., lighting.ALBEDO].max() < 0.002

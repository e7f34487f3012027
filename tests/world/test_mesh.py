"""Loading user meshes: formats, units, up axis, and one-line errors for broken files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from cavenav.core.errors import MeshError
from cavenav.world.mesh import load_mesh, make_mesh

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
STRAIGHT = EXAMPLES / "meshes" / "cave_straight_20m.dae"


def test_shipped_collada_tile_loads_in_metres_z_up() -> None:
    mesh = load_mesh(STRAIGHT)
    extent = np.ptp(mesh.vertices, axis=0)
    assert extent == pytest.approx([5.3, 20.0, 5.1], abs=0.1)
    assert mesh.triangle_count == 20016


def test_collada_centimetre_unit_is_honoured(tmp_path: Path) -> None:
    text = STRAIGHT.read_text().replace('meter="1"', 'meter="0.01"', 1)
    assert 'meter="0.01"' in text
    path = tmp_path / "cm.dae"
    path.write_text(text)
    extent = np.ptp(load_mesh(path).vertices, axis=0)
    assert extent[1] == pytest.approx(0.2, abs=0.01)


def test_explicit_scale_overrides_the_file_unit() -> None:
    assert np.ptp(load_mesh(STRAIGHT, scale=2.0).vertices[:, 1]) == pytest.approx(40.0, abs=0.1)


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".glb"])
def test_common_formats_load(tmp_path: Path, suffix: str) -> None:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    path = tmp_path / f"box{suffix}"
    box.export(path)
    mesh = load_mesh(path, up_axis="z")
    assert np.ptp(mesh.vertices, axis=0) == pytest.approx([1.0, 2.0, 3.0])


def test_gltf_is_y_up_by_default(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(1.0, 3.0, 2.0))  # tall along y, as glTF means "up"
    path = tmp_path / "box.glb"
    box.export(path)
    assert np.ptp(load_mesh(path).vertices, axis=0) == pytest.approx([1.0, 2.0, 3.0])


def test_missing_file_names_the_path(tmp_path: Path) -> None:
    with pytest.raises(MeshError, match="not found"):
        load_mesh(tmp_path / "nope.obj")


def test_a_file_that_is_not_a_mesh_is_a_one_line_error(tmp_path: Path) -> None:
    path = tmp_path / "notes.ply"
    path.write_text("this is not a mesh\n")
    with pytest.raises(MeshError, match="notes.ply: cannot read as a .ply mesh") as info:
        load_mesh(path)
    assert "\n" not in str(info.value)


def test_unsupported_suffix(tmp_path: Path) -> None:
    path = tmp_path / "cave.xyz"
    path.write_text("1 2 3\n")
    with pytest.raises(MeshError, match="unsupported"):
        load_mesh(path)


def test_empty_mesh(tmp_path: Path) -> None:
    path = tmp_path / "empty.obj"
    path.write_text("# nothing here\n")
    with pytest.raises(MeshError, match="empty.obj: mesh has no vertices"):
        load_mesh(path)


def test_nan_vertices_are_counted() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, np.nan]], float)
    with pytest.raises(MeshError, match="1 vertices have NaN"):
        make_mesh(vertices, np.array([[0, 1, 2]]))


def test_obj_with_nan_vertices(tmp_path: Path) -> None:
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 nan 1\nf 1 2 3\n")
    with pytest.raises(MeshError, match="NaN"):
        load_mesh(path)


# ------------------------------------------------------------------ footprint


def test_a_vertex_no_triangle_uses_leaves_the_footprint_raster_as_it_was() -> None:
    # Meshes from files often carry stray vertices: one far away must neither stretch the
    # map's grid (shrinking the cave to a dot) nor mark a cell of its own.
    from cavenav.episode.plots import footprint_raster

    disc = trimesh.creation.cylinder(radius=2.0, height=0.5, sections=32)
    mesh = make_mesh(disc.vertices, disc.faces, "disc")
    stray = make_mesh(np.vstack([disc.vertices, [[1e9, -1e9, 0.0]]]), disc.faces, "stray")
    covered, extent = footprint_raster(mesh)
    stray_covered, stray_extent = footprint_raster(stray)
    assert stray_extent == extent
    np.testing.assert_array_equal(stray_covered, covered)

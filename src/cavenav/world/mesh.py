"""Cave meshes: load any common format, honour units and up axis, validate.

The meshes users bring are rarely clean: COLLADA files declare centimetres that trimesh
does not apply, glTF is y-up by definition, artist tiles are open at their portals. This
module turns any of them into a `CaveMesh` in metres with z up, or raises one `MeshError`
line that names the problem.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cavenav.errors import MeshError

__all__ = ["CaveMesh", "MESH_SUFFIXES", "load_mesh"]

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".dae", ".off")

# Rotations that bring a file's up axis to +z (right-handed, so no mirroring).
_TO_Z_UP = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),  # (x, y, z) -> (x, -z, y)
    "x": np.array([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]]),  # (x, y, z) -> (-z, y, x)
}


@dataclass(frozen=True, eq=False)
class CaveMesh:
    """A triangle mesh of cave walls in metres, z up.

    Attributes:
        vertices: (n, 3) float64 positions.
        faces: (m, 3) int64 vertex indices.
        name: where it came from, for messages and plots.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = "mesh"

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned minimum and maximum corners."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def triangle_count(self) -> int:
        return int(len(self.faces))


def _dae_unit_and_up(path: Path) -> tuple[float, str]:
    """Read `<unit meter>` and `<up_axis>` from a COLLADA file, which trimesh ignores."""
    from lxml import etree

    try:
        root = etree.parse(str(path)).getroot()
    except etree.XMLSyntaxError as exc:
        raise MeshError(f"{path}: not a valid COLLADA (XML) file: {exc}") from None
    ns = {"c": root.nsmap.get(None, "")} if root.nsmap.get(None) else {}
    unit = root.find(".//c:asset/c:unit" if ns else ".//asset/unit", ns)
    up = root.find(".//c:asset/c:up_axis" if ns else ".//asset/up_axis", ns)
    scale = float(unit.get("meter", "1")) if unit is not None else 1.0
    up_axis = (up.text or "Z_UP").strip()[0].lower() if up is not None else "y"
    return scale, up_axis


def load_mesh(
    path: str | Path,
    scale: float | None = None,
    up_axis: str | None = None,
) -> CaveMesh:
    """Load a cave mesh file as metres with z up.

    Args:
        path: OBJ, PLY, STL, glTF/GLB, COLLADA or OFF file.
        scale: metres per file unit; by default the file's declared unit (COLLADA) or 1.
        up_axis: "x", "y" or "z"; by default the file's declared axis (COLLADA), "y" for
            glTF (y-up by specification) and "z" otherwise.

    Raises:
        MeshError: missing file, unknown format, not a mesh, empty, or non-finite vertices.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(
            f"{path}: unsupported mesh format '{suffix}'; use one of {', '.join(MESH_SUFFIXES)}"
        )
    file_scale, file_up = 1.0, "y" if suffix in (".glb", ".gltf") else "z"
    if suffix == ".dae":
        file_scale, file_up = _dae_unit_and_up(path)
    scale = file_scale if scale is None else float(scale)
    up = (up_axis or file_up).lower()
    if up not in _TO_Z_UP:
        raise MeshError(f"{path}: up axis must be 'x', 'y' or 'z', got '{up_axis}'")
    if not (math.isfinite(scale) and scale > 0):
        raise MeshError(f"{path}: scale must be a positive number, got {scale}")

    import trimesh

    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"{path}: cannot read as a {suffix} mesh ({exc})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path}: holds no triangle mesh")
    return make_mesh(np.asarray(loaded.vertices) @ _TO_Z_UP[up].T * scale, loaded.faces, path.name)


def make_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh") -> CaveMesh:
    """Validate raw arrays and wrap them as a CaveMesh.

    Raises:
        MeshError: empty mesh, wrong shapes, non-finite vertices, out-of-range indices.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise MeshError(f"{name}: mesh has no vertices")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise MeshError(f"{name}: mesh has no triangles")
    bad = int((~np.isfinite(vertices)).any(axis=1).sum())
    if bad:
        raise MeshError(f"{name}: {bad} vertices have NaN or infinite coordinates")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{name}: triangle indices point outside the {len(vertices)} vertices")
    extent = np.ptp(vertices, axis=0)
    if np.count_nonzero(extent > 1e-6) < 2:
        raise MeshError(f"{name}: mesh is degenerate (extent {extent.round(3).tolist()} m)")
    return CaveMesh(vertices=vertices, faces=faces, name=name)

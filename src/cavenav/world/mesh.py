"""Cave meshes: load any common format, honour units and up axis, validate.

The meshes users bring are rarely clean: COLLADA files declare centimetres that trimesh
does not apply, glTF is y-up by definition, artist tiles are open at their portals. This
module turns any of them into a `CaveMesh` in metres with z up, or raises one `MeshError`
line that names the problem. Most formats carry no unit at all: whether the passage is a
plausible size is asked by `cavenav.world.units`, which casts rays. Tiles drawn to be
chained become one cave with `place_mesh` and `join_meshes`; `open_portals` finds where
a mesh is open.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cavenav.core.errors import MeshError

__all__ = [
    "MESH_SUFFIXES",
    "SEAM_WELD_M",
    "CaveMesh",
    "Portal",
    "join_meshes",
    "load_mesh",
    "make_mesh",
    "open_portals",
    "place_mesh",
    "sphere_directions",
]

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
        scale: metres per unit of the file it was read from (1 for built meshes), so a
            message about its size can say which ``scale`` would fix it.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = "mesh"
    scale: float = 1.0

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
    vertices = np.asarray(loaded.vertices) @ _TO_Z_UP[up].T * scale
    return make_mesh(vertices, loaded.faces, path.name, scale=scale)


def make_mesh(
    vertices: np.ndarray, faces: np.ndarray, name: str = "mesh", *, scale: float = 1.0
) -> CaveMesh:
    """Validate raw arrays and wrap them as a CaveMesh.

    Args:
        scale: metres per file unit that ``vertices`` were scaled by (see `CaveMesh`).

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
    return CaveMesh(vertices=vertices, faces=faces, name=name, scale=float(scale))


def sphere_directions(n: int) -> np.ndarray:
    """(n, 3) roughly uniform unit vectors (a Fibonacci sphere), slightly irrational so
    that no ray runs exactly along a mesh edge."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5**0.5) * k + 0.1234
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


# ------------------------------------------------------------------ open portals and chains

# Vertices closer than this are one vertex when edges are matched: files repeat a vertex
# once per face or material (exactly), and chained tiles share their seams (see
# `join_meshes`). A micrometre is far below any feature of a cave and far above rounding.
_SAME_VERTEX_M = 1e-6

# How near rim vertices of two pieces must be for `join_meshes` to weld them. The OSRF
# tiles' portal rims agree to 2.5 cm (the same 80-vertex ring, 2.1-2.6 m from its centre,
# drawn anew for each tile) with 18 cm between rim vertices, so 5 cm closes every seam
# and never gathers two different rim vertices of one ring.
SEAM_WELD_M = 0.05


@dataclass(frozen=True, eq=False)
class Portal:
    """An opening of an open mesh: one closed loop of boundary edges.

    Attributes:
        centre: (3,) the loop's centre, the mean of its edges weighted by their length.
        normal: (3,) unit normal of the loop's best-fit plane, pointing out of the
            passage (away from the walls that end at the loop).
        radius: the farthest loop vertex from ``centre`` across that plane, metres: a disc
            of this radius covers the whole opening.
        loop: (k, 3) the loop's vertices, in no particular order.
    """

    centre: np.ndarray
    normal: np.ndarray
    radius: float
    loop: np.ndarray


def _merged_faces(mesh: CaveMesh) -> np.ndarray:
    """(m, 3) faces with coincident vertices (within `_SAME_VERTEX_M`) given one index."""
    key = np.round(mesh.vertices / _SAME_VERTEX_M).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first[inverse.ravel()][mesh.faces]


def _boundary_edges(faces: np.ndarray) -> np.ndarray:
    """(e, 2) vertex indices of the edges that belong to one face only."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]  # degenerate faces
    unique, count = np.unique(edges, axis=0, return_counts=True)
    return unique[count == 1]


def open_portals(mesh: CaveMesh) -> list[Portal]:
    """Every opening of ``mesh``: each connected loop of boundary edges, largest first.

    A tube open at both ends has two; a closed (watertight) mesh none; a crack in an
    artist's mesh is listed too, as a small one. The OSRF tiles' portals are rings 2.1 to
    2.6 m from their centre, 2 m above the tile's origin in the planes x = +-10 m or
    y = +-10 m: the middles of the sides of a 20 m square, so tiles on a 20 m grid chain.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = _merged_faces(mesh)
    edges = _boundary_edges(faces)
    if len(edges) == 0:
        return []
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    portals: list[Portal] = []
    for component in np.unique(label[edges[:, 0]]):
        loop_edges = edges[label[edges[:, 0]] == component]
        loop = mesh.vertices[np.unique(loop_edges)]
        a, b = mesh.vertices[loop_edges[:, 0]], mesh.vertices[loop_edges[:, 1]]
        length = np.linalg.norm(b - a, axis=1)
        centre = (0.5 * (a + b) * length[:, None]).sum(axis=0) / max(length.sum(), 1e-12)
        normal = np.linalg.svd(loop - centre)[2][-1]  # least-spread direction: the plane's
        # The walls ending at the loop lie behind it: point the normal away from them.
        touching = np.isin(faces, np.unique(loop_edges)).any(axis=1)
        behind = mesh.vertices[faces[touching]].mean(axis=(0, 1)) - centre
        normal = -normal if behind @ normal > 0 else normal
        across = (loop - centre) - np.outer((loop - centre) @ normal, normal)
        radius = float(np.linalg.norm(across, axis=1).max())
        portals.append(Portal(centre=centre, normal=normal, radius=radius, loop=loop))
    return sorted(portals, key=lambda p: -p.radius)


def place_mesh(
    mesh: CaveMesh, offset: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw_deg: float = 0.0
) -> CaveMesh:
    """``mesh`` turned by ``yaw_deg`` about the vertical through its origin, then moved by
    ``offset`` (metres).

    Positive yaw turns counter-clockwise seen from above, the sense in which a positive
    `Pose` yaw turns the vehicle left: turned by 90 degrees, a tile's +y portal faces -x.
    """
    a = math.radians(yaw_deg)
    c, s = math.cos(a), math.sin(a)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    vertices = mesh.vertices @ turn.T + np.asarray(offset, np.float64)
    return CaveMesh(vertices=vertices, faces=mesh.faces, name=mesh.name, scale=mesh.scale)


def join_meshes(meshes: list[CaveMesh], weld_m: float = SEAM_WELD_M) -> CaveMesh:
    """One mesh of several placed pieces (see `place_mesh`), their seams welded.

    Tiles drawn to be chained meet portal to portal, but each draws its own rim, and the
    rims of two tiles disagree by up to a few centimetres: a hairline ring through which a
    camera ray could see out. Rim vertices of different pieces closer than ``weld_m`` are
    gathered into one point (the earliest piece's), with any rim vertex of theirs as close
    (the OSRF rims repeat a vertex 2 mm apart at each diagonal), which closes the seam:
    the joined mesh has open portals only where no piece meets another. Nothing else
    moves, not even near-duplicates on a rim that meets nothing.

    The name is the pieces' names joined by '+'; the scale is the first piece's.

    Raises:
        MeshError: no pieces.
    """
    if not meshes:
        raise MeshError("no meshes to join")
    if len(meshes) == 1:
        return meshes[0]
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    # Coincident copies of a vertex share one index, so that moving it moves them all.
    merged = [_merged_faces(m) + k for m, k in zip(meshes, offsets, strict=True)]
    faces = np.concatenate(merged)
    vertices = np.concatenate([m.vertices for m in meshes])
    rim = np.concatenate([np.unique(_boundary_edges(f)) for f in merged])  # piece by piece
    piece = np.searchsorted(offsets, rim, side="right") - 1
    pairs = cKDTree(vertices[rim]).query_pairs(weld_m, output_type="ndarray")
    if weld_m > 0 and len(pairs):
        n = len(rim)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, cluster = connected_components(graph, directed=False)
        _, first = np.unique(cluster, return_index=True)  # each cluster's earliest member
        low = np.full(len(first), len(meshes))
        high = np.full(len(first), -1)
        np.minimum.at(low, cluster, piece)
        np.maximum.at(high, cluster, piece)
        seam = high[cluster] > low[cluster]  # clusters that join two pieces
        vertices[rim[seam]] = vertices[rim[first[cluster[seam]]]]
    name = "+".join(m.name for m in meshes)
    return make_mesh(vertices, faces, name, scale=meshes[0].scale)

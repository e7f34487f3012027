"""Procedural caves: a signed-distance field of a swept tube, meshed by marching cubes.

A passage is a centre-line with a horizontal half-width and a vertical half-height at
every sample. The field is negative in water and positive in rock:

    phi(p) = min over nearby samples i of  |o| - |o| / r(o),
             o = p - c_i,   r(o) = sqrt((o.n_i / a_i)^2 + (o.u_i / b_i)^2 + (o.t_i / a_i)^2)

(the radial distance from the sample to its elliptical section), plus fractal noise that
roughens the walls, minus boulders (ellipsoids of rock). Marching cubes at the zero level
gives watertight walls with obstacles merged for free. The grid is cut just past the exit,
so the passage runs through the grid's boundary and the surface stays open there: rays
leave the cave through that portal as they would through a real exit.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from cavenav.files import write_then_rename
from cavenav.world.mesh import CaveMesh, make_mesh

__all__ = ["GENERATOR_VERSION", "Boulder", "PassageSpec", "build_cave", "cache_dir"]

# Bump whenever the generator's output changes, so cached meshes are rebuilt.
GENERATOR_VERSION = 1


@dataclass(frozen=True)
class Boulder:
    """An ellipsoid of rock: centre (3,) and semi-axes (3,) in metres."""

    centre: tuple[float, float, float]
    radii: tuple[float, float, float]


@dataclass(frozen=True, eq=False)
class PassageSpec:
    """Everything that defines one generated cave.

    Attributes:
        centreline: (n, 3) polyline from a point behind the start to a point past the exit.
        half_width: (n,) horizontal half-size of the section at each point, metres.
        half_height: (n,) vertical half-size of the section at each point, metres.
        boulders: ellipsoids of rock carved out of the passage.
        exit_index: index of the centre-line point where the exit plane lies; the grid is
            cut 1.5 m past it along the exit direction, which must be an axis.
        roughness: amplitude of the wall noise in metres (standard deviation; 0.3 looks like rock).
        seed: seeds the wall noise.
        voxel: grid spacing in metres; 0.2 resolves rock detail and stays fast.
    """

    centreline: np.ndarray
    half_width: np.ndarray
    half_height: np.ndarray
    boulders: tuple[Boulder, ...] = field(default_factory=tuple)
    exit_index: int = -1
    roughness: float = 0.3
    seed: int = 0
    voxel: float = 0.2

    def digest(self) -> str:
        """A short hash of every input, for the mesh cache."""
        h = hashlib.sha256()
        for arr in (self.centreline, self.half_width, self.half_height):
            h.update(np.ascontiguousarray(arr, np.float64).tobytes())
        h.update(
            repr(
                (
                    self.boulders,
                    self.exit_index,
                    self.roughness,
                    self.seed,
                    self.voxel,
                    GENERATOR_VERSION,
                )
            ).encode()
        )
        return h.hexdigest()[:16]


def resample(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Resample a polyline at even arc length.

    Returns:
        ((k, 3) points, (k,) arc length of each); also used to interpolate profiles.
    """
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s_new = np.arange(0.0, s[-1] + 1e-9, spacing)
    return np.stack([np.interp(s_new, s, points[:, k]) for k in range(3)], axis=1), s_new


def _frames(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit tangent, horizontal normal (left) and section 'up' at each centre-line point."""
    t = np.gradient(points, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.cross(np.array([0.0, 0.0, 1.0]), t)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    u = np.cross(t, n)
    return t, n, u


def _fractal_noise(shape: tuple[int, ...], voxel: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise of unit standard deviation.

    Octaves of wavelength 4, 1.6 and 0.8 m weighted 1, 0.5 and 0.25: bulges, ledges, knobs.
    """
    out = np.zeros(shape, np.float32)
    for wavelength, weight in ((4.0, 1.0), (1.6, 0.5), (0.8, 0.25)):
        cells = max(wavelength / voxel, 1.0)
        coarse_shape = tuple(int(np.ceil(s / cells)) + 3 for s in shape)
        coarse = rng.standard_normal(coarse_shape).astype(np.float32)
        fine = ndimage.zoom(coarse, cells, order=3, prefilter=False)
        out += weight * fine[tuple(slice(0, s) for s in shape)]
    return out / out.std()  # unit standard deviation, whatever the grid size


def build_cave(spec: PassageSpec, name: str = "cave") -> CaveMesh:
    """Generate the cave mesh for ``spec`` (cached on disk, see `cache_dir`)."""
    cache = cache_dir() / f"{name}-{spec.digest()}.npz"
    if cache.is_file():
        with np.load(cache) as data:
            return make_mesh(data["vertices"], data["faces"], name)
    mesh = _generate(spec, name)
    cache.parent.mkdir(parents=True, exist_ok=True)

    def save(tmp: Path) -> None:
        with open(tmp, "wb") as out:  # np.savez would add ".npz" to a path
            np.savez_compressed(
                out, vertices=mesh.vertices.astype(np.float32), faces=mesh.faces.astype(np.int32)
            )

    write_then_rename(cache, save)
    with np.load(cache) as data:  # the cached float32 copy, so cold and warm runs agree
        return make_mesh(data["vertices"], data["faces"], name)


def cache_dir() -> Path:
    """Mesh cache: ``$CAVENAV_CACHE`` or ``$XDG_CACHE_HOME/cavenav`` or ``~/.cache/cavenav``."""
    if os.environ.get("CAVENAV_CACHE"):
        return Path(os.environ["CAVENAV_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "cavenav"


def _generate(spec: PassageSpec, name: str) -> CaveMesh:
    from skimage.measure import marching_cubes

    voxel = spec.voxel
    pts = np.asarray(spec.centreline, np.float64)
    half_w = np.asarray(spec.half_width, np.float64)
    half_h = np.asarray(spec.half_height, np.float64)
    tangent, normal, up = _frames(pts)
    reach = float(max(half_w.max(), half_h.max())) + 1.0 + spec.roughness

    lo = pts.min(axis=0) - reach
    hi = pts.max(axis=0) + reach
    # Cut the grid 1.5 m past the exit along its (axis-aligned) direction: open portal.
    exit_dir = tangent[spec.exit_index]
    axis = int(np.argmax(np.abs(exit_dir)))
    cut = pts[spec.exit_index, axis] + 1.5 * np.sign(exit_dir[axis])
    if exit_dir[axis] > 0:
        hi[axis] = cut
    else:
        lo[axis] = cut
    shape = tuple(int(np.ceil((hi[k] - lo[k]) / voxel)) + 1 for k in range(3))
    axes = [lo[k] + voxel * np.arange(shape[k]) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    phi = np.full(len(grid), reach, np.float32)
    tree = cKDTree(pts)
    dist, idx = tree.query(grid, k=4, distance_upper_bound=reach)
    for j in range(idx.shape[1]):
        near = np.isfinite(dist[:, j])
        i = idx[near, j]
        o = grid[near] - pts[i]
        r = np.sqrt(
            (np.einsum("ij,ij->i", o, normal[i]) / half_w[i]) ** 2
            + (np.einsum("ij,ij->i", o, up[i]) / half_h[i]) ** 2
            + (np.einsum("ij,ij->i", o, tangent[i]) / half_w[i]) ** 2
        )
        length = np.linalg.norm(o, axis=1)
        value = (length - length / np.maximum(r, 1e-6)).astype(np.float32)
        phi[near] = np.minimum(phi[near], value)
    phi = phi.reshape(shape)

    rng = np.random.default_rng(spec.seed)
    phi += spec.roughness * _fractal_noise(shape, voxel, rng)

    for boulder in spec.boulders:
        c, r = np.asarray(boulder.centre), np.asarray(boulder.radii)
        b_lo = np.maximum(((c - r - 1.0 - lo) / voxel).astype(int), 0)
        b_hi = np.minimum(((c + r + 1.0 - lo) / voxel).astype(int) + 1, shape)
        sl = tuple(slice(b_lo[k], b_hi[k]) for k in range(3))
        sub = np.stack(np.meshgrid(*[axes[k][sl[k]] for k in range(3)], indexing="ij"), -1)
        rel = (sub - c) / r
        rb = np.linalg.norm(rel, axis=-1)
        inside = (rb - 1.0) * float(r.min())  # negative inside the boulder
        phi[sl] = np.maximum(phi[sl], -inside)

    verts, faces, _, _ = marching_cubes(phi, level=0.0, spacing=(voxel,) * 3)
    verts = verts + lo
    return make_mesh(verts, _largest_components(faces, len(verts)), name)


def _largest_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Drop disconnected specks of under 100 triangles that the wall noise can leave.

    Free-standing boulders are far larger, so they stay.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), (n_vertices,) * 2)
    _, labels = connected_components(graph, directed=False)
    face_label = labels[faces[:, 0]]
    counts = np.bincount(face_label)
    keep = counts[face_label] >= 100
    return faces[keep]

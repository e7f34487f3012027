"""Procedural caves: a signed-distance field of a swept tube, meshed by marching cubes.

A passage is a centre-line with a horizontal half-width and a vertical half-height at
every sample. The field is negative in water and positive in rock:

    phi(p) = min over nearby samples i of  |o| - |o| / r(o),
             o = p - c_i,   r(o) = sqrt((o.n_i / a_i)^2 + (o.u_i / b_i)^2 + (o.t_i / a_i)^2)

(the radial distance from the sample to its elliptical section). The samples are taken
every `MESH_SAMPLE_M` along the centre line, whatever spacing the layout drew it at (its
profiles and sections interpolated): where two samples' ellipsoids meet they leave a
seam, a ring of rock around the passage d^2 / 8a high that creases the wall by d / a
radians, for samples d apart. At the layouts' 0.25 m that was a ring every 0.25 m,
2.4 mm high and creased by 5 degrees; at 0.1 m it is 0.4 mm and 2 degrees, finer than
the voxels carry. The main passage's sections take the shapes of real caves where a
`Section` says so (flat roofs, keyholes, ceiling half-tubes, notches, ledges:
`cavenav.world.morphology`); then fractal noise roughens the walls, scallops are cut
into them, silt is laid over the floor, and boulders, breakdown and speleothems are
made rock. Side branches are tubes of their
own and the field is the least of all tubes', so junctions merge by themselves and every
tube ends in a rounded, closed end. Marching cubes at the zero level gives watertight walls
with obstacles merged for free. The faces past a plane 1.5 m beyond the exit are left
out, so the surface stays open there: rays leave the cave through that portal as they
would through a real exit.

Nothing repeats along a passage (issue 49; `cavenav.world.rings` measures it). The voxel
grid is turned about z by `GRID_YAW`, so that no passage laid along x or y, as most
families' are, runs along it: along the grid, marching cubes builds the wall of slabs one
voxel thick, each a ring of facets creased where it meets the next, and the lattices
that the wall noise and the scallops are drawn on, which lie in the grid's frame, put
their planes across the passage, a ring of creases every lattice spacing.

Memory stays bounded for long caves: the tubes are evaluated block by block, only in the
blocks within reach of a centre-line (the rest of the grid is rock), and the noise a slab
at a time; what remains are two or three float32 arrays of the grid (field and noise,
and the sediment's field where there is silt).
"""

from __future__ import annotations

import hashlib
import math
import os
import warnings
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from cavenav.core.errors import CavenavWarning, MeshError
from cavenav.core.files import write_then_rename
from cavenav.world.mesh import CaveMesh, make_mesh
from cavenav.world.morphology import Boulder, Section, Speleothem, carve_scallops, settle_block

__all__ = [
    "GENERATOR_VERSION",
    "Boulder",
    "Branch",
    "PassageSpec",
    "along",
    "arc_length",
    "arc_length_at",
    "build_cave",
    "cache_dir",
    "cpu_independent",
    "gaussian_smooth",
    "resample",
    "rounded_corners",
    "settled_blocks",
]

# Bump whenever the generator's output changes, so cached meshes are rebuilt.
GENERATOR_VERSION = 3

# The voxel grid's turn about z from the world's axes (see the module's notes): 31.7
# degrees, whose tangent (the golden ratio's inverse) no fraction of small numbers comes
# near, so a passage along x or y meets the grid's planes at no short period. A turn of
# points is written term by term (no BLAS, whose kernels round differently by CPU).
GRID_YAW = math.atan(2.0 / (1.0 + math.sqrt(5.0)))
_COS, _SIN = math.cos(GRID_YAW), math.sin(GRID_YAW)

# The spacing of the tubes' samples when they are meshed (see the module's notes).
MESH_SAMPLE_M = 0.1


def _to_grid(points: np.ndarray) -> np.ndarray:
    """(n, 3) world points in the turned grid's frame."""
    x, y = points[:, 0], points[:, 1]
    return np.stack([_COS * x + _SIN * y, _COS * y - _SIN * x, points[:, 2]], axis=1)


def _to_world(points: np.ndarray) -> np.ndarray:
    """(n, 3) points of the turned grid's frame in the world's."""
    x, y = points[:, 0], points[:, 1]
    return np.stack([_COS * x - _SIN * y, _SIN * x + _COS * y, points[:, 2]], axis=1)


# Voxels handled at once (about 2 M: a few tens of MB of temporaries), and the side of
# the blocks the tubes are evaluated in (8 voxels, 1.6 m at 0.2 m: fine enough to skip
# most of the rock around a winding passage, coarse enough to be cheap to sort out).
_SLAB_VOXELS = 1 << 21
_BLOCK = 8


@dataclass(frozen=True, eq=False)
class Branch:
    """A side passage: a tube of its own that leaves the main passage and ends blind.

    Attributes:
        centreline: (n, 3) polyline from a point inside the passage it leaves to its far
            end, where the tube closes in a rounded end.
        half_width: (n,) horizontal half-size of the section at each point, metres.
        half_height: (n,) vertical half-size of the section at each point, metres.
    """

    centreline: np.ndarray
    half_width: np.ndarray
    half_height: np.ndarray


@dataclass(frozen=True, eq=False)
class PassageSpec:
    """Everything that defines one generated cave.

    Attributes:
        centreline: (n, 3) polyline from a point behind the start to a point past the exit.
        half_width: (n,) horizontal half-size of the section at each point, metres.
        half_height: (n,) vertical half-size of the section at each point, metres.
        boulders: rock in the passage: ellipsoids, which stay where they are put, and
            angular blocks, which fall from there to rest (`settled_blocks`).
        exit_index: index of the centre-line point where the exit plane lies; the surface
            is opened 1.5 m past it across the exit direction, which must be an axis.
        roughness: amplitude of the wall noise in metres (standard deviation; 0.3 looks like rock).
        seed: seeds the wall noise.
        voxel: grid spacing in metres; 0.2 resolves rock detail and stays fast.
        branches: side passages; none may reach past the exit plane, where the surface is
            opened, or it would open a second way out.
        section: how the main passage's section departs from an ellipse at each
            centre-line point (`Section`); None keeps it elliptical.
        breakdown: blocks fallen from a collapsed roof, falling to rest on the floor as
            the angular boulders do, after them: part of the cave's floor rather than
            obstacles in its way.
        speleothems: stalactites, stalagmites and columns, rock like the boulders.
        scallops: how wide the scallops dissolved into every wall are, metres (their
            depth is an eighth of that); 0 leaves the walls unscalloped.
    """

    centreline: np.ndarray
    half_width: np.ndarray
    half_height: np.ndarray
    boulders: tuple[Boulder, ...] = field(default_factory=tuple)
    exit_index: int = -1
    roughness: float = 0.3
    seed: int = 0
    voxel: float = 0.2
    branches: tuple[Branch, ...] = field(default_factory=tuple)
    section: Section | None = None
    breakdown: tuple[Boulder, ...] = field(default_factory=tuple)
    speleothems: tuple[Speleothem, ...] = field(default_factory=tuple)
    scallops: float = 0.0

    def digest(self) -> str:
        """A short hash of every input and of `GENERATOR_VERSION`, for the mesh cache."""
        h = hashlib.sha256()
        for arr in (self.centreline, self.half_width, self.half_height):
            h.update(np.ascontiguousarray(arr, np.float64).tobytes())
        for branch in self.branches:
            h.update(f"branch of {len(branch.centreline)}".encode())
            for arr in (branch.centreline, branch.half_width, branch.half_height):
                h.update(np.ascontiguousarray(arr, np.float64).tobytes())
        if self.section is not None:
            for arr in self.section.arrays():
                h.update(np.ascontiguousarray(arr, np.float64).tobytes())
        h.update(
            repr(
                (
                    self.boulders,
                    self.exit_index,
                    self.roughness,
                    self.seed,
                    self.voxel,
                    self.breakdown,
                    self.speleothems,
                    self.scallops,
                    GENERATOR_VERSION,
                )
            ).encode()
        )
        return h.hexdigest()[:16]


def cpu_independent(function: Callable[[float], float], x: np.ndarray) -> np.ndarray:
    """``function`` (``math.sin``, ``math.exp``, ...) of every element of ``x``, through the C
    library rather than numpy's ufunc.

    numpy picks its kernels by CPU: on a machine with AVX-512 its ``exp`` (and possibly
    others in later releases) differs from the C library's in the last bits, and a seed
    then draws a slightly different cave (another digest, another mesh). The C library's
    answer does not depend on the SIMD level, and equals numpy's where numpy has no SIMD
    kernel, so caves keep the digests they always had. Layout arrays are a few thousand
    elements: this costs about a millisecond.

    Returns:
        float64 array of the shape of ``x``.
    """
    x = np.asarray(x, np.float64)
    return np.fromiter(map(function, x.ravel().tolist()), np.float64, x.size).reshape(x.shape)


def gaussian_smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter1d(values, sigma, mode="nearest")``, bit for bit where
    numpy has no SIMD ``exp``, and the same on every CPU.

    scipy computes the Gaussian's weights with numpy's ``exp``, which AVX-512 machines
    compute differently in the last bits (see `cpu_independent`); the weights here come
    from the C library, in scipy's own order of operations (a radius of 4 sigma).

    Returns:
        (n,) float64, ``values`` smoothed along their one axis.
    """
    radius = int(4.0 * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1)
    weights = cpu_independent(math.exp, -0.5 / (sigma * sigma) * x**2)
    weights = weights / weights.sum()
    return ndimage.correlate1d(values, weights[::-1], mode="nearest")


def resample(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Resample a polyline at even arc length.

    Returns:
        ((k, 3) points, (k,) arc length of each); also used to interpolate profiles.
    """
    s_new = np.arange(0.0, arc_length(points)[-1] + 1e-9, spacing)
    return along(points, s_new), s_new


def arc_length(points: np.ndarray) -> np.ndarray:
    """(k,) arc length of a polyline's (k, 3) points from its first."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def arc_length_at(polyline: np.ndarray, point: np.ndarray) -> float:
    """Arc length along ``polyline`` (n, 3) of its point nearest ``point`` (3,)."""
    a, b = polyline[:-1], polyline[1:]
    seg = b - a
    length2 = np.maximum((seg**2).sum(axis=1), 1e-12)
    t = np.clip(((point - a) * seg).sum(axis=1) / length2, 0.0, 1.0)
    gap = np.linalg.norm(a + t[:, None] * seg - point, axis=1)
    k = int(np.argmin(gap))
    lengths = np.sqrt(length2)
    return float(lengths[:k].sum() + t[k] * lengths[k])


def along(points: np.ndarray, stations: np.ndarray) -> np.ndarray:
    """(n, 3) the points of a polyline at arc lengths ``stations`` (clamped to its ends)."""
    s = arc_length(points)
    return np.stack([np.interp(stations, s, points[:, k]) for k in range(3)], axis=1)


def rounded_corners(corners: np.ndarray, radius: float, chords: int = 64) -> np.ndarray:
    """The polyline through ``corners`` with each inner corner rounded off by a circular
    arc of ``radius`` metres, tangent to both legs.

    A passage's sections are laid across its centre line, each in the frame of its own
    sample. Where the line turns at a point, the samples on either side of the corner
    carry frames turned by the whole angle, and the wall shows a straight seam where
    their sections meet. Along the arc the frames turn by spacing / ``radius`` radians
    from one sample to the next, as along a winding passage. The arc leaves each leg
    ``radius`` x tan(turn / 2) before the corner (at a right angle, ``radius``); where a
    leg is shorter than twice that, the arc shrinks to fit. A corner that turns straight
    back keeps its point. Solution passages round their bends so; the inner corner,
    within the passage's half-width of the arc, stays a sharp edge of rock.

    Each arc is a rational quadratic Bezier curve (its control point the corner, its
    weight cos(turn / 2)), which is exactly circular and needs no trigonometry; the
    scalars are Python floats written out term by term (numpy's dot product goes through
    BLAS, whose kernels differ by CPU, and Python's ``sum`` changed its rounding in 3.12),
    so a seed draws the same line on every machine.

    Returns:
        the (k, 3) polyline, each arc drawn with ``chords`` chords.
    """
    corners = np.asarray(corners, np.float64)
    corners = corners[np.r_[True, (np.diff(corners, axis=0) != 0.0).any(axis=1)]]  # no repeats
    t = np.linspace(0.0, 1.0, chords + 1)[:, None]
    out = [corners[:1]]
    for before, corner, after in zip(corners[:-2], corners[1:-1], corners[2:], strict=True):
        into, out_of = corner - before, after - corner
        (ix, iy, iz), (ox, oy, oz) = into.tolist(), out_of.tolist()
        into_length, out_length = math.hypot(ix, iy, iz), math.hypot(ox, oy, oz)
        cos_turn = min(max((ix * ox + iy * oy + iz * oz) / (into_length * out_length), -1.0), 1.0)
        if not -1.0 < cos_turn < 1.0:
            out.append(corner[None])  # straight on, or straight back: no arc fits
            continue
        tangent_length = radius * math.sqrt((1.0 - cos_turn) / max(1.0 + cos_turn, 1e-12))
        reach = min(tangent_length, 0.5 * into_length, 0.5 * out_length)
        first = corner - into * (reach / into_length)
        last = corner + out_of * (reach / out_length)
        weight = math.sqrt(0.5 * (1.0 + cos_turn))
        a, b, c = (1.0 - t) ** 2, 2.0 * t * (1.0 - t) * weight, t**2
        out.append((a * first + b * corner + c * last) / (a + b + c))
    out.append(corners[-1:])
    return np.concatenate(out)


def _frames(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit tangent, horizontal normal (left) and section 'up' at each centre-line point."""
    t = np.gradient(points, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.cross(np.array([0.0, 0.0, 1.0]), t)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    u = np.cross(t, n)
    return t, n, u


@dataclass(frozen=True)
class _Tube:
    """One swept tube ready to evaluate: samples, their frames, sizes and a search tree."""

    points: np.ndarray  # (n, 3)
    tangent: np.ndarray  # (n, 3) unit
    normal: np.ndarray  # (n, 3) unit, horizontal
    up: np.ndarray  # (n, 3) unit
    half_width: np.ndarray  # (n,)
    half_height: np.ndarray  # (n,)
    tree: cKDTree
    along: np.ndarray  # (n,) arc length of each sample
    section: Section | None = None

    @classmethod
    def of(
        cls,
        centreline: np.ndarray,
        half_width: np.ndarray,
        half_height: np.ndarray,
        section: Section | None = None,
    ) -> _Tube:
        old = arc_length(np.asarray(centreline, np.float64))
        stations = np.linspace(0.0, old[-1], int(round(old[-1] / MESH_SAMPLE_M)) + 1)
        pts = along(np.asarray(centreline, np.float64), stations)
        tangent, normal, up = _frames(pts)
        half_w = np.interp(stations, old, np.asarray(half_width, np.float64))
        half_h = np.interp(stations, old, np.asarray(half_height, np.float64))
        if section is not None:
            section = Section(*(np.interp(stations, old, a) for a in section.arrays()))
        return cls(pts, tangent, normal, up, half_w, half_h, cKDTree(pts), stations, section)

    @property
    def size(self) -> float:
        """The largest half-size of any section, reaches of its features included, metres."""
        size = max(self.half_width.max(), self.half_height.max())
        if self.section is not None:
            s = self.section
            size = max(
                size,
                float((self.half_height + s.canyon_depth).max()),
                float((self.half_height + s.ceiling_channel).max()),
                float((self.half_width + np.abs(s.notch)).max()),
            )
        return float(size)

    def field(self, grid: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray | None]:
        """phi of this tube at ``grid`` (m, 3): the least over the 4 nearest samples of
        the radial distance outside their sections, ``reach`` where none is within reach;
        and the sediment's field there, from the nearest sample (None without a `Section`).

        Returns:
            ((m,) float32, (m,) float32 positive under the sediment's top, or None).
        """
        phi = np.full(len(grid), reach, np.float32)
        sediment = None if self.section is None else np.full(len(grid), -np.inf, np.float32)
        dist, idx = self.tree.query(grid, k=4, distance_upper_bound=reach)
        for j in range(idx.shape[1]):
            near = np.isfinite(dist[:, j])
            i = idx[near, j]
            o = grid[near] - self.points[i]
            a = np.einsum("ij,ij->i", o, self.normal[i])
            b = np.einsum("ij,ij->i", o, self.up[i])
            c = np.einsum("ij,ij->i", o, self.tangent[i])
            if self.section is None:
                r = np.sqrt(
                    (a / self.half_width[i]) ** 2
                    + (b / self.half_height[i]) ** 2
                    + (c / self.half_width[i]) ** 2
                )
                length = np.linalg.norm(o, axis=1)
                value = length - length / np.maximum(r, 1e-6)
            else:
                value, floor = self.section.field(
                    i, a, b, c, self.half_width[i], self.half_height[i], self.along[i] + c
                )
                if j == 0 and sediment is not None:
                    sediment[near] = floor
            phi[near] = np.minimum(phi[near], value.astype(np.float32))
        return phi, sediment


def _fractal_noise(shape: tuple[int, ...], voxel: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise of unit standard deviation over the whole grid, (shape) float32.

    Octaves of wavelength 4, 1.6 and 0.8 m weighted 1, 0.5 and 0.25: bulges, ledges, knobs.
    Each octave is a coarse lattice of random values blown up by cubic interpolation,
    exactly as ``ndimage.zoom(coarse, cells, order=3, prefilter=False)`` cut to ``shape``
    would, but a slab at a time and without the zoom's overhang of 3 cells per axis:
    the same numbers, in a fraction of the time and memory.
    """
    out = np.zeros(shape, np.float32)
    rows = max(1, _SLAB_VOXELS // (shape[1] * shape[2]))
    for wavelength, weight in ((4.0, 1.0), (1.6, 0.5), (0.8, 0.25)):
        cells = max(wavelength / voxel, 1.0)
        coarse_shape = tuple(int(np.ceil(s / cells)) + 3 for s in shape)
        coarse = rng.standard_normal(coarse_shape).astype(np.float32)
        # zoom's mapping: output index k samples the lattice at k (n_in - 1) / (n_out - 1).
        zoomed = np.array([int(round(n * cells)) for n in coarse_shape])
        step = (np.array(coarse_shape) - 1) / (zoomed - 1)
        for a in range(0, shape[0], rows):
            b = min(a + rows, shape[0])
            ranges = (np.arange(a, b), np.arange(shape[1]), np.arange(shape[2]))
            coords = np.meshgrid(*(r * step[k] for k, r in enumerate(ranges)), indexing="ij")
            fine = ndimage.map_coordinates(
                coarse, coords, output=np.float32, order=3, prefilter=False
            )
            out[a:b] += weight * fine
    out /= out.std()  # unit standard deviation, whatever the grid size
    return out


def build_cave(spec: PassageSpec, name: str = "cave") -> CaveMesh:
    """Generate the cave mesh for ``spec`` (cached on disk, see `cache_dir`).

    A damaged cache file (a crash of another tool, a disk error) is built again, with one
    `CavenavWarning`; a cache that cannot be written (read-only, full) is no error, but
    worth one warning: every process then builds its caves again.
    """
    cache = cache_dir() / f"{name}-{spec.digest()}.npz"
    if cache.is_file():
        cached = _read_cached(cache, name)
        if cached is not None:
            return cached
    generated = _generate(spec, name)
    # Stored as float32: the mesh returned is that copy, so cold and warm runs agree.
    vertices, faces = generated.vertices.astype(np.float32), generated.faces.astype(np.int32)

    def save(tmp: Path) -> None:
        with open(tmp, "wb") as out:  # np.savez would add ".npz" to a path
            np.savez_compressed(out, vertices=vertices, faces=faces)

    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        write_then_rename(cache, save)
    except OSError as error:
        if cache.parent not in _UNWRITABLE:  # once per folder and process, not per cave
            _UNWRITABLE.add(cache.parent)
            warnings.warn(
                f"cannot keep built caves in {cache.parent} ({error.strerror or error}): "
                "every process builds its caves again; set CAVENAV_CACHE to a writable folder",
                CavenavWarning,
                stacklevel=2,
            )
    return make_mesh(vertices, faces, name)


# Cache folders already found unwritable in this process, warned about once.
_UNWRITABLE: set[Path] = set()


def _read_cached(path: Path, name: str) -> CaveMesh | None:
    """The mesh cached at ``path``, or None (with a warning) when the file is damaged."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return make_mesh(data["vertices"], data["faces"], name)
    except (
        OSError,
        ValueError,
        EOFError,
        KeyError,
        zipfile.BadZipFile,
        zlib.error,
        MeshError,
    ) as error:
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        warnings.warn(
            f"the cached cave {path} is damaged ({reason}): building it again",
            CavenavWarning,
            stacklevel=3,  # where the cave was asked for
        )
        return None


def cache_dir() -> Path:
    """Mesh cache: ``$CAVENAV_CACHE`` or ``$XDG_CACHE_HOME/cavenav`` or ``~/.cache/cavenav``."""
    if os.environ.get("CAVENAV_CACHE"):
        return Path(os.environ["CAVENAV_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "cavenav"


def _generate(spec: PassageSpec, name: str) -> CaveMesh:
    from skimage.measure import marching_cubes

    phi, sediment, lo, axes, main = _rock_field(spec)
    _add_rocks(phi, sediment, spec, lo, axes)
    del sediment
    verts, faces, _, _ = marching_cubes(phi, level=0.0, spacing=(spec.voxel,) * 3)
    verts = _to_world(verts + lo)
    exit_at = arc_length(np.asarray(spec.centreline, np.float64))[spec.exit_index]
    faces = _open_exit(verts, faces, main, int(np.argmin(np.abs(main.along - exit_at))))
    return make_mesh(verts, _largest_components(faces, len(verts)), name)


def settled_blocks(spec: PassageSpec) -> list[tuple[Boulder, np.ndarray]]:
    """Where the angular blocks of ``spec`` (its boulders', then its breakdown's) come to
    rest in the cave built from it, each with the (k, 2) points of the floor or of the
    blocks under it that it rests on (`settle_block`). The spec's centres are where each
    block starts to fall: the cave's rough floor, which only the built field knows,
    decides where it stops."""
    phi, sediment, lo, axes, _ = _rock_field(spec)
    return _add_rocks(phi, sediment, spec, lo, axes, with_speleothems=False)


def _rock_field(
    spec: PassageSpec,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, list[np.ndarray], _Tube]:
    """The field of the cave's passages, walls roughened and scalloped, silt laid (rock
    where 0 or more), the sediment's own field (None without silt), the grid's corner and
    axes in the turned grid's frame, and the main passage's tube."""
    voxel = spec.voxel
    tubes = [_Tube.of(spec.centreline, spec.half_width, spec.half_height, spec.section)]
    tubes += [_Tube.of(b.centreline, b.half_width, b.half_height) for b in spec.branches]
    reach = max(tube.size for tube in tubes) + 1.0 + spec.roughness

    # The grid, turned by GRID_YAW, holds every tube; the exit is opened after meshing.
    every_point = _to_grid(np.concatenate([tube.points for tube in tubes]))
    lo = every_point.min(axis=0) - reach
    hi = every_point.max(axis=0) + reach
    shape = tuple(int(np.ceil((hi[k] - lo[k]) / voxel)) + 1 for k in range(3))
    axes = [lo[k] + voxel * np.arange(shape[k]) for k in range(3)]

    # Rock (``reach``) wherever no tube reaches: the value a voxel with no centre-line
    # sample within reach always had, so skipping those voxels changes no mesh.
    phi = np.full(shape, reach, np.float32)
    sediment = None if spec.section is None else np.full(shape, -np.inf, np.float32)
    for idx in _blocks_near(every_point, lo, voxel, shape, reach):
        grid = _to_world(np.stack([axes[k][idx[:, k]] for k in range(3)], axis=1))
        value, floor = tubes[0].field(grid, reach)
        for tube in tubes[1:]:
            value = np.minimum(value, tube.field(grid, reach)[0])
        phi[idx[:, 0], idx[:, 1], idx[:, 2]] = value
        if floor is not None and sediment is not None:
            sediment[idx[:, 0], idx[:, 1], idx[:, 2]] = floor

    rng = np.random.default_rng(spec.seed)
    noise = _fractal_noise(shape, voxel, rng)
    noise *= spec.roughness  # in place: no third grid-sized array
    phi += noise
    del noise
    carve_scallops(phi, lo, voxel, spec.scallops, spec.scallops / 8, rng)
    if sediment is not None:  # laid over the rough rock: flat where it fills, rock pokes through
        np.maximum(phi, sediment, out=phi)
    return phi, sediment, lo, axes, tubes[0]


def _open_exit(verts: np.ndarray, faces: np.ndarray, main: _Tube, exit_index: int) -> np.ndarray:
    """``faces`` but those whose centre lies past the plane 1.5 m beyond the exit, across
    the exit's direction (which must be an axis): the passage runs on past that plane, so
    the surface stays open where it crossed it, in a rim as ragged as a facet."""
    exit_dir = main.tangent[exit_index]
    axis = int(np.argmax(np.abs(exit_dir)))
    sign = float(np.sign(exit_dir[axis]))
    cut = main.points[exit_index, axis] + 1.5 * sign
    past = (verts[faces, axis].sum(axis=1) / 3.0 - cut) * sign > 0.0
    return faces[~past]


def _add_rocks(
    phi: np.ndarray,
    sediment: np.ndarray | None,
    spec: PassageSpec,
    lo: np.ndarray,
    axes: list[np.ndarray],
    with_speleothems: bool = True,
) -> list[tuple[Boulder, np.ndarray]]:
    """Make rock (in place) of the boulders, breakdown and speleothems of ``spec``, each
    evaluated only in the part of the grid (corner ``lo``, coordinates ``axes``, in the
    turned grid's frame) within its reach. The angular blocks fall first, one by one in
    the spec's order, each onto the floor and the blocks already down (`settle_block`);
    they are returned where they came to rest, with what they rest on."""

    def region(centre: np.ndarray, reach_m: float) -> tuple[slice, ...] | None:
        at = _to_grid(np.asarray(centre, np.float64)[None])[0]
        b_lo = np.maximum(((at - reach_m - 1.0 - lo) / spec.voxel).astype(int), 0)
        b_hi = np.minimum(((at + reach_m + 1.0 - lo) / spec.voxel).astype(int) + 1, phi.shape)
        return None if np.any(b_hi <= b_lo) else tuple(slice(b_lo[k], b_hi[k]) for k in range(3))

    def rock(centre: np.ndarray, reach_m: float, outside: Callable[[np.ndarray], np.ndarray]):  # noqa: ANN202
        sl = region(centre, reach_m)
        if sl is None:
            return
        sub = np.stack(np.meshgrid(*[axes[k][sl[k]] for k in range(3)], indexing="ij"), -1)
        inside = -outside(_to_world(sub.reshape(-1, 3))).reshape(sub.shape[:3])
        phi[sl] = np.maximum(phi[sl], inside)

    settled = []
    for boulder in (*spec.boulders, *spec.breakdown):
        if boulder.angular is not None:
            boulder, contact = _settle(phi, sediment, boulder, region, axes)
            settled.append((boulder, contact))
        rock(np.asarray(boulder.centre), boulder.reach, boulder.field)
    for cone in spec.speleothems if with_speleothems else ():
        middle = np.array([cone.x, cone.y, (cone.bottom + cone.top) / 2])
        rock(middle, max(cone.reach, (cone.top - cone.bottom) / 2), cone.field)
    return settled


def _settle(
    phi: np.ndarray,
    sediment: np.ndarray | None,
    block: Boulder,
    region: Callable[[np.ndarray, float], tuple[slice, ...] | None],
    axes: list[np.ndarray],
) -> tuple[Boulder, np.ndarray]:
    """`settle_block` on the grid's columns around ``block``, each from the height of the
    block's centre (where it starts to fall: in the water) down to the grid's floor."""
    sl = region(np.asarray(block.centre), block.reach)
    if sl is None:
        return block, np.empty((0, 2))
    tops = int(np.searchsorted(axes[2], block.centre[2])) + 1
    columns = (sl[0], sl[1], slice(0, min(tops, phi.shape[2])))
    gx, gy = np.meshgrid(axes[0][sl[0]], axes[1][sl[1]], indexing="ij")
    xy = _to_world(np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1))
    rock = phi[columns].reshape(gx.size, -1)
    silt = None if sediment is None else (sediment[columns] >= phi[columns]).reshape(gx.size, -1)
    return settle_block(block, xy[:, 0], xy[:, 1], axes[2][columns[2]], rock, silt)


def _blocks_near(
    points: np.ndarray, lo: np.ndarray, voxel: float, shape: tuple[int, ...], reach: float
) -> Iterator[np.ndarray]:
    """Grid indices of the voxels that may lie within ``reach`` of a centre-line point.

    The grid (``shape`` voxels of ``voxel`` metres from corner ``lo``) is cut into blocks of
    `_BLOCK` voxels a side; a block whose centre is farther than ``reach`` plus its
    half-diagonal (and a voxel, for rounding) from every point is left out whole: none of
    its voxels has a sample within reach. Yields (m, 3) int arrays of about `_SLAB_VOXELS`
    voxels, so the memory of one batch is bounded whatever the cave's size.
    """
    size = np.array(shape)
    counts = -(-size // _BLOCK)
    blocks = np.stack(np.meshgrid(*(np.arange(n) for n in counts), indexing="ij"), -1)
    blocks = blocks.reshape(-1, 3)
    centres = lo + voxel * (blocks * _BLOCK + (_BLOCK - 1) / 2)
    half_diagonal = voxel * (_BLOCK - 1) * np.sqrt(3) / 2
    gap, _ = cKDTree(points).query(centres, distance_upper_bound=reach + half_diagonal + voxel)
    near = blocks[np.isfinite(gap)]
    offsets = np.stack(np.meshgrid(*[np.arange(_BLOCK)] * 3, indexing="ij"), -1).reshape(-1, 3)
    per_batch = max(1, _SLAB_VOXELS // len(offsets))
    for first in range(0, len(near), per_batch):
        idx = (near[first : first + per_batch, None, :] * _BLOCK + offsets).reshape(-1, 3)
        yield idx[(idx < size).all(axis=1)]


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

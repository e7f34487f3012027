"""What can be computed once per cave or per camera, so that a frame only looks it up.

- `surface_table`: per triangle and per side, the rock's albedo (seeded 3-D noise,
  sediment on up-facing floors, darker in crevices) and the daylight it receives through
  the cave's openings. Both come from one batch of cosine-weighted rays cast from every
  triangle: rays that stay within a short radius measure how enclosed (crevice-like) the
  surface is; rays that leave the cave gather open-water light attenuated over their
  path to the cave's bounds; rays that hit another lit wall add one bounce. The side of a
  triangle that a camera sees is decided per pixel, so meshes of any winding work.
- `backscatter_table`: the lamps' light scattered back into each pixel by the water
  between the camera and depth r. Lamps and camera move together, so in the camera frame
  this depends only on the pixel and r; it is tabulated on a coarse pixel grid and a
  square-root depth grid and interpolated per pixel.

See `cavenav.sensors.optics` for the image-formation model.
"""

from __future__ import annotations

import hashlib
import math
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from cavenav.core.files import write_then_rename
from cavenav.sensors import kernels
from cavenav.sensors import optics as optics_model
from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.kernels import (
    beam_profile,
    bounce_light,
    corner_sums,
    gather_sky,
    hemisphere_rays,
    integrate_backscatter,
)
from cavenav.sensors.optics import Optics
from cavenav.world.mesh import CaveMesh
from cavenav.world.procedural import cache_dir
from cavenav.world.raycast import RayCaster

__all__ = [
    "BackscatterTable",
    "LampArrays",
    "at_vertices",
    "backscatter_table",
    "face_normals",
    "lamp_arrays",
    "rock_albedo",
    "rock_photographs",
    "RockPhotographs",
    "surface_patches",
    "surface_table",
    "vertex_normals",
]

ALBEDO, DAYLIGHT = slice(0, 3), slice(3, 6)  # columns of the surface table
CREVICE_RADIUS_M = 0.6  # rays hitting rock closer than this count as enclosed
# Most ray origins of the surface table: 64 rays each, so at most 12.8 million rays
# (about 10 s on 2 cores at 3 million triangles, whose BVH slows every ray). Every
# cave shipped or generated has fewer triangles (S1-S5 about 80,000-100,000), and keeps
# one origin per triangle; a finer mesh is grouped into patches (`surface_patches`).
SURFACE_PATCHES = 200_000


# Face normals and areas by mesh, while the mesh lives (see `face_normals`).
_FACES: weakref.WeakKeyDictionary[CaveMesh, tuple[np.ndarray, np.ndarray]] = (
    weakref.WeakKeyDictionary()
)
_FACES_LOCK = threading.Lock()


# The limestone palette (reflectance, R G B), relative to `Optics.rock_colour`'s default:
# pale cream limestone, grey limestone, brown (iron-stained) rock, and the black-brown
# manganese and iron oxide coatings that cover patches of flooded cave walls.
DEFAULT_ROCK = (0.40, 0.37, 0.33)
ROCK_PALETTE = (
    (0.62, 0.57, 0.47),  # cream
    (0.44, 0.43, 0.41),  # grey
    (0.40, 0.30, 0.21),  # brown
)
COATING = (0.07, 0.06, 0.05)


def _noise_field(p: np.ndarray, rng: np.random.Generator, octaves) -> np.ndarray:  # noqa: ANN001
    """(n,) smooth band-limited noise at points p (n, 3): random plane waves per octave,
    ``octaves`` (wavelength m, weight) pairs; about unit variance."""
    field = np.zeros(len(p), np.float32)
    for wavelength, weight in octaves:
        for _ in range(3):
            k = rng.normal(size=3).astype(np.float32)
            k *= 2 * np.pi / wavelength / np.linalg.norm(k)
            field += weight * np.sin(p @ k + rng.uniform(0, 2 * np.pi)) / 1.2
    return field


def rock_albedo(mesh: CaveMesh, seed: int = 0, colour=DEFAULT_ROCK) -> np.ndarray:
    """(n_vertices, 3) float32 rock reflectance from seeded 3-D noise at each vertex.

    One noise field chooses the rock's colour from `ROCK_PALETTE` (cream where it is
    high, brown where it is low, grey between), a second lays dark mineral coatings in
    sharp-edged patches over about a tenth of the walls, and bands of strata run through
    it all, as in bedded limestone. ``colour``
    scales the palette (its default, `DEFAULT_ROCK`, is the palette's own mean tone).
    Random plane waves are cheap to evaluate once per vertex: mottling from metres down
    to a few decimetres.
    """
    rng = np.random.default_rng(seed)
    p = mesh.vertices.astype(np.float32)
    tone = _noise_field(p, rng, ((4.0, 0.6), (1.5, 0.3), (0.5, 0.2)))
    palette = np.asarray(ROCK_PALETTE, np.float32)
    cream = np.clip(tone, 0.0, 1.0)[:, None]
    brown = np.clip(-tone, 0.0, 1.0)[:, None]
    rock = palette[1] + cream * (palette[0] - palette[1]) + brown * (palette[2] - palette[1])
    coating = _noise_field(p, rng, ((2.5, 0.7), (0.8, 0.35), (0.3, 0.15)))
    cover = np.clip((coating - 0.9) * 4.0, 0.0, 1.0)[:, None]  # about a tenth, sharp edges
    rock += cover * (np.asarray(COATING, np.float32) - rock)
    strata = 0.08 * np.sin(p[:, 2] * 2 * np.pi / rng.uniform(0.6, 1.4) + rng.uniform(0, 6.3))
    rock *= (1.0 + strata)[:, None] * (np.asarray(colour, np.float32) / np.asarray(DEFAULT_ROCK))
    return np.clip(rock, 0.02, 0.9).astype(np.float32)


ROCK_PHOTOGRAPHS = Path(__file__).parent / "rock"
# The photographs' span on the rock: the bedding of StriatedRock then runs 5-10 cm thick,
# the cracks of CaveWall a few decimetres apart, as in limestone passage walls.
PHOTOGRAPH_SPAN_M = 2.0
PHOTOGRAPH_FILES = ("StriatedRock_Natural.jpg", "CaveWall_Natural.jpg")  # walls, floors
# The photographs are of dry rock under diffuse daylight. Wet rock under a lamp shows its
# pale grains and dark cracks with more contrast (water darkens what is porous, fills
# the fine relief that scatters light): their relative luminance is raised to this power.
PHOTOGRAPH_CONTRAST = 2.0


@dataclass(frozen=True)
class RockPhotographs:
    """Photographed rock as the renderer samples it (`kernels.photographed_rock`): each
    photograph's luminance as a mip pyramid of square uint8 levels, packed in one array.

    Attributes:
        texels: every level of every photograph, row-major, concatenated.
        offsets: (photographs, levels) where each level starts in ``texels``.
        sizes: (levels,) texels a side of each level, a power of two, halving.
        units: (photographs,) the relative albedo of one unit of a texel: a texel times
            its unit is the rock's albedo relative to its mean, with contrast as wet
            rock shows it (`PHOTOGRAPH_CONTRAST`).
        texel_m: the finest level's texel on the rock, metres.
    """

    texels: np.ndarray
    offsets: np.ndarray
    sizes: np.ndarray
    units: np.ndarray
    texel_m: float

    def as_tuple(self) -> tuple:
        """What the kernels take."""
        return self.texels, self.offsets, self.sizes, self.units, 1.0 / self.texel_m


def _mip_levels(luma: np.ndarray, smallest: int = 8) -> list[np.ndarray]:
    """``luma`` and its halvings by 2x2 means (a box filter: each coarser texel is the
    mean of what a pixel that large would gather), down to ``smallest`` a side."""
    levels = [luma]
    while levels[-1].shape[0] > smallest:
        finer = levels[-1].astype(np.float32)
        half = 0.25 * (
            finer[0::2, 0::2] + finer[1::2, 0::2] + finer[0::2, 1::2] + finer[1::2, 1::2]
        )
        levels.append(np.round(half).astype(np.uint8))
    return levels


@lru_cache(maxsize=1)
def rock_photographs() -> RockPhotographs:
    """The shipped photographs of rock (`ROCK_PHOTOGRAPHS`, credited in its NOTICE.md)
    as `RockPhotographs`, read once per process.

    Only the JPEG's luma is decoded (its Y channel, no chroma and no colour conversion):
    the photographs are near-neutral grey, and the rock's colour comes from the cave's
    own limestone palette (`rock_albedo`), which they modulate.
    """
    from PIL import Image

    pyramids, units = [], []
    for name in PHOTOGRAPH_FILES:
        with Image.open(ROCK_PHOTOGRAPHS / name) as image:
            image.draft("L", image.size)
            luma = np.asarray(image.convert("L"), np.float64)
        relative = (luma / luma.mean()) ** PHOTOGRAPH_CONTRAST
        relative /= relative.mean()
        unit = float(np.percentile(relative, 99.9)) / 255.0  # the brightest specks clip
        pyramids.append(_mip_levels(np.round(np.minimum(relative / unit, 255)).astype(np.uint8)))
        units.append(unit)
    sizes = np.array([level.shape[0] for level in pyramids[0]], np.int64)
    flat = [level.ravel() for pyramid in pyramids for level in pyramid]
    starts = np.cumsum([0] + [len(level) for level in flat[:-1]])
    return RockPhotographs(
        texels=np.concatenate(flat),
        offsets=starts.reshape(len(pyramids), len(sizes)).astype(np.int64),
        sizes=sizes,
        units=np.array(units, np.float32),
        texel_m=PHOTOGRAPH_SPAN_M / int(sizes[0]),
    )


def face_normals(mesh: CaveMesh) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3) unit normals (by winding) and (m,) areas of the triangles, read-only.

    Kept while the mesh lives: the surface table and both vertex averages of a rig need
    them, and at millions of triangles each computation takes a second.
    """
    with _FACES_LOCK:
        known = _FACES.get(mesh)
    if known is not None:
        return known
    v, f = mesh.vertices, mesh.faces
    a = v[f[:, 0]]
    ab, ac = v[f[:, 1]] - a, v[f[:, 2]] - a
    # np.cross's own formula, written out on columns: the same bits, without its copies.
    normal = np.empty_like(ab)
    normal[:, 0] = ab[:, 1] * ac[:, 2] - ab[:, 2] * ac[:, 1]
    normal[:, 1] = ab[:, 2] * ac[:, 0] - ab[:, 0] * ac[:, 2]
    normal[:, 2] = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    double_area = np.linalg.norm(normal, axis=1)
    normal /= np.maximum(double_area, 1e-12)[:, None]
    area = 0.5 * double_area
    normal.flags.writeable = area.flags.writeable = False
    with _FACES_LOCK:
        _FACES[mesh] = (normal, area)
    return normal, area


def at_vertices(mesh: CaveMesh, per_face: np.ndarray) -> np.ndarray:
    """(n_vertices, ...) float32 area-weighted mean of a per-face array over each vertex's
    faces, for smooth interpolation across triangles."""
    _, area = face_normals(mesh)
    n, m = len(mesh.vertices), len(mesh.faces)
    weighted = (per_face * area.reshape(-1, *([1] * (per_face.ndim - 1)))).reshape(m, -1)
    total = np.zeros((n, weighted.shape[1]))
    weight = np.zeros(n)
    corner_sums(mesh.faces, np.ascontiguousarray(weighted), area, total, weight)
    total /= np.maximum(weight, 1e-12)[:, None]
    return total.reshape(n, *per_face.shape[1:]).astype(np.float32)


def vertex_normals(mesh: CaveMesh) -> np.ndarray:
    """(n_vertices, 3) float32 unit normals: the area-weighted mean of the faces around.

    Shading with these interpolated across each triangle hides the facets of coarse
    meshes. Where neighbouring faces disagree in winding they cancel, and the renderer
    falls back to the face normal.
    """
    normals = at_vertices(mesh, face_normals(mesh)[0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.maximum(length, 1e-12)).astype(np.float32)


def _hemisphere(n: int) -> np.ndarray:
    """(n, 3) cosine-weighted directions around +z (a Fibonacci spiral on the disc)."""
    i = np.arange(n) + 0.5
    r = np.sqrt(i / n)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=1)


# Recent tables by mesh content and parameters: rigs are many, caves few.
_SURFACE_CACHE: OrderedDict[tuple, np.ndarray] = OrderedDict()
_SURFACE_CACHE_SIZE = 6
_SURFACE_LOCK = threading.Lock()


def surface_table(
    caster: RayCaster, optics: Optics, seed: int = 0, rays: int = 32, *, cached: bool = True
) -> np.ndarray:
    """(m, 2, 6) float32: per triangle and side (0: along its normal, 1: against it),
    columns 0-2 the albedo and 3-5 the daylight D (radiance = albedo * D).

    About 1 s per 100,000 triangles on 2 cores, and rays from at most `SURFACE_PATCHES`
    places however fine the mesh; kept per mesh and parameters in memory and, like the
    caves, on disk (`cavenav.world.procedural.cache_dir`), so a new process finds it.
    ``cached=False`` computes it anew and keeps nothing (the warm-up, which must run
    every kernel).
    """
    if not cached:
        return _surface_table(caster, optics, seed, rays)
    mesh = caster.mesh
    water = optics.medium
    digest = hashlib.blake2b(mesh.vertices.tobytes(), digest_size=16)
    digest.update(mesh.faces.tobytes())
    key = (digest.hexdigest(), seed, rays, optics.rock_colour, optics.sediment_colour,
           optics.daylight, optics.daylight_colour, water.absorption, water.scattering)  # fmt: skip
    # Sweeps build rigs on several threads at once: look up and evict under the lock, and
    # return the table held here (another thread may evict the key right after).
    with _SURFACE_LOCK:
        table = _SURFACE_CACHE.get(key)
        if table is not None:
            _SURFACE_CACHE.move_to_end(key)
            return table
    path = cache_dir() / "lighting" / f"{_file_key(key)}.npy"
    table = _load_table(path, len(mesh.faces))
    if table is None:
        table = _surface_table(caster, optics, seed, rays)  # outside the lock: about a second
        _store_table(path, table)
    with _SURFACE_LOCK:
        _SURFACE_CACHE[key] = table
        while len(_SURFACE_CACHE) > _SURFACE_CACHE_SIZE:
            _SURFACE_CACHE.popitem(last=False)
    return table


@lru_cache(maxsize=1)
def _source_digest() -> str:
    """Digest of the code that computes a surface table: this module (albedo, patches,
    crevice radius), the kernels and the optics model.

    Part of every file key, so that any change to that code makes new files instead of
    serving tables the old code computed, with no version to remember to bump. Read once
    per process (70 kB, well under a millisecond).
    """
    digest = hashlib.blake2b(digest_size=16)
    for source in (__file__, kernels.__file__, optics_model.__file__):
        digest.update(Path(source).read_bytes())
    return digest.hexdigest()


def _file_key(key: tuple) -> str:
    blob = repr((_source_digest(), key)).encode()  # floats' repr is exact
    return hashlib.blake2b(blob, digest_size=16).hexdigest()


def _load_table(path: Path, triangles: int) -> np.ndarray | None:
    """The table stored at ``path``, or None when there is none or it is not whole."""
    try:
        table = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None
    if table.shape != (triangles, 2, 6) or table.dtype != np.float32:
        return None
    return table


def _store_table(path: Path, table: np.ndarray) -> None:
    """Keep ``table`` for the next process; a cache that cannot be written is no error."""

    def save(tmp: Path) -> None:
        with open(tmp, "wb") as out:  # np.save would add ".npy" to a path
            np.save(out, table, allow_pickle=False)

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_then_rename(path, save)
    except OSError:
        pass


def surface_patches(
    centre: np.ndarray, normal: np.ndarray, area: np.ndarray, limit: int | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """Group a fine mesh's triangles into about ``limit`` small patches of like facing.

    A patch is the triangles whose centres share a cube of the grid and whose normals
    share an octant and a largest component, so they face within 60 degrees of one
    another: the two faces of a thin wall, or two walls meeting in a corner, never share
    a patch.
    The cube's side is set from the total area so that about ``limit`` cubes are
    occupied: 5 cm for 3 million triangles over a 20 m tile, well under the 0.6 m of
    `CREVICE_RADIUS_M` and the metres over which daylight changes.

    Args:
        centre: (m, 3) triangle centres.
        normal: (m, 3) unit normals.
        area: (m,) areas.
        limit: the number of patches aimed at (default `SURFACE_PATCHES`).

    Returns:
        None when m <= ``limit`` (each triangle is its own patch); else ``patch``, (m,)
        int64 the patch of each triangle, and ``representative``, (k,) int64 for each
        patch the triangle nearest its area-weighted centre, whose rays stand for it.
    """
    m = len(centre)
    limit = SURFACE_PATCHES if limit is None else limit
    if m <= limit:
        return None
    facing = ((normal > 0.0) @ np.array([1, 2, 4])) * 3 + np.abs(normal).argmax(axis=1)
    low = centre.min(axis=0)
    # A surface crossing cubes at a slant occupies more than area / side^2 of them, about
    # 1.2 times as many; a retry corrects any remaining excess.
    side = math.sqrt(1.2 * max(float(area.sum()), 1e-12) / limit)
    for _ in range(4):
        cell = ((centre - low) / side).astype(np.int64)
        dims = cell.max(axis=0) + 1
        key = ((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]) * 24 + facing
        order = np.argsort(key, kind="stable")  # by patch
        starts = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])
        if len(starts) <= 1.15 * limit:
            break
        side *= math.sqrt(len(starts) / limit)
    k = len(starts)
    sorted_patch = np.zeros(m, np.int64)
    sorted_patch[starts[1:]] = 1
    sorted_patch = np.cumsum(sorted_patch)
    patch = np.empty(m, np.int64)
    patch[order] = sorted_patch
    weight = np.maximum(np.bincount(patch, area, minlength=k), 1e-30)
    mean = np.stack([np.bincount(patch, area * centre[:, j], k) / weight for j in range(3)], 1)
    gap = np.einsum("ij,ij->i", centre - mean[patch], centre - mean[patch])[order]
    # In each patch's run of the sorted order, the first triangle at the run's least gap.
    nearest = np.flatnonzero(gap == np.minimum.reduceat(gap, starts)[sorted_patch])
    first = np.r_[True, sorted_patch[nearest][1:] != sorted_patch[nearest][:-1]]
    return patch, order[nearest[first]]


def _ray_origins(
    centre: np.ndarray, normal: np.ndarray, area: np.ndarray
) -> tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """Where the surface table's rays leave from, and how to spread their findings.

    Rays leave from every triangle of a mesh of up to SURFACE_PATCHES, else from one per
    patch; what they find (enclosure, daylight, bounce) is then spread over the patch,
    while albedo and sediment stay each triangle's own.

    Returns:
        origins (k, 3), their normals (k, 3), and a function taking (k, ...) per-origin
        values to (m, ...) per-triangle values.
    """
    patches = surface_patches(centre, normal, area)
    if patches is None:
        return centre, normal, lambda per_origin: per_origin
    patch, representative = patches
    return centre[representative], normal[representative], lambda per_origin: per_origin[patch]


def _surface_table(caster: RayCaster, optics: Optics, seed: int, n_rays: int) -> np.ndarray:
    mesh = caster.mesh
    rng = np.random.default_rng([seed, 7])
    normal, area = face_normals(mesh)
    centre = mesh.vertices[mesh.faces].mean(axis=1)
    m = len(mesh.faces)
    c = optics.medium.attenuation
    bounds = (mesh.bounds + np.array([[-1e-3], [1e-3]])).astype(np.float32)
    sky = optics.sky
    pattern = _hemisphere(n_rays)
    albedo = rock_albedo(mesh, seed, optics.rock_colour)[mesh.faces].mean(axis=1)
    origin, facing, spread = _ray_origins(centre, normal, area)
    k = len(origin)
    table = np.zeros((m, 2, 6), np.float32)
    hit_face = np.empty((2, k, n_rays), np.int64)
    hit_side = np.empty((2, k, n_rays), np.int8)
    hit_dist = np.empty((2, k, n_rays), np.float32)
    enclosed = np.empty(k)
    direct = np.empty((k, 3))
    chunk = max(1, 1_000_000 // n_rays)
    rays = np.empty((chunk * n_rays, 6), np.float32)
    for side, sign in enumerate((1.0, -1.0)):
        n = sign * facing
        # A random tangent frame per origin, so the fixed ray pattern leaves no streaks.
        tangent = np.cross(n, rng.normal(size=(k, 3)))
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        for start in range(0, k, chunk):
            sl = slice(start, min(start + chunk, k))
            batch = rays[: (sl.stop - start) * n_rays]
            hemisphere_rays(origin[sl], n[sl], tangent[sl], pattern, 0.01, batch)
            out = caster.cast_raw_rays(batch)
            gather_sky(
                batch, out["t_hit"], out["primitive_ids"], out["primitive_normals"], bounds,
                c, sky, CREVICE_RADIUS_M, enclosed[sl], direct[sl], hit_face[side, sl],
                hit_side[side, sl], hit_dist[side, sl],
            )  # fmt: skip
        up = np.clip((sign * normal[:, 2] - 0.55) * 3.0, 0.0, 1.0)[:, None]  # silt on floors
        rho = albedo + up * (np.asarray(optics.sediment_colour) - albedo)
        rho *= spread(1.0 - 0.75 * enclosed**1.5)[:, None]  # crevices: light trapped, darker
        table[:, side, ALBEDO] = rho
        table[:, side, DAYLIGHT] = spread(direct)
    # One bounce: light from directly lit walls reaches walls around the corner.
    leaving = np.ascontiguousarray(table[..., ALBEDO] * table[..., DAYLIGHT])
    bounce = np.empty((k, 3), np.float32)
    for side in range(2):
        bounce_light(hit_face[side], hit_side[side], hit_dist[side], leaving, c, bounce)
        table[:, side, DAYLIGHT] += spread(bounce)
    return table


@dataclass(frozen=True)
class LampArrays:
    """The lamps as arrays for the kernels, in the camera frame (see `optics.Lamp`)."""

    position: np.ndarray  # (k, 3) float32
    axis: np.ndarray  # (k, 3) float32 unit
    power: np.ndarray  # (k, 3) float32: radiance of a white wall 1 m ahead, per channel
    profile: np.ndarray  # (k, CURVE_STEPS + 1) float32: each beam, `kernels.beam_profile`

    def __iter__(self):  # noqa: ANN204
        """The fields in the order the kernels take them."""
        return iter((self.position, self.axis, self.power, self.profile))


def lamp_arrays(optics: Optics) -> LampArrays:
    lamps = optics.fitted_lamps
    axis = np.array([lamp.axis for lamp in lamps], np.float64).reshape(-1, 3)
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    profile = [beam_profile(*lamp.exponents, lamp.hot_spot) for lamp in lamps]
    return LampArrays(
        position=np.array([lamp.position for lamp in lamps], np.float32).reshape(-1, 3),
        axis=axis.astype(np.float32),
        power=optics.lamp_power.reshape(-1, 3),
        profile=np.array(profile, np.float32).reshape(-1, kernels.CURVE_STEPS + 1),
    )


@dataclass(frozen=True)
class BackscatterTable:
    """Backscatter radiance B(pixel, planar depth), cumulative along each ray.

    values[gy, gx, j] is B at planar depth far * (j / bins)^2 for the block of pixels
    [gy * block, (gy + 1) * block) x [gx * block, (gx + 1) * block), integrated through
    its centre; beyond `far` the veil no longer grows. The veil changes by well under 1%
    from one block to the next, so a pixel takes its block's value.
    """

    values: np.ndarray  # (H / block, W / block, bins + 1, 3) float32
    block: int
    bins: int
    far: float


@lru_cache(maxsize=16)
def backscatter_table(
    camera: CameraIntrinsics, optics: Optics, block: int = 8, bins: int = 32, far: float = 40.0
) -> BackscatterTable:
    """Integrate the lamps' backscatter for a pixel grid every ``block`` pixels.

    Lamp light reaches the water it lights, and the light scattered back reaches the
    lens, through the water's kept attenuation (`Water.kept_attenuation`): what is
    scattered forward on either leg still arrives, and the veil is smooth enough that
    its blur does not show. The integral runs in 8 sub-steps per depth bin (about 0.2 s
    for 640x480, cached).
    """
    dirs = veil_directions(camera, block)
    lamps = lamp_arrays(optics)
    water = optics.medium
    out = np.zeros((len(dirs), bins + 1, 3), np.float32)
    integrate_backscatter(
        dirs,
        *lamps,
        np.asarray(water.scattering, np.float32),
        water.kept_attenuation,
        water.phase_g,
        far,
        bins,
        8,
        out,
    )
    rows, columns = -(-camera.height // block), -(-camera.width // block)
    return BackscatterTable(out.reshape(rows, columns, bins + 1, 3), block, bins, far)


def veil_directions(camera: CameraIntrinsics, block: int) -> np.ndarray:
    """(rows * columns, 3) float32 camera-frame directions (unit z) through the centres of
    the blocks of ``block`` pixels the veil's tables hold, row by row."""
    gx = (np.arange(-(-camera.width // block), dtype=np.float32) + 0.5) * block
    gy = (np.arange(-(-camera.height // block), dtype=np.float32) + 0.5) * block
    xx, yy = np.meshgrid(
        (gx - 0.5 * camera.width) / camera.focal_px, (gy - 0.5 * camera.height) / camera.focal_px
    )
    return np.stack([xx, yy, np.ones_like(xx)], axis=-1).reshape(-1, 3).astype(np.float32)

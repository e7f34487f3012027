"""Per-pixel kernels compiled with numba: everything after the ray cast.

The sensor step must cost little more than its ray cast (target: 1.5x). In numpy each
formula is a separate pass over 307,200 pixels with its temporaries; here a frame takes
three parallel kernels and a small serial one. `shade_grid` shades every fourth pixel of
every fourth row in full and meters the frame for the camera; `spread_halo` blurs the
light the water scatters forward there into its halo; `shade_frame` then reads each hit
once, takes the smooth part of its light from the grid (or shades it in full at edges),
takes it through the sensor (noise, gain) and writes the depth PNG; `develop_image`
filters the sensor's noise and writes the colour through the camera's curve. The model
is described in `cavenav.sensors.optics`.

Random numbers come from a counter-based hash (splitmix64) of a key and an index, so
every pixel and particle draws its own numbers in any thread order: bit-identical images
for the same seed and pose.
"""

from __future__ import annotations

import functools
import importlib
import math
import os
import threading
from collections.abc import Callable
from typing import Any

# Between kernels numba's OpenMP workers must sleep, not spin: spinning, they take the
# cores from Open3D's ray cast (its own TBB threads) that runs next. Measured on 2 cores:
# the forward cast inside the sensor step went from 34 to 28 ms. Read by libgomp when
# numba first loads it, so it is set before any kernel runs; a user's setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402
import numpy as np  # noqa: E402
from llvmlite import ir  # noqa: E402
from numba.core import types  # noqa: E402
from numba.extending import intrinsic  # noqa: E402
from numba.np.ufunc import parallel as numba_parallel  # noqa: E402

from cavenav.sensors.optics import LUMA, TONE_FLOOR, TONE_SHIFT  # noqa: E402

# OpenMP, else numba's own work queue; never TBB, whose old system builds only warn.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]  # type: ignore[attr-defined]

__all__ = [
    "KERNELS_RUN_CONCURRENTLY",
    "beam_profile",
    "bounce_light",
    "corner_sums",
    "develop_image",
    "fill_rays",
    "gather_sky",
    "hemisphere_rays",
    "integrate_backscatter",
    "integrate_silt",
    "mix",
    "photograph_rock_grid",
    "shade_frame",
    "shade_grid",
    "splat_particles",
    "spread_halo",
]

_NO_HIT = np.uint32(0xFFFFFFFF)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_INV_4PI = 1.0 / (4.0 * math.pi)
SHARE = 4  # shade_grid shades every SHARE-th pixel and row; shade_frame interpolates
# Fast-math without "no infinities": rays that escape carry t = inf.
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


def _launches_from_many_threads() -> bool:
    """Whether the threading layer Numba picks here lets several threads launch parallel
    kernels at once: OpenMP and TBB do; the work queue, Numba's fallback where OpenMP
    cannot be loaded (no libgomp, as in slim containers; macOS wheels), aborts the
    process.

    Found as Numba will choose, without starting its threads: once OpenMP's have started,
    a process forked from this one (Gymnasium's async vector environments, a default
    `multiprocessing.Pool`) is killed at its first parallel kernel, and importing this
    module must not do that.
    """
    if numba_parallel._is_initialized:
        return numba.threading_layer() != "workqueue"
    chosen = str(numba.config.THREADING_LAYER).lower()  # type: ignore[attr-defined]
    if chosen == "default":
        priority = numba.config.THREADING_LAYER_PRIORITY  # type: ignore[attr-defined]
        chosen = next(layer for layer in priority if layer == "workqueue" or _loads(layer))
    return chosen in ("omp", "tbb", "threadsafe", "safe")  # "forksafe" may be the queue


def _loads(layer: str) -> bool:
    """Whether Numba's ``layer`` ("omp" or "tbb") can be loaded here."""
    try:
        if layer == "tbb":
            numba_parallel._check_tbb_version_compatible()
        importlib.import_module(f"numba.np.ufunc.{layer}pool")
    except ImportError:
        return False
    return True


# Whether frames may be shaded on several threads at once (see `_parallel_kernel`).
KERNELS_RUN_CONCURRENTLY = _launches_from_many_threads()
_LAUNCHING = threading.Lock()
# A child forked while another thread held the lock would wait on it for ever.
os.register_at_fork(after_in_child=lambda: globals().update(_LAUNCHING=threading.Lock()))


def _parallel_kernel(
    function: Callable[..., Any], fastmath: bool | set[str] = _FAST
) -> Callable[..., Any]:
    """A kernel split over Numba's threads (``numba.prange``), compiled once and cached
    (with ``fastmath``'s liberties: False takes none).

    It lets go of the GIL, so that several frames are shaded at once, each on threads of
    its own: a batched environment's, a sweep's episodes in flight. Where the layer
    cannot take that (`KERNELS_RUN_CONCURRENTLY`), its launches take turns instead; the
    compiled kernel is then ``__wrapped__``.
    """
    kernel = numba.njit(parallel=True, fastmath=fastmath, cache=True, nogil=True)(function)
    if KERNELS_RUN_CONCURRENTLY:
        return kernel

    @functools.wraps(function)
    def in_turn(*args: Any) -> Any:  # noqa: ANN401 - the kernel's
        with _LAUNCHING:
            return kernel(*args)

    in_turn.__wrapped__ = kernel
    return in_turn


@numba.njit(inline="always")
def mix(x: np.uint64) -> np.uint64:
    """splitmix64's finaliser: a well-mixed 64-bit hash of ``x``."""
    x = (x ^ (x >> np.uint64(30))) * _M1
    x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


@numba.njit(inline="always")
def _gauss(h: np.uint64) -> float:
    """An approximately standard normal number from the four 16-bit quarters of ``h``."""
    mask = np.uint64(0xFFFF)
    total = (
        float(h & mask)
        + float((h >> np.uint64(16)) & mask)
        + float((h >> np.uint64(32)) & mask)
        + float(h >> np.uint64(48))
    )
    return (total / 65536.0 - 2.0) * 1.7320508


@numba.njit(inline="always")
def _uniform(h: np.uint64, shift: int) -> float:
    """A uniform deviate with zero mean and unit variance from 21 bits of ``h``."""
    bits = np.int64(h >> np.uint64(shift)) & 0x1FFFFF  # signed: one instruction to float
    return float(bits) * (3.4641016 / 2097152.0) - 1.7320508


@intrinsic
def _float_bits(typingctx, value):  # noqa: ANN001, ANN202
    """The IEEE-754 bit pattern of a float32, as an int32."""
    if value != types.float32:
        return None

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        return builder.bitcast(args[0], ir.IntType(32))

    return types.int32(types.float32), codegen


# Curves that the shading reads at a cosine, tabulated over [0, 1] in this many steps and
# read with linear interpolation: a lookup instead of a logarithm and two exponentials
# per lamp and pixel (error below 0.1% for the lamps' lobes and the glint's cos^60).
CURVE_STEPS = 1024


def beam_profile(wide: float, hot_exp: float, hot: float) -> np.ndarray:
    """(CURVE_STEPS + 1,) float32 a lamp's relative intensity at cosines 0, 1 / CURVE_STEPS,
    ..., 1 of the angle off its axis: a wide lobe cos^wide and a hot spot cos^hot_exp
    holding ``hot`` of the on-axis intensity (see `optics.Lamp`)."""
    cosine = np.linspace(0.0, 1.0, CURVE_STEPS + 1)
    return ((1.0 - hot) * cosine**wide + hot * cosine**hot_exp).astype(np.float32)


@numba.njit(inline="always")
def _curve(table: np.ndarray, k: int, cosine: float) -> float:
    """Row k of a (m, CURVE_STEPS + 1) table of a curve at ``cosine``; 0 at or below 0."""
    if cosine <= 0.0:
        return 0.0
    x = min(cosine, 1.0) * CURVE_STEPS
    j = min(int(x), CURVE_STEPS - 1)
    return table[k, j] + (x - j) * (table[k, j + 1] - table[k, j])


@numba.njit(inline="always")
def _spot(wx, wy, wz, d, axis, profile, k) -> float:  # noqa: ANN001
    """Lamp k's beam (its row of ``profile``) toward a point at offset (wx, wy, wz) =
    point - lamp, |w| = d."""
    return _curve(profile, k, (wx * axis[k, 0] + wy * axis[k, 1] + wz * axis[k, 2]) / d)


@numba.njit(inline="always")
def _veil(table: np.ndarray, row: int, col: int, depth: float, far: float):  # noqa: ANN202
    """Backscatter in front of depth ``depth`` from column (row, col) of a (h, w, bins + 1,
    3) table, linear over its square-root-spaced depths.

    Indexes the table directly: a view of the column would cost an atomic reference
    count per pixel, contended between threads.
    """
    bins = table.shape[2] - 1
    q = math.sqrt(min(depth, far) / far) * bins
    j = min(int(q), bins - 1)
    f = q - j
    return (
        table[row, col, j, 0] + f * (table[row, col, j + 1, 0] - table[row, col, j, 0]),
        table[row, col, j, 1] + f * (table[row, col, j + 1, 1] - table[row, col, j, 1]),
        table[row, col, j, 2] + f * (table[row, col, j + 1, 2] - table[row, col, j, 2]),
    )


@numba.njit(inline="always")
def _sky_shape(up: float) -> float:
    """Open water's brightness along a direction whose vertical component is ``up``:
    brightest toward the surface, a tenth of that looking into the deep."""
    return 0.1 + 0.9 * ((1.0 + up) * 0.5) ** 2.5


@numba.njit(inline="always")
def _smooth_normal(nx, ny, nz, u, v, a, b, c, vertex_normals):  # noqa: ANN001, ANN202
    """(smoothed, normal): vertex normals interpolated at (u, v), on face normal n's side.

    Falls back to the face normal where the corners disagree (a crease, or a mesh whose
    winding flips), so smoothing never turns a wall away from the light it faces.
    """
    w = 1.0 - u - v
    sx = w * vertex_normals[a, 0] + u * vertex_normals[b, 0] + v * vertex_normals[c, 0]
    sy = w * vertex_normals[a, 1] + u * vertex_normals[b, 1] + v * vertex_normals[c, 1]
    sz = w * vertex_normals[a, 2] + u * vertex_normals[b, 2] + v * vertex_normals[c, 2]
    length = math.sqrt(sx * sx + sy * sy + sz * sz)
    along = (sx * nx + sy * ny + sz * nz) / max(length, 1e-12)
    if abs(along) < 0.5:
        return False, nx, ny, nz
    scale = 1.0 / length if along > 0 else -1.0 / length
    return True, sx * scale, sy * scale, sz * scale


@numba.njit(inline="always")
def _leave(o: float, e: float, lo: float, hi: float) -> float:
    """Path length from o along unit component e to the slab [lo, hi] (inf if parallel)."""
    if e > 1e-9:
        return max((hi - o) / e, 0.0)
    if e < -1e-9:
        return max((lo - o) / e, 0.0)
    return np.inf


@numba.njit(inline="always")
def _scattered_toward(px, py, pz, path, vx, vy, vz, lamps, hg, g, attenuation, here) -> None:  # noqa: ANN001
    """Set ``here`` (3) to the lamps' light that a unit scattering coefficient at (px, py,
    pz) (camera frame, ``path`` metres from the lens) sends toward the lens along (vx,
    vy, vz): each lamp's beam there, by the Henyey-Greenstein phase (asymmetry g, ``hg``
    its factor), attenuated on its way out and back."""
    lamp_pos, lamp_axis, lamp_power, profile = lamps
    here[:] = 0.0
    for k in range(lamp_pos.shape[0]):
        wx, wy, wz = px - lamp_pos[k, 0], py - lamp_pos[k, 1], pz - lamp_pos[k, 2]
        d = max(math.sqrt(wx * wx + wy * wy + wz * wz), 1e-3)
        spot = _spot(wx, wy, wz, d, lamp_axis, profile, k)
        if spot <= 0.0:
            continue
        cos_theta = (wx * vx + wy * vy + wz * vz) / d  # light's path vs the view
        phase = hg / (1.0 + g * g - 2.0 * g * cos_theta) ** 1.5
        # The lamps' power is the radiance of a white wall at 1 m: intensity / pi.
        intensity = math.pi * spot * phase / (d * d)
        for c in range(3):
            here[c] += lamp_power[k, c] * intensity * math.exp(-attenuation[c] * (d + path))


@_parallel_kernel
def integrate_backscatter(
    dirs: np.ndarray,  # (n, 3) float32 camera-frame directions with unit z
    lamp_pos: np.ndarray,  # (k, 3) float32 camera frame
    lamp_axis: np.ndarray,  # (k, 3) float32 unit
    lamp_power: np.ndarray,  # (k, 3) per colour channel
    profile: np.ndarray,  # (k, CURVE_STEPS + 1) the beams, see beam_profile
    scattering: np.ndarray,  # (3,) 1/m
    attenuation: np.ndarray,  # (3,) 1/m
    g: float,  # Henyey-Greenstein asymmetry
    far: float,  # planar depth of the last bin
    bins: int,
    substeps: int,
    out: np.ndarray,  # (n, bins + 1, 3) float32: cumulative radiance at far * (j / bins)^2
) -> None:
    """Radiance the water scatters back toward the camera from the lamps' beams."""
    steps = bins * substeps
    hg = (1.0 - g * g) * _INV_4PI
    lamps = (lamp_pos, lamp_axis, lamp_power, profile)
    for i in numba.prange(dirs.shape[0]):
        ux, uy, uz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        length = math.sqrt(ux * ux + uy * uy + uz * uz)
        vx, vy, vz = -ux / length, -uy / length, -uz / length  # toward the camera
        acc = np.zeros(3)
        prev = np.zeros(3)
        here = np.zeros(3)
        s_prev = 0.0
        for m in range(steps + 1):
            s = far * (m / steps) ** 2
            _scattered_toward(s * ux, s * uy, s * uz, s * length, vx, vy, vz, lamps, hg, g, attenuation, here)  # fmt: skip  # noqa: E501
            for c in range(3):
                here[c] *= scattering[c]
            if m > 0:
                for c in range(3):
                    acc[c] += 0.5 * (prev[c] + here[c]) * (s - s_prev) * length
            if m % substeps == 0:
                for c in range(3):
                    out[i, m // substeps, c] = acc[c]
            prev[:] = here
            s_prev = s


@_parallel_kernel
def integrate_silt(
    dirs: np.ndarray,  # (n, 3) float32 camera-frame directions with unit z
    lamp_pos: np.ndarray,  # (k, 3) float32 camera frame
    lamp_axis: np.ndarray,  # (k, 3) float32 unit
    lamp_power: np.ndarray,  # (k, 3) per colour channel
    profile: np.ndarray,  # (k, CURVE_STEPS + 1) the beams, see beam_profile
    puffs: np.ndarray,  # (m, 5) float32 camera frame: x, y, z, sigma, grams
    scattering: np.ndarray,  # (3,) m^2/g
    extinction: np.ndarray,  # (3,) m^2/g, scattering plus absorption
    attenuation: np.ndarray,  # (3,) 1/m, the water's own (kept: Water.kept_attenuation)
    g: float,  # Henyey-Greenstein asymmetry of the silt
    far: float,  # planar depth of the last bin
    bins: int,
    substeps: int,
    veil: np.ndarray,  # (n, bins + 1, 3) float32 out: cumulative radiance, as the water's
    transmission: np.ndarray,  # (n, bins + 1, 3) float32 out: of light to depth and back
) -> None:
    """The lamps' light that silt puffs scatter back toward the camera, and how much of
    the rock's light they let through, at the backscatter table's depths.

    Silt of concentration C (g/m^3, the sum of the puffs' Gaussians) scatters b* C and
    takes e* C out of a beam per metre. Lamp light reaches a point at depth s through the
    silt before it (the lamps sit beside the lens, so their path is taken as the view's),
    scatters toward the lens, and comes back through it: the integrand is the water's
    backscatter integrand with b* C for the water's b, times exp(-2 tau(s)), tau the silt's
    optical depth to s. The rock at depth s is seen through exp(-2 tau(s)). A puff more
    than 4 sigma from a ray is left out of that ray; past the last puff it meets, a ray's
    figures stay as they are.
    """
    steps = bins * substeps
    hg = (1.0 - g * g) * _INV_4PI
    norm = 1.0 / (2.0 * math.pi) ** 1.5
    lamps = (lamp_pos, lamp_axis, lamp_power, profile)
    for i in numba.prange(dirs.shape[0]):
        ux, uy, uz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        length = math.sqrt(ux * ux + uy * uy + uz * uz)
        vx, vy, vz = -ux / length, -uy / length, -uz / length  # toward the camera
        near = np.empty(puffs.shape[0], np.int64)
        count = 0
        last = 0.0  # planar depth past which no puff this ray meets lies
        for m in range(puffs.shape[0]):
            cx, cy, cz, sigma = puffs[m, 0], puffs[m, 1], puffs[m, 2], puffs[m, 3]
            along = (cx * ux + cy * uy + cz * uz) / (length * length)  # planar depth
            ox, oy, oz = cx - along * ux, cy - along * uy, cz - along * uz
            if ox * ox + oy * oy + oz * oz < 16.0 * sigma * sigma and along > -4.0 * sigma:
                near[count] = m
                count += 1
                last = max(last, along + 4.0 * sigma / length)
        tau = np.zeros(3)
        acc = np.zeros(3)
        prev = np.zeros(3)
        here = np.zeros(3)
        prev_c = 0.0
        s_prev = 0.0
        for m in range(steps + 1):
            s = far * (m / steps) ** 2
            if count == 0 or s_prev > last:
                if m % substeps == 0:
                    for c in range(3):
                        veil[i, m // substeps, c] = acc[c]
                        transmission[i, m // substeps, c] = math.exp(-2.0 * tau[c])
                continue
            px, py, pz = s * ux, s * uy, s * uz
            conc = 0.0
            for q in range(count):
                p = near[q]
                sigma = puffs[p, 3]
                dx, dy, dz = px - puffs[p, 0], py - puffs[p, 1], pz - puffs[p, 2]
                r2 = (dx * dx + dy * dy + dz * dz) / (sigma * sigma)
                if r2 < 16.0:
                    conc += puffs[p, 4] * norm / (sigma * sigma * sigma) * math.exp(-0.5 * r2)
            if m > 0:
                for c in range(3):
                    tau[c] += 0.5 * (prev_c + conc) * extinction[c] * (s - s_prev) * length
            here[:] = 0.0
            if conc > 0.0:
                _scattered_toward(px, py, pz, s * length, vx, vy, vz, lamps, hg, g, attenuation, here)  # fmt: skip  # noqa: E501
                for c in range(3):
                    here[c] *= scattering[c] * conc * math.exp(-2.0 * tau[c])
            if m > 0:
                for c in range(3):
                    acc[c] += 0.5 * (prev[c] + here[c]) * (s - s_prev) * length
            if m % substeps == 0:
                for c in range(3):
                    veil[i, m // substeps, c] = acc[c]
                    transmission[i, m // substeps, c] = math.exp(-2.0 * tau[c])
            prev[:] = here
            prev_c = conc
            s_prev = s


@numba.njit(fastmath=_FAST, cache=True, nogil=True)
def splat_particles(
    origin: np.ndarray,  # (3,) camera position, world
    rotation: np.ndarray,  # (3, 3) camera-to-world, columns x right, y down, z forward
    lamp_pos: np.ndarray,  # (k, 3) world
    lamp_axis: np.ndarray,  # (k, 3) world, unit
    lamp_power: np.ndarray,  # (k, 3)
    profile: np.ndarray,  # (k, CURVE_STEPS + 1)
    attenuation: np.ndarray,  # (3,)
    density: float,  # particles per cubic metre
    seed: int,
    reach: float,  # metres; farther specks are too faint to matter
    focal_px: float,
    width: int,
    height: int,
    t: np.ndarray,  # (n,) planar depth of the scene, for occlusion
    specks: np.ndarray,  # (n, 3) float32 radiance, added to
    speck_blocks: np.ndarray,  # (ceil(H / SHARE), ceil(W / SHARE)) uint8: set where added
) -> int:
    """Add lamp-lit marine snow to ``specks``; returns the number of specks drawn.

    Drawn before the frame is shaded, so that `shade_frame` adds them in its one pass;
    ``speck_blocks`` marks the blocks of SHARE x SHARE pixels it needs to look at.

    Particles are fixed in the world (one hashed set per 1 m cell), so they show parallax
    as the vehicle moves. Near the lens they are out of focus: wide, faint discs.
    """
    drawn = 0
    key = mix(np.uint64(seed) + _GOLDEN)
    lo = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = int(math.floor(origin[a] - reach))
    span = int(math.ceil(2 * reach)) + 1
    whole = int(density)
    extra = density - whole
    for cx in range(lo[0], lo[0] + span):
        for cy in range(lo[1], lo[1] + span):
            for cz in range(lo[2], lo[2] + span):
                h = mix(key ^ np.uint64(cx + (1 << 20)))
                h = mix(h ^ np.uint64(cy + (1 << 20)))
                h = mix(h ^ np.uint64(cz + (1 << 20)))
                count = whole + (1 if float(h >> np.uint64(11)) * 2.0**-53 < extra else 0)
                for _ in range(count):
                    h = mix(h + _GOLDEN)
                    qx = cx + float(h & np.uint64(0x1FFFFF)) * 2.0**-21
                    qy = cy + float((h >> np.uint64(21)) & np.uint64(0x1FFFFF)) * 2.0**-21
                    qz = cz + float(h >> np.uint64(42)) * 2.0**-22
                    wx, wy, wz = qx - origin[0], qy - origin[1], qz - origin[2]
                    z = wx * rotation[0, 2] + wy * rotation[1, 2] + wz * rotation[2, 2]
                    if z < 0.08 or z > reach:
                        continue
                    x = wx * rotation[0, 0] + wy * rotation[1, 0] + wz * rotation[2, 0]
                    y = wx * rotation[0, 1] + wy * rotation[1, 1] + wz * rotation[2, 1]
                    u = focal_px * x / z + 0.5 * width
                    v = focal_px * y / z + 0.5 * height
                    size = 0.0005 + 0.002 * float(mix(h) >> np.uint64(11)) * 2.0**-53
                    size_px = focal_px * size / z
                    blur_px = focal_px * 0.004 * abs(1.0 / z - 0.5)  # 4 mm aperture, focus 2 m
                    radius = max(0.6, 0.5 * (blur_px + size_px))
                    if u < -radius or u > width + radius or v < -radius or v > height + radius:
                        continue
                    path = math.sqrt(wx * wx + wy * wy + wz * wz)
                    lit = np.zeros(3)
                    for k in range(lamp_pos.shape[0]):
                        lx = qx - lamp_pos[k, 0]
                        ly = qy - lamp_pos[k, 1]
                        lz = qz - lamp_pos[k, 2]
                        d = math.sqrt(lx * lx + ly * ly + lz * lz)
                        spot = _spot(lx, ly, lz, d, lamp_axis, profile, k)
                        if spot > 0.0:
                            for c in range(3):
                                lit[c] += (
                                    lamp_power[k, c]
                                    * spot
                                    / (d * d)
                                    * math.exp(-attenuation[c] * d)
                                )
                    # The speck's light spread over its disc of confusion.
                    amplitude = 0.6 * min(1.0, (0.5 * size_px) ** 2 / (radius * radius))
                    x0, x1 = max(int(u - radius), 0), min(int(u + radius) + 1, width - 1)
                    y0, y1 = max(int(v - radius), 0), min(int(v + radius) + 1, height - 1)
                    any_pixel = False
                    for py in range(y0, y1 + 1):
                        for px in range(x0, x1 + 1):
                            i = py * width + px
                            if t[i] <= z:
                                continue  # behind the wall
                            dist = math.hypot(px + 0.5 - u, py + 0.5 - v)
                            weight = min(max(radius + 0.5 - dist, 0.0), 1.0)
                            if weight <= 0.0:
                                continue
                            any_pixel = True
                            speck_blocks[py // SHARE, px // SHARE] = 1
                            for c in range(3):
                                specks[i, c] += (
                                    amplitude * weight * lit[c] * math.exp(-attenuation[c] * path)
                                )
                    drawn += any_pixel
    return drawn


SHININESS = 60.0  # Blinn-Phong exponent of wet rock: highlights some 10 degrees wide
_GLINT = (np.linspace(0.0, 1.0, CURVE_STEPS + 1) ** SHININESS).astype(np.float32)[None, :]


@numba.njit(inline="always")
def _surface_light(i, tri, r, hit, d, n, uvs, faces, vertex_normals, surface, surface_at, lamps, gloss, c, kept):  # fmt: skip  # noqa: ANN001, ANN202, E501
    """Light from rock hit by pixel i reaching the camera, before the photographed rock:
    (R, G, B straight, R, G, B scattered forward, green lamp light returned). r is the
    path length to the hit point ``hit`` (3 floats), ``d`` the ray's direction (3
    floats), ``n`` the hit triangle's normal, ``gloss`` the rock's specular reflectance,
    ``c`` the water's beam attenuation and ``kept`` what is left of it (k) when light
    scattered by a few degrees is counted as kept (`optics.Water.kept_attenuation`),
    each (3).

    The lamps' light reaches the rock through k: what the water scatters forward still
    lands about the spot. On the way back, exp(-c r) of the rock's light comes straight
    and exp(-k r) - exp(-c r) comes scattered forward, which `shade_grid` collects and
    the rig spreads into a halo (forward scatter's blur).

    Diffuse light takes the rock's colour; the wet surface's specular reflection
    (normalised Blinn-Phong, `SHININESS`) keeps the lamps' colour, and at arm's length
    can clip. The lamps are within 0.25 m of the camera, so each lamp's path differs
    from the camera's by a short delta, and exp(-c d_k) = exp(-c r) exp(-c delta) takes a
    second-order series for the second factor (error below 1% for c * delta < 0.35):
    three exponentials per pixel instead of nine.
    """
    hx, hy, hz = hit
    dx, dy, dz = d
    nx, ny, nz = n
    c0, c1, c2 = c
    k0, k1, k2 = kept
    lamp_pos, lamp_axis, lamp_power, profile = lamps
    side = 0
    if nx * dx + ny * dy + nz * dz > 0.0:  # the camera sees the triangle's back
        side = 1
        nx, ny, nz = -nx, -ny, -nz
    # Scalars only: views (faces[tri], surface[tri, side]) would cost atomic reference
    # counts in this hottest of paths.
    a, b, cc = faces[tri, 0], faces[tri, 1], faces[tri, 2]
    u, v = uvs[i, 0], uvs[i, 1]
    w = 1.0 - u - v
    smooth, nx, ny, nz = _smooth_normal(nx, ny, nz, u, v, a, b, cc, vertex_normals)
    if smooth:  # surface properties, too, blend smoothly across the triangle
        r0 = w * surface_at[a, side, 0] + u * surface_at[b, side, 0] + v * surface_at[cc, side, 0]
        r1 = w * surface_at[a, side, 1] + u * surface_at[b, side, 1] + v * surface_at[cc, side, 1]
        r2 = w * surface_at[a, side, 2] + u * surface_at[b, side, 2] + v * surface_at[cc, side, 2]
        r3 = w * surface_at[a, side, 3] + u * surface_at[b, side, 3] + v * surface_at[cc, side, 3]
        r4 = w * surface_at[a, side, 4] + u * surface_at[b, side, 4] + v * surface_at[cc, side, 4]
        r5 = w * surface_at[a, side, 5] + u * surface_at[b, side, 5] + v * surface_at[cc, side, 5]
    else:
        r0, r1, r2 = surface[tri, side, 0], surface[tri, side, 1], surface[tri, side, 2]
        r3, r4, r5 = surface[tri, side, 3], surface[tri, side, 4], surface[tri, side, 5]
    inv_view = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
    vx, vy, vz = -dx * inv_view, -dy * inv_view, -dz * inv_view  # toward the camera
    peak = gloss * (SHININESS + 8.0) / 8.0
    e0 = e1 = e2 = s0 = s1 = s2 = 0.0
    for k in range(lamp_pos.shape[0]):
        wx = lamp_pos[k, 0] - hx
        wy = lamp_pos[k, 1] - hy
        wz = lamp_pos[k, 2] - hz
        d2 = max(wx * wx + wy * wy + wz * wz, 0.01)
        inv_d = 1.0 / math.sqrt(d2)
        cos_in = (nx * wx + ny * wy + nz * wz) * inv_d
        if cos_in <= 0.0:
            continue  # the lamp is behind this face
        cos_axis = -(wx * lamp_axis[k, 0] + wy * lamp_axis[k, 1] + wz * lamp_axis[k, 2]) * inv_d
        spot = _curve(profile, k, cos_axis)
        if spot <= 0.0:
            continue
        e = spot * cos_in / d2
        delta = d2 * inv_d - r
        x0, x1, x2 = k0 * delta, k1 * delta, k2 * delta
        f0 = e * lamp_power[k, 0] * (1.0 - x0 + 0.5 * x0 * x0)
        f1 = e * lamp_power[k, 1] * (1.0 - x1 + 0.5 * x1 * x1)
        f2 = e * lamp_power[k, 2] * (1.0 - x2 + 0.5 * x2 * x2)
        e0, e1, e2 = e0 + f0, e1 + f1, e2 + f2
        if peak > 0.0:  # the half-way vector between the lamp and the camera
            qx, qy, qz = wx * inv_d + vx, wy * inv_d + vy, wz * inv_d + vz
            q2 = qx * qx + qy * qy + qz * qz
            cos_h = (nx * qx + ny * qy + nz * qz) / math.sqrt(max(q2, 1e-12))
            glint = peak * _curve(_GLINT, 0, cos_h)
            s0, s1, s2 = s0 + glint * f0, s1 + glint * f1, s2 + glint * f2
    t0, t1, t2 = math.exp(-c0 * r), math.exp(-c1 * r), math.exp(-c2 * r)
    # exp(-k r) = exp(-c r) exp((c - k) r), and c - k (scattering kept forward) is about
    # the same in every channel: one exponential, and a second-order series for the
    # others' small difference x (error x^3 / 6: below 1e-4 within 10 m in the cave
    # presets; in the muddiest Jerlov water 1% at 1 m, 6% at 2 m, where little light is
    # left). The exponent stops at 80, where exp(-c r) has long underflowed: float32
    # overflows at 88, and inf x 0 is NaN.
    regained = math.exp(min((c1 - k1) * r, 80.0))
    x0, x2 = (c0 - k0 - c1 + k1) * r, (c2 - k2 - c1 + k1) * r
    u0 = t0 * regained * (1.0 + x0 + 0.5 * x0 * x0)
    u1 = t1 * regained
    u2 = t2 * regained * (1.0 + x2 + 0.5 * x2 * x2)
    out0 = r0 * (e0 * u0 + r3) + s0 * u0  # leaving the rock toward the camera
    out1 = r1 * (e1 * u1 + r4) + s1 * u1
    out2 = r2 * (e2 * u2 + r5) + s2 * u2
    return (
        out0 * t0, out1 * t1, out2 * t2,
        out0 * (u0 - t0), out1 * (u1 - t1), out2 * (u2 - t2),
        r1 * e1 * u1 * t1,
    )  # fmt: skip


# Photographed rock (`lighting.rock_photographs`, `photographed_rock`): its luminance,
# relative to its mean, is the rock's albedo at the millimetre-to-decimetre scale, and
# read as a height (pale rock standing out, dark cracks and pits sunk in; RELIEF_M per
# unit) it turns the rock toward or away from the lamps. Depth and collisions keep the
# mesh's own surface.
RELIEF_M = 0.008
_PHOTO_SHIFT = 4194304.0  # 2^22 texels: coordinates positive, so truncation is floor


@numba.njit(inline="always")
def _photo_sample(texels, start, size, u, v):  # noqa: ANN001, ANN202
    """(value, d/du, d/dv) of one square level of a photograph at texel coordinates
    (u, v), bilinear, wrapping (the photographs tile seamlessly)."""
    mask = size - 1
    u += _PHOTO_SHIFT
    v += _PHOTO_SHIFT
    iu, iv = int(u), int(v)
    fu, fv = u - iu, v - iv
    row0 = start + (iv & mask) * size
    row1 = start + ((iv + 1) & mask) * size
    i0, i1 = iu & mask, (iu + 1) & mask
    t00, t01 = float(texels[row0 + i0]), float(texels[row0 + i1])
    t10, t11 = float(texels[row1 + i0]), float(texels[row1 + i1])
    top, bottom = t00 + fu * (t01 - t00), t10 + fu * (t11 - t10)
    return top + fv * (bottom - top), (t01 - t00) + fv * (t11 - t10 - t01 + t00), bottom - top


@numba.njit(inline="always")
def photographed_rock(texels, offsets, sizes, units, per_texel, hit, n, toward_lamps, footprint):  # fmt: skip  # noqa: ANN001, ANN201, E501
    """The photographed rock's factor on the smooth rock's light at ``hit`` (3 floats,
    world), facing ``n`` (unit), lit from the unit direction ``toward_lamps``: its
    relative albedo there, times how its relief turns the surface toward the lamps or
    away. The photographs are `lighting.RockPhotographs` (its `as_tuple`, spread).

    ``footprint`` is the pixel's width on the rock, metres: the mip level whose texels
    are half as wide to as wide is read, so that distant rock averages its detail
    rather than aliasing it (found from the float's exponent: no logarithm, no loop).
    The photograph is projected along the axis the rock faces most (one read a pixel,
    and no stretching beyond the 1.4x of a surface at 45 degrees): walls, facing x or
    y, show the bedded photograph with its strata level and continuous from one plane
    to the other; floors and ceilings the plain one, which changes where the rock turns
    from wall to floor.
    """
    hx, hy, hz = hit
    nx, ny, nz = n
    reach = np.float32(max(footprint * per_texel, 1.0))  # finest texels a pixel spans
    exponent = (np.int64(_float_bits(reach)) >> 23) - 127
    level = min(exponent, sizes.shape[0] - 1)
    size = sizes[level]
    scale = per_texel * size / sizes[0]  # texels a metre at this level
    ax, ay, az = abs(nx), abs(ny), abs(nz)
    if az >= ax and az >= ay:  # floors and ceilings
        unit = units[1]
        value, du, dv = _photo_sample(texels, offsets[1, level], size, hx * scale, hy * scale)
        gx, gy, gz = du, dv, 0.0
    else:  # walls: the same strata (v) on both planes, the x plane's shifted along
        unit = units[0]
        u = hy * scale + 0.5 * size if ax >= ay else hx * scale
        value, du, dv = _photo_sample(texels, offsets[0, level], size, u, -hz * scale)
        gx, gy, gz = (0.0, du, -dv) if ax >= ay else (du, 0.0, -dv)
    albedo = unit * value
    rise = RELIEF_M * scale * unit  # the relief's slope, metres per metre, per unit
    gx, gy, gz = rise * gx, rise * gy, rise * gz
    # To first order in the slope, the relief's normal is n minus the slope's part along
    # the surface, and the light it gathers changes by that part's pull toward the
    # lamps: none where they face the rock head-on, most where they graze it. Left
    # unnormalised, it keeps the rock's mean tone: bumps turn as much toward as away.
    lx, ly, lz = toward_lamps
    flat = nx * lx + ny * ly + nz * lz
    along = gx * nx + gy * ny + gz * nz
    pull = (gx - along * nx) * lx + (gy - along * ny) * ly + (gz - along * nz) * lz
    turned = max(flat - pull, 0.0) / max(flat, 0.2)
    return albedo * min(turned, 3.0)


@numba.njit(inline="always")
def _open_water(ox, oy, oz, ex, ey, ez, sky, bounds, c0, c1, c2):  # noqa: ANN001, ANN202
    """Open water beyond the cave along a ray from (ox, oy, oz) in unit direction
    (ex, ey, ez) that escapes it, dimmed by the water up to the cave's bounding box."""
    r_exit = min(_leave(ox, ex, bounds[0, 0], bounds[1, 0]),
                 _leave(oy, ey, bounds[0, 1], bounds[1, 1]),
                 _leave(oz, ez, bounds[0, 2], bounds[1, 2]))  # fmt: skip
    shape = _sky_shape(ez)
    return (
        sky[0] * shape * math.exp(-c0 * r_exit),
        sky[1] * shape * math.exp(-c1 * r_exit),
        sky[2] * shape * math.exp(-c2 * r_exit),
    )


@numba.njit(inline="always")
def _lens(length: float, vignetting: float) -> float:
    """Vignetting of a pixel whose ray is ``length`` long per unit depth: cos^4 law."""
    cos2 = 1.0 / (length * length)
    return 1.0 - vignetting * (1.0 - cos2 * cos2)


@numba.njit(inline="always")
def _tone(lut: np.ndarray, value: float) -> np.uint8:
    """The tone curve (see `optics.tone_lut`) at a linear value; NaN and negatives are black.

    Indexed by the float's own bits: no square root or logarithm per channel.
    """
    bits = np.int64(_float_bits(np.float32(value if value > 0.0 else 0.0)))  # type: ignore[call-arg]
    return lut[min(max((bits >> TONE_SHIFT) - TONE_FLOOR, 0), lut.shape[0] - 1)]


@numba.njit(inline="always")
def _own_light(i, row, col, cast, rays, scene, lamps, water):  # noqa: ANN001, ANN202
    """Radiance reaching the lens along pixel i's ray, before marine snow and the
    photographed rock: (R, G, B straight, with the veil; R, G, B scattered forward, for
    the halo; green lamp light returned by the rock, 0 for open water; R, G, B of the
    straight light that is the rock's own, which the photographed rock multiplies)."""
    t, triangle, normals, uvs = cast
    directions, ray_length, origin = rays
    faces, vertex_normals, surface, surface_at, specular = scene[:5]
    attenuation, kept, backscatter, block, far, sky, bounds, silt_veil, silt_light = water
    c0, c1, c2 = attenuation[0], attenuation[1], attenuation[2]
    k0, k1, k2 = kept[0], kept[1], kept[2]
    depth = t[i]
    length = ray_length[i]
    dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
    v0, v1, v2 = _veil(backscatter, row // block, col // block, depth, far)
    if triangle[i] == _NO_HIT:
        ex, ey, ez = dx / length, dy / length, dz / length
        o0, o1, o2 = _open_water(
            origin[0], origin[1], origin[2], ex, ey, ez, sky, bounds, c0, c1, c2
        )
        a0, a1, a2 = _open_water(
            origin[0], origin[1], origin[2], ex, ey, ez, sky, bounds, k0, k1, k2
        )
        h0, h1, h2 = a0 - o0, a1 - o1, a2 - o2
        lamp_return = 0.0
        rock = 0.0
    else:
        hit = (origin[0] + depth * dx, origin[1] + depth * dy, origin[2] + depth * dz)
        o0, o1, o2, h0, h1, h2, lamp_return = _surface_light(
            i, triangle[i], depth * length, hit, (dx, dy, dz),
            (normals[i, 0], normals[i, 1], normals[i, 2]), uvs, faces, vertex_normals,
            surface, surface_at, lamps, specular, (c0, c1, c2), (k0, k1, k2),
        )  # fmt: skip
        rock = 1.0
    if silt_veil.shape[0] > 1:  # silt hangs in the water: a table as large as the veil's
        s0, s1, s2 = _veil(silt_veil, row // block, col // block, depth, far)
        t0, t1, t2 = _veil(silt_light, row // block, col // block, depth, far)
        o0, o1, o2 = t0 * o0, t1 * o1, t2 * o2
        v0, v1, v2 = v0 + s0, v1 + s1, v2 + s2
        h0, h1, h2, lamp_return = t0 * h0, t1 * h1, t2 * h2, t1 * lamp_return
    return (
        v0 + o0, v1 + o1, v2 + o2, h0, h1, h2, lamp_return, rock * o0, rock * o1, rock * o2,
    )  # fmt: skip


@numba.njit(inline="always")
def _photo_at(i, nx, ny, nz, cast, rays, scene, spacing):  # noqa: ANN001, ANN202
    """`photographed_rock` for the rock pixel i sees, its surface facing (nx, ny, nz)
    (unit; either side), read at the footprint of ``spacing`` pixels.

    Its relief is lit from the camera: the lamps of an ROV flank the camera
    symmetrically, a few decimetres apart, so the mean of their directions to rock a
    metre or more away is the camera's within a few degrees.
    """
    t = cast[0]
    directions, ray_length, origin = rays
    focal_px = scene[5]
    depth = t[i]
    length = ray_length[i]
    dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
    inv_length = 1.0 / length
    facing = -(nx * dx + ny * dy + nz * dz) * inv_length
    side = 1.0
    if facing < 0.0:  # the side the camera sees
        side, facing = -1.0, -facing
    return photographed_rock(
        scene[6], scene[7], scene[8], scene[9], scene[10],
        (origin[0] + depth * dx, origin[1] + depth * dy, origin[2] + depth * dz),
        (side * nx, side * ny, side * nz),
        (-dx * inv_length, -dy * inv_length, -dz * inv_length),
        spacing * depth * length / (focal_px * max(facing, 0.25)),
    )  # fmt: skip


PHOTO_SHARE = 2  # photograph_rock_grid reads the photographed rock every PHOTO_SHARE pixels


@_parallel_kernel
def photograph_rock_grid(
    cast: tuple,  # (t, triangle, normals, uvs) as in shade_frame
    rays: tuple,  # (directions, ray_length, origin) as in shade_frame
    scene: tuple,  # as in shade_frame
    width: int,
    photo: np.ndarray,  # (ceil(H / PHOTO_SHARE) + 1, ceil(W / PHOTO_SHARE) + 1, 1) float32 out
) -> None:
    """The photographed rock's factor (`photographed_rock`) at every PHOTO_SHARE-th pixel
    of every PHOTO_SHARE-th row (and the last ones), 1 where a ray escapes; `shade_frame`
    interpolates it between them.

    Read at the footprint of PHOTO_SHARE pixels, the photographs' detail is as fine as
    these points can carry without aliasing: two pixels, the scale at which a frame's
    structure is measured (`cavenav.sensors.image_stats`), at a quarter of the cost of
    reading them at every pixel (the sensor step's budget; `benchmarks/sensor_step.py`).
    The triangle's own normal picks the plane and tilts the relief: the smooth normal
    would cost a third more, for a difference only where the rock turns through 45
    degrees.
    """
    t, triangle, normals, _ = cast
    height = t.shape[0] // width
    for a in numba.prange(photo.shape[0]):
        row = min(a * PHOTO_SHARE, height - 1)
        for b in range(photo.shape[1]):
            col = min(b * PHOTO_SHARE, width - 1)
            i = row * width + col
            if triangle[i] == _NO_HIT:
                photo[a, b, 0] = 1.0
                continue
            nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
            photo[a, b, 0] = _photo_at(i, nx, ny, nz, cast, rays, scene, PHOTO_SHARE)


@_parallel_kernel
def shade_grid(
    cast: tuple,  # (t, triangle, normals, uvs) as in shade_frame
    rays: tuple,  # (directions, ray_length, origin) as in shade_frame
    scene: tuple,  # (faces, vertex_normals, surface, surface_at, specular, focal px, *photos)
    lamps: tuple,  # (position, axis, power (k, 3), beam profile) world frame
    water: tuple,  # see shade_frame
    specks: np.ndarray,  # (n, 3) float32 marine snow, see splat_particles
    speck_blocks: np.ndarray,  # (ceil(H / SHARE), ceil(W / SHARE)) uint8
    vignetting: float,
    width: int,
    grid: np.ndarray,  # (H', W', 11) float32 out, H' = ceil(H / SHARE) + 1, likewise W'
    grid_triangle: np.ndarray,  # (H', W') uint32 out: the triangle hit at each point
    halo: np.ndarray,  # (H', W', 3) float32 out: light scattered forward, per grid point
    row_sums: np.ndarray,  # (H', 3) float64 out: each grid row's colour at the sensor, summed
) -> None:
    """Shade the pixels of every SHARE-th row and column (and the last ones) into ``grid``,
    and sum each row's colour at the sensor into ``row_sums``.

    Per grid point: 1 / depth (-1 where the ray escapes), the normal the rock is shaded
    with (the vertex normals smoothed across the triangle, `_smooth_normal`), the
    radiance reaching the lens straight (RGB: the smooth rock, and the veil in front of
    it), the green lamp light the rock returns, and the part of the straight radiance
    that is the rock's own (RGB), which `shade_frame` multiplies per pixel by the
    photographed rock; and in ``halo`` the light scattered
    forward on its way, which the rig blurs (`spread_halo`) for `shade_frame` to add.
    `shade_frame` interpolates between these wherever a pixel lies on the same smooth
    surface as the four around it. The mean, halo included, is what the camera meters
    for its auto white balance and exposure before the frame is developed
    (`grid_mean`). Rows are summed one by one, each on one thread, so that the mean
    does not depend on how many threads shaded them.
    """
    t, triangle, normals, uvs = cast
    faces, vertex_normals = scene[0], scene[1]
    ray_length = rays[1]
    height = t.shape[0] // width
    for a in numba.prange(grid.shape[0]):
        row = min(a * SHARE, height - 1)
        sum0 = sum1 = sum2 = 0.0
        for b in range(grid.shape[1]):
            col = min(b * SHARE, width - 1)
            i = row * width + col
            l0, l1, l2, h0, h1, h2, lamp_return, r0, r1, r2 = _own_light(
                i, row, col, cast, rays, scene, lamps, water
            )
            halo[a, b, 0], halo[a, b, 1], halo[a, b, 2] = h0, h1, h2
            grid_triangle[a, b] = triangle[i]
            if triangle[i] == _NO_HIT:
                grid[a, b, 0] = -1.0
            else:
                grid[a, b, 0] = 1.0 / t[i]
                tri = triangle[i]
                _, nx, ny, nz = _smooth_normal(
                    normals[i, 0], normals[i, 1], normals[i, 2], uvs[i, 0], uvs[i, 1],
                    faces[tri, 0], faces[tri, 1], faces[tri, 2], vertex_normals,
                )  # fmt: skip
                grid[a, b, 1], grid[a, b, 2], grid[a, b, 3] = nx, ny, nz
                grid[a, b, 4], grid[a, b, 5], grid[a, b, 6] = l0, l1, l2
                grid[a, b, 7] = lamp_return
                grid[a, b, 8], grid[a, b, 9], grid[a, b, 10] = r0, r1, r2
            if speck_blocks[row // SHARE, col // SHARE]:
                l0, l1, l2 = l0 + specks[i, 0], l1 + specks[i, 1], l2 + specks[i, 2]
            lens = _lens(ray_length[i], vignetting)
            sum0 += (l0 + h0) * lens
            sum1 += (l1 + h1) * lens
            sum2 += (l2 + h2) * lens
        row_sums[a, 0], row_sums[a, 1], row_sums[a, 2] = sum0, sum1, sum2


SAME_FACING = 0.9  # cosine of the largest angle between normals of one smooth surface


@numba.njit(inline="always")
def _smooth_cell(grid, a, b) -> bool:  # noqa: ANN001
    """Whether the four grid points (a, b) to (a + 1, b + 1) are rock facing one way."""
    if grid[a, b, 0] <= 0.0:
        return False
    nx, ny, nz = grid[a, b, 1], grid[a, b, 2], grid[a, b, 3]
    for p, q in ((a, b + 1), (a + 1, b), (a + 1, b + 1)):
        if grid[p, q, 0] <= 0.0:
            return False
        if grid[p, q, 1] * nx + grid[p, q, 2] * ny + grid[p, q, 3] * nz < SAME_FACING:
            return False
    return True


# The channels of shade_grid's grid that shade_frame interpolates: 1 / depth, the straight
# light (RGB), the lamps' green light returned, the rock's own light (RGB).
_BLENDED = (0, 4, 5, 6, 7, 8, 9, 10)


@numba.njit(inline="always")
def _down_to_row(grid, a, fy) -> np.ndarray:  # noqa: ANN001
    """(W', 8) float64: the `_BLENDED` channels of grid rows a and a + 1, blended the
    fraction ``fy`` of the way down: a pixel row's values at the grid's columns."""
    blended = np.empty((grid.shape[1], len(_BLENDED)))
    for b in range(grid.shape[1]):
        for k in range(len(_BLENDED)):
            upper = grid[a, b, _BLENDED[k]]
            blended[b, k] = upper + fy * (grid[a + 1, b, _BLENDED[k]] - upper)
    return blended


@numba.njit(inline="always")
def _across(at_row, b, k, fx) -> float:  # noqa: ANN001
    """Channel k of ``at_row`` (`_down_to_row`) the fraction ``fx`` of the way from grid
    column b to b + 1."""
    return at_row[b, k] + fx * (at_row[b + 1, k] - at_row[b, k])


@numba.njit(inline="always")
def _photo_down_to_row(photo, row) -> np.ndarray:  # noqa: ANN001
    """(W'',) float64: `photograph_rock_grid`'s points blended down to pixel ``row``."""
    y0 = row // PHOTO_SHARE
    fy = (row - y0 * PHOTO_SHARE) / PHOTO_SHARE
    y1 = min(y0 + 1, photo.shape[0] - 1)
    blended = np.empty(photo.shape[1])
    for x in range(photo.shape[1]):
        blended[x] = photo[y0, x, 0] + fy * (photo[y1, x, 0] - photo[y0, x, 0])
    return blended


@numba.njit(inline="always")
def _photo_across(photo_row, col) -> float:  # noqa: ANN001
    """The photographed rock's factor at pixel ``col`` of the row of ``photo_row``."""
    x0 = col // PHOTO_SHARE
    fx = (col - x0 * PHOTO_SHARE) / PHOTO_SHARE
    x1 = min(x0 + 1, photo_row.shape[0] - 1)
    return photo_row[x0] + fx * (photo_row[x1] - photo_row[x0])


@numba.njit(inline="always")
def _finish(i, l0, l1, l2, lamp_return, hit, col, t, frame_key, depth_range, row_light, depth_png):  # fmt: skip  # noqa: ANN001, E501
    """Pixel i's depth degradation and depth PNG, once its light is known; the light goes
    to ``row_light`` for the camera."""
    d_min, d_max, depth_dropout, depth_noise = depth_range
    depth = t[i]
    if hit:
        if depth_dropout > 0.0 and lamp_return < depth_dropout:
            depth = np.inf  # too little of the lamps' light came back
            t[i] = depth
        elif depth_noise > 0.0:
            depth = _noisy_depth(i, depth, t.shape[0], frame_key, depth_noise)
            t[i] = depth
    depth_png[i] = _depth_level(depth, d_min, d_max)
    row_light[col, 0], row_light[col, 1], row_light[col, 2] = l0, l1, l2


@numba.njit(inline="always")
def _noisy_depth(i, depth, n, frame_key, depth_noise):  # noqa: ANN001, ANN202
    """Pixel i's ``depth`` (of a frame of ``n`` pixels) with the depth camera's noise,
    which grows as the square of the range, seeded by the frame and the pixel."""
    if depth_noise > 0.0:
        h = mix(frame_key ^ np.uint64(n + i))
        depth = max(depth + depth_noise * (depth / 10.0) ** 2 * _gauss(h), 0.0)
    return depth


@numba.njit(inline="always")
def _depth_level(depth, d_min, d_max):  # noqa: ANN001, ANN202
    """The depth PNG's 8-bit level of ``depth``: d_min black, d_max and beyond white."""
    level = (min(depth, d_max) - d_min) * (255.0 / (d_max - d_min))
    return np.uint8(min(max(level, 0.0), 255.0) + 0.5)


@_parallel_kernel
def spread_halo(
    halo: np.ndarray,  # (H', W', 3) float32: forward-scattered light at the grid's points
    cell: int,  # grid points a side of the cells the blur works on
    weights: np.ndarray,  # (2 r + 1,) the blur's 1-D Gaussian over cells
    grid: np.ndarray,  # (H', W', 8) float32: shade_grid's, its light (4-6) updated here
) -> None:
    """Blur forward scatter's light into its halo and write it back to ``halo``, and add
    it to the light of ``grid``'s points, so that pixels interpolated from the grid
    carry it (`shade_frame` adds it to the others itself).

    The light is averaged over cells of ``cell`` x ``cell`` points (the blur is some 45
    pixels wide at 640x480: detail finer than a cell does not survive it), blurred by
    ``weights`` along both axes (edges repeated), and interpolated back to the points
    bilinearly, cell centres at cell (j + 1/2) - 1/2.
    """
    rows, columns = halo.shape[0], halo.shape[1]
    tall, wide = -(-rows // cell), -(-columns // cell)
    coarse = np.zeros((tall, wide, 3))
    for a in range(tall * cell):
        for b in range(wide * cell):
            src_a, src_b = min(a, rows - 1), min(b, columns - 1)
            for c in range(3):
                coarse[a // cell, b // cell, c] += halo[src_a, src_b, c]
    coarse /= cell * cell
    radius = weights.shape[0] // 2
    for axis in range(2):
        blurred = np.zeros_like(coarse)
        for j in range(tall):
            for k in range(wide):
                for t in range(-radius, radius + 1):
                    if axis == 0:
                        jj, kk = min(max(j + t, 0), tall - 1), k
                    else:
                        jj, kk = j, min(max(k + t, 0), wide - 1)
                    for c in range(3):
                        blurred[j, k, c] += weights[t + radius] * coarse[jj, kk, c]
        coarse = blurred
    centre = (cell - 1) / 2.0
    for a in numba.prange(rows):  # each point its own: the same on any number of threads
        y = min(max((a - centre) / cell, 0.0), tall - 1.0)
        y0 = int(y)
        y1, fy = min(y0 + 1, tall - 1), y - y0
        for b in range(columns):
            x = min(max((b - centre) / cell, 0.0), wide - 1.0)
            x0 = int(x)
            x1, fx = min(x0 + 1, wide - 1), x - x0
            for c in range(3):
                value = _bilinear(coarse, y0, y1, fy, x0, x1, fx, c)
                halo[a, b, c] = value
                grid[a, b, 4 + c] += value


@numba.njit(inline="always")
def _interpolated(field, row, col, share, c) -> float:  # noqa: ANN001
    """Channel c of ``field``, a grid of every ``share``-th pixel and row (and the last
    ones), at pixel (row, col), bilinearly between the points around it."""
    y0, x0 = row // share, col // share  # a grid has a point past every pixel
    fy, fx = (row - y0 * share) / share, (col - x0 * share) / share
    y1, x1 = min(y0 + 1, field.shape[0] - 1), min(x0 + 1, field.shape[1] - 1)
    return _bilinear(field, y0, y1, fy, x0, x1, fx, c)


@numba.njit(inline="always")
def _halo_at(halo, row, col):  # noqa: ANN001, ANN202
    """Forward scatter's blurred light at pixel (row, col), from the shading grid's."""
    return (
        _interpolated(halo, row, col, SHARE, 0),
        _interpolated(halo, row, col, SHARE, 1),
        _interpolated(halo, row, col, SHARE, 2),
    )


@numba.njit(inline="always")
def _bilinear(field, y0, y1, fy, x0, x1, fx, c) -> float:  # noqa: ANN001
    """Channel c of (h, w, channels) ``field`` between rows y0, y1 and columns x0, x1, at the
    fractions fy, fx of the way from the first to the second."""
    top = field[y0, x0, c] + fx * (field[y0, x1, c] - field[y0, x0, c])
    bottom = field[y1, x0, c] + fx * (field[y1, x1, c] - field[y1, x0, c])
    return top + fy * (bottom - top)


@numba.njit(inline="always")
def _develop_row(row, width, row_light, ray_length, specks, speck_blocks, camera, radiance, signal):  # fmt: skip  # noqa: ANN001, E501
    """Marine snow and the sensor over one row's light: lens vignetting, sensor noise, the
    raw signal's floor at zero, white balance and the gain, in the order of a camera's raw
    pipeline, into ``signal`` for `develop_image`.

    Noise is added to the sensor signal before the exposure gain, so a dark frame that the
    auto exposure brightens shows its noise, as a real camera's does; the white balance
    then lifts the noise of the channels it lifts.
    """
    gains, gain, vignetting, noise, frame_key, _ = camera
    read2 = np.float32((READ_NOISE * noise) ** 2)
    shot = np.float32(SHOT_NOISE * noise / 3.0)
    g0, g1, g2 = (np.float32(gains[0] * gain), np.float32(gains[1] * gain),
                  np.float32(gains[2] * gain))  # fmt: skip
    zero = np.float32(0.0)  # in float32, as the signal is
    start = row * width
    for b in range(speck_blocks.shape[1]):
        if speck_blocks[row // SHARE, b]:
            for col in range(b * SHARE, min(b * SHARE + SHARE, width)):
                for c in range(3):
                    row_light[col, c] += specks[start + col, c]
                    specks[start + col, c] = 0.0
    if radiance.shape[0]:
        radiance[start : start + width] = row_light
    for col in range(width):
        i = start + col
        l0, l1, l2 = row_light[col, 0], row_light[col, 1], row_light[col, 2]
        lens = np.float32(_lens(ray_length[i], vignetting))
        v0, v1, v2 = l0 * lens, l1 * lens, l2 * lens
        if noise > 0.0:
            # Read noise plus shot noise of the pixel's mean level; three deviates from
            # one 64-bit hash.
            h = mix(frame_key ^ np.uint64(i))
            sigma = np.float32(math.sqrt(read2 + shot * abs(v0 + v1 + v2)))
            v0 += sigma * np.float32(_uniform(h, 0))
            v1 += sigma * np.float32(_uniform(h, 21))
            v2 += sigma * np.float32(_uniform(h, 42))
        signal[i, 0] = g0 * max(v0, zero)
        signal[i, 1] = g1 * max(v1, zero)
        signal[i, 2] = g2 * max(v2, zero)


# The sensor's noise at noise = 1, in units of full scale before the gain. An ROV camera
# (a 1/2.9-inch 1080p sensor: wells of about 10,000 electrons, read noise of about 5)
# streams 1920x1080, which a 640x480 frame samples down: each of its pixels gathers
# about five of the sensor's, 50,000 electrons of well and 11 of read noise. Shot noise
# is Poisson: the variance per unit of signal is one electron's share of that well.
READ_NOISE = 11.0 / 50_000.0
SHOT_NOISE = 1.0 / 50_000.0
DENOISE_SIGMAS = 2.5  # neighbours within this many noise deviations of a pixel are alike
LUMA_R, LUMA_G, LUMA_B = LUMA


@_parallel_kernel
def develop_image(
    signal: np.ndarray,  # (n, 3) float32: the sensor's signal, from shade_frame
    width: int,
    camera: tuple,  # (gains, gain, vignetting, noise, frame_key, black level), as shade_frame's
    denoise: float,  # 0-1: how much of the filtered luma replaces the pixel's own
    lut: np.ndarray,  # the tone curve, see optics.tone_lut
    rgb: np.ndarray,  # (n, 3) uint8 out
    luma: np.ndarray,  # (2, n) float32 work buffer: luma, then the filter's shift of it
) -> None:
    """The camera's processing after the sensor: a noise filter, the black clamp, then
    the tone curve and 8-bit sRGB (the lookup table).

    The filter is Lee's sigma filter (1983), the edge-keeping smoothing of camera
    pipelines, on luma (Rec. 601's Y, the luma of JPEG and H.264): each pixel's luma
    becomes the mean of its 3x3 neighbours' that lie within `DENOISE_SIGMAS` of the noise
    expected at its level, so flat rock loses its grain of noise while edges and texture
    stronger than the noise stay; the pixel's three channels move by the same amount.
    The expected noise counts the white balance, which lifts the noise of the channels
    it lifts. Colour noise is left to the compression's half-resolution colour, as
    cameras leave it to their chroma filter.

    The black clamp works on luma too (`optics.black_clamp`): a pixel whose luma is at or
    below the black level reads black, the rest are scaled down alike in every channel,
    so the clamp darkens without shifting hues (a per-channel clamp would take the red out
    of all but the nearest rock, since the water takes it first).
    """
    n = signal.shape[0]
    gains, gain, _, noise, _, black = camera
    own, shift = luma[0], luma[1]
    for i in numba.prange(n):
        own[i] = LUMA_R * signal[i, 0] + LUMA_G * signal[i, 1] + LUMA_B * signal[i, 2]
    filtering = denoise > 0.0 and noise > 0.0
    if filtering:
        _sigma_filter(own, width, (gains[0], gains[1], gains[2]), gain, noise, denoise, shift)
    floor, stretch = np.float32(black), np.float32(1.0 / (1.0 - black))
    zero = np.float32(0.0)
    for i in numba.prange(n):  # in float32, as the signal is
        moved = shift[i] if filtering else zero
        y = own[i] + moved
        scale = stretch * max(y - floor, zero) / y if y > zero else zero
        rgb[i, 0] = _tone(lut, (signal[i, 0] + moved) * scale)
        rgb[i, 1] = _tone(lut, (signal[i, 1] + moved) * scale)
        rgb[i, 2] = _tone(lut, (signal[i, 2] + moved) * scale)


@numba.njit(inline="always")
def _sigma_filter(own, width, gains, gain, noise, denoise, shift) -> None:  # noqa: ANN001
    """`develop_image`'s filter: the shift of each pixel's luma toward the mean of its 3x3
    neighbours (edges clamped) that lie within `DENOISE_SIGMAS` of its noise.

    The luma of a pixel whose raw level is v has the variance g^2 k^2 (read^2 + shot v),
    g the gain, k^2 = sum of (luma weight x white balance)^2, and v about Y / (g m), m =
    sum of luma weight x white balance; the difference of two pixels has twice that.
    Squared reach in float32 throughout, which the loop vectorises.
    """
    g0, g1, g2 = gains
    k2 = (LUMA_R * g0) ** 2 + (LUMA_G * g1) ** 2 + (LUMA_B * g2) ** 2
    m = LUMA_R * g0 + LUMA_G * g1 + LUMA_B * g2
    spread = 2.0 * DENOISE_SIGMAS**2 * k2
    read2 = np.float32(spread * (gain * READ_NOISE * noise) ** 2)
    shot = np.float32(spread * gain * SHOT_NOISE * noise / max(m, 1e-6))
    strength = np.float32(denoise)
    zero, one = np.float32(0.0), np.float32(1.0)
    height = own.shape[0] // width
    for row in numba.prange(height):
        up, mid, down = max(row - 1, 0) * width, row * width, min(row + 1, height - 1) * width
        for col in range(width):
            left, right = max(col - 1, 0), min(col + 1, width - 1)
            y = own[mid + col]
            reach2 = read2 + shot * max(y, zero)
            total = count = zero
            for v in (own[up + left], own[up + col], own[up + right],
                      own[mid + left], y, own[mid + right],
                      own[down + left], own[down + col], own[down + right]):  # fmt: skip
                near = one if (v - y) * (v - y) <= reach2 else zero
                total += near * v
                count += near
            shift[mid + col] = strength * (total / count - y)


@_parallel_kernel
def shade_frame(
    cast: tuple,  # (t, triangle, normals, uvs): the forward cast, see below
    rays: tuple,  # (directions, ray_length, origin), see below
    scene: tuple,  # (faces, vertex_normals, surface, surface_at, specular, focal px, *photos)
    lamps: tuple,  # (position, axis, power (k, 3), beam profile) world frame
    water: tuple,  # attenuation, kept, backscatter, block, far, sky, bounds, silt tables
    grid: np.ndarray,  # from shade_grid
    grid_triangle: np.ndarray,  # from shade_grid
    photo: np.ndarray,  # from photograph_rock_grid
    halo: np.ndarray,  # (H', W', 3) float32: forward scatter's blurred light, see below
    specks: np.ndarray,  # (n, 3) float32 marine snow; zeroed here as it is read
    speck_blocks: np.ndarray,  # (ceil(H / SHARE), ceil(W / SHARE)) uint8
    camera: tuple,  # (gains, gain, vignetting, noise, frame_key, black level)
    depth_range: tuple,  # (d_min, d_max, depth_dropout, depth_noise)
    width: int,
    radiance: np.ndarray,  # (n, 3) float32 out: radiance at the lens; (0, 3): not wanted
    signal: np.ndarray,  # (n, 3) float32 out: the sensor's signal, for develop_image
    depth_png: np.ndarray,  # (n,) uint8 out
) -> None:
    """Shade every pixel, take it through the sensor (`develop_image` finishes the
    image) and normalise its depth.

    The forward cast: t (n,) float32 planar depth, inf where no hit, degraded in place;
    triangle (n,) uint32 hit triangle, 0xFFFFFFFF where no hit; normals (n, 3) float32
    triangle normals; uvs (n, 2) float32 barycentric coordinates of each hit. Rays:
    directions (n, 3) float32 world, unit optical component; ray_length (n,) their
    lengths (1 / cos off-axis); origin (3,) the camera.

    Water: its beam attenuation c and kept attenuation k (3,) each, the backscatter table
    (h, w, bins + 1, 3), its block in pixels and far depth, open water's brightness, the
    cave's bounds, and the silt's veil and light tables (`integrate_silt`; (1, 1, 2, 3)
    zeros for clear water). ``halo`` holds the light scattered forward, blurred, at the
    grid's points (`spread_halo`, which has added it to the grid's light already, so
    pixels interpolated from the grid carry it); the others add it, interpolated.

    The radiance of rock and veil is interpolated from `shade_grid`'s four points around
    a pixel where they and the pixel see one smooth surface: rock at all four, their
    shading normals within 25 degrees (`SAME_FACING`; smooth shading makes the light
    continuous across such creases, and the jagged facets of a marching-cubes wall
    differ by more), and 1 / depth, which is linear across the image of a plane, within
    2% of the interpolation. The other pixels (silhouettes, sharp edges, open water) are
    shaded on their own, in a second loop per row that keeps the first one lean; a third
    adds the marine snow and takes the row's light, still in L1, through the sensor.
    Depth, marine snow and noise are always per pixel.
    """
    t, triangle, normals, _ = cast
    ray_length = rays[1]
    frame_key = camera[4]
    height = t.shape[0] // width
    for row in numba.prange(height):
        a = row // SHARE
        top = a * SHARE
        fy = (row - top) / max(min(top + SHARE, height - 1) - top, 1)
        b = left = 0
        across = 1.0
        t00 = t01 = t10 = t11 = _NO_HIT
        smooth_cell = False
        pending = np.empty(width, np.int64)
        row_light = np.empty((width, 3), np.float32)
        # The grid's and the photographs' points blended down to this row once, so that
        # a pixel blends only across: a quarter of the multiplications.
        at_row = _down_to_row(grid, a, fy)
        photo_row = _photo_down_to_row(photo, row)
        count = 0
        for col in range(width):
            if col % SHARE == 0:  # entering the cell between grid columns b and b + 1
                b = col // SHARE
                left = col
                across = 1.0 / max(min(left + SHARE, width - 1) - left, 1)
                smooth_cell = _smooth_cell(grid, a, b)
                t00, t01 = grid_triangle[a, b], grid_triangle[a, b + 1]
                t10, t11 = grid_triangle[a + 1, b], grid_triangle[a + 1, b + 1]
            i = row * width + col
            tri = triangle[i]
            if smooth_cell and tri != _NO_HIT:
                inverse = 1.0 / t[i]
                fx = (col - left) * across
                if (
                    # On a corner's own triangle, or facing as the corners do: the normals
                    # (12 bytes a pixel) are read only where the triangles change.
                    (
                        tri in (t00, t01, t10, t11)
                        or normals[i, 0] * grid[a, b, 1] + normals[i, 1] * grid[a, b, 2]
                        + normals[i, 2] * grid[a, b, 3] >= SAME_FACING
                    )
                    and abs(_across(at_row, b, 0, fx) - inverse) <= 0.02 * inverse
                ):  # fmt: skip
                    more = _photo_across(photo_row, col) - 1.0
                    _finish(
                        i, _across(at_row, b, 1, fx) + more * _across(at_row, b, 5, fx),
                        _across(at_row, b, 2, fx) + more * _across(at_row, b, 6, fx),
                        _across(at_row, b, 3, fx) + more * _across(at_row, b, 7, fx),
                        _across(at_row, b, 4, fx), True, col, t, frame_key, depth_range,
                        row_light, depth_png,
                    )  # fmt: skip
                    continue
            pending[count] = col
            count += 1
        for k in range(count):
            col = pending[k]
            i = row * width + col
            l0, l1, l2, _, _, _, lamp_return, r0, r1, r2 = _own_light(
                i, row, col, cast, rays, scene, lamps, water
            )
            if triangle[i] != _NO_HIT:
                more = _photo_across(photo_row, col) - 1.0
                l0, l1, l2 = l0 + more * r0, l1 + more * r1, l2 + more * r2
            h0, h1, h2 = _halo_at(halo, row, col)
            _finish(
                i, l0 + h0, l1 + h1, l2 + h2, lamp_return, triangle[i] != _NO_HIT, col, t,
                frame_key, depth_range, row_light, depth_png,
            )  # fmt: skip
        _develop_row(
            row, width, row_light, ray_length, specks, speck_blocks, camera, radiance, signal
        )


@_parallel_kernel
def hemisphere_rays(
    centre: np.ndarray,  # (k, 3) ray origins before the offset
    normal: np.ndarray,  # (k, 3) unit: the hemisphere's pole
    tangent: np.ndarray,  # (k, 3) unit, perpendicular to normal: orients the pattern
    pattern: np.ndarray,  # (r, 3) directions around +z
    offset: float,  # origins move this far along the normal, off the surface
    rays: np.ndarray,  # (k * r, 6) float32 out
) -> None:
    """The pattern of directions turned onto each (normal, tangent) frame."""
    r = pattern.shape[0]
    for f in numba.prange(centre.shape[0]):
        nx, ny, nz = normal[f, 0], normal[f, 1], normal[f, 2]
        ax, ay, az = tangent[f, 0], tangent[f, 1], tangent[f, 2]
        bx, by, bz = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax
        for j in range(r):
            u, v, w = pattern[j, 0], pattern[j, 1], pattern[j, 2]
            i = f * r + j
            rays[i, 0] = centre[f, 0] + offset * nx
            rays[i, 1] = centre[f, 1] + offset * ny
            rays[i, 2] = centre[f, 2] + offset * nz
            rays[i, 3] = u * ax + v * bx + w * nx
            rays[i, 4] = u * ay + v * by + w * ny
            rays[i, 5] = u * az + v * bz + w * nz


@_parallel_kernel
def gather_sky(
    rays: np.ndarray,  # (k * r, 6) float32 as from hemisphere_rays
    t: np.ndarray,  # (k * r,) float32 hit distance (unit directions)
    ids: np.ndarray,  # (k * r,) uint32 hit triangle
    hit_normals: np.ndarray,  # (k * r, 3) float32
    bounds: np.ndarray,  # (2, 3) the cave's box
    attenuation: np.ndarray,  # (3,)
    sky: np.ndarray,  # (3,) open-water radiance looking straight up
    crevice_radius: float,
    enclosed: np.ndarray,  # (k,) out: fraction of rays hitting rock within the radius
    direct: np.ndarray,  # (k, 3) out: mean open-water radiance over the rays
    hit_face: np.ndarray,  # (k, r) int64 out: triangle each ray hits, -1 if none
    hit_side: np.ndarray,  # (k, r) int8 out: side of that triangle the ray reaches
    hit_dist: np.ndarray,  # (k, r) float32 out
) -> None:
    """Per origin: how enclosed it is, and the daylight reaching it straight from open water.

    With cosine-weighted directions, the mean radiance over the rays is the irradiance
    divided by pi, which is what a Lambertian surface's radiance needs.
    """
    r = hit_face.shape[1]
    for f in numba.prange(hit_face.shape[0]):
        near = 0
        d0 = d1 = d2 = 0.0
        for j in range(r):
            i = f * r + j
            if ids[i] == _NO_HIT:
                o0, o1, o2 = _open_water(
                    rays[i, 0], rays[i, 1], rays[i, 2], rays[i, 3], rays[i, 4], rays[i, 5],
                    sky, bounds, attenuation[0], attenuation[1], attenuation[2],
                )  # fmt: skip
                d0, d1, d2 = d0 + o0, d1 + o1, d2 + o2
                hit_face[f, j] = -1
                hit_side[f, j] = 0
                hit_dist[f, j] = 0.0
            else:
                near += t[i] < crevice_radius
                hit_face[f, j] = ids[i]
                facing = (
                    hit_normals[i, 0] * rays[i, 3]
                    + hit_normals[i, 1] * rays[i, 4]
                    + hit_normals[i, 2] * rays[i, 5]
                )
                hit_side[f, j] = 1 if facing > 0.0 else 0  # the ray meets the back side
                hit_dist[f, j] = t[i]
        enclosed[f] = near / r
        direct[f, 0], direct[f, 1], direct[f, 2] = d0 / r, d1 / r, d2 / r


@_parallel_kernel
def bounce_light(
    hit_face: np.ndarray,  # (k, r) int64, -1 where the ray escaped
    hit_side: np.ndarray,  # (k, r) int8
    hit_dist: np.ndarray,  # (k, r) float32
    leaving: np.ndarray,  # (m, 2, 3) radiance leaving each side of each triangle
    attenuation: np.ndarray,  # (3,)
    out: np.ndarray,  # (k, 3) out: mean radiance arriving along the rays
) -> None:
    """One bounce: the light other walls send back along each hemisphere ray."""
    r = hit_face.shape[1]
    for f in numba.prange(hit_face.shape[0]):
        b0 = b1 = b2 = 0.0
        for j in range(r):
            face = hit_face[f, j]
            if face < 0:
                continue
            side, dist = hit_side[f, j], hit_dist[f, j]
            b0 += leaving[face, side, 0] * math.exp(-attenuation[0] * dist)
            b1 += leaving[face, side, 1] * math.exp(-attenuation[1] * dist)
            b2 += leaving[face, side, 2] * math.exp(-attenuation[2] * dist)
        out[f, 0], out[f, 1], out[f, 2] = b0 / r, b1 / r, b2 / r


@numba.njit(cache=True, nogil=True)
def corner_sums(
    faces: np.ndarray,  # (m, 3) int vertex indices
    weighted: np.ndarray,  # (m, k) float64 per-face values times the face's weight
    weight: np.ndarray,  # (m,) float64 per-face weights
    total: np.ndarray,  # (n, k) float64 out, zeroed: sum of weighted over each vertex's faces
    total_weight: np.ndarray,  # (n,) float64 out, zeroed: sum of weight likewise
) -> None:
    """Scatter-add each face's row to its three vertices: corner 0 of every face first,
    then 1, then 2, one thread, so each vertex sums in np.add.at's order, bit for bit."""
    m, k = weighted.shape
    for corner in range(3):
        for f in range(m):
            v = faces[f, corner]
            for j in range(k):
                total[v, j] += weighted[f, j]
            total_weight[v] += weight[f]


@_parallel_kernel
def fill_rays(
    pixel_dirs: np.ndarray, rotation: np.ndarray, origin: np.ndarray, rays: np.ndarray
) -> None:
    """rays[i] = (origin, rotation @ pixel_dirs[i]) for (n, 3) camera-frame directions."""
    for i in numba.prange(pixel_dirs.shape[0]):
        for k in range(3):
            rays[i, k] = origin[k]
            rays[i, 3 + k] = (
                rotation[k, 0] * pixel_dirs[i, 0]
                + rotation[k, 1] * pixel_dirs[i, 1]
                + rotation[k, 2] * pixel_dirs[i, 2]
            )

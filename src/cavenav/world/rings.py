"""Rings: whether a cave's wall relief repeats along its passage.

A passage whose relief repeats at one wavelength along its axis looks turned on a lathe:
every frame shows concentric bands, each the same distance behind the last (issue 49).
Rock is rough at every scale with none preferred, so the spectrum of its relief along the
passage is smooth; a repeating term of a generator stands out of it as a line. This
module measures how far the tallest line stands out, in two spectra of the same rays:

- the radius spectrum: the spectrum of the wall's distance from the axis, r(s, theta),
  along the axis. It sees relief that repeats: a lathe's grooves, ripples.
- the crease spectrum: the spectrum of how sharply the wall bends along the axis, its
  crease strength |d2r/ds2|, averaged around each eighth of the circumference. It sees
  rings whose strength repeats where their height does not. Relief built on a lattice
  (lattice noise, a jittered lattice of scallops, the slabs of marching cubes) has
  random heights but bends hardest on the lattice's planes, and a passage along a
  lattice axis meets those planes as rings, one every lattice spacing; so do the seams
  where the sections of a swept tube's samples meet. Such rings leave no line in the
  radius spectrum, and the eye sees them at once.

How, in `ring_spectra`:

1. The axis: a centre line (a generated cave's own; `portal_axis` or `centred_axis` for
   a mesh that has none), stations every `STEP_M` of arc length, smoothed over
   `AXIS_SMOOTHING_M` so that a polyline's corners put no period of their own into the
   rays' directions.
2. r(s, theta): the first hit of `ANGLES` rays from each station, evenly spread around
   the axis in the plane across it (`wall_radii`). Rays that meet no wall are left out:
   an escape (an open portal), a ray that meets a surface at a glance (`GLANCING`: the
   side of a branch or of an object), a ray longer than three times the median (a side
   branch), or one that departs by more than `OFF_WALL_M` from its angle's running
   median over `OBJECT_SPAN_M` (a boulder, a block or a speleothem up to about 2.5 m
   long: an object in the passage, not relief of its wall, whose edges would fill every
   spectrum with the comb of a box), each widened by 0.3 m along s. The gaps are
   bridged by straight lines; angles that miss over 30 % of the stations are dropped.
3. The radius spectrum: per angle, Welch's estimate along s (Hann windows of
   `WINDOW_M`, half overlapping, each segment's linear trend removed), averaged over
   the angles. The crease spectrum: |d2r/ds2| of each angle (a Gaussian derivative at
   `CREASE_SIGMA_M`, which keeps the rays' rounding out but not a kink repeated every
   0.2 m), averaged over the measured rays of each eighth of the circumference, its
   Welch spectrum per eighth, averaged over the eight.
4. The peak factor at each wavelength of the band (`BAND_M`): its power over the median
   power of its neighbours, the bins within a factor `NEIGHBOURS` either side in
   wavelength but for the two next to it (a line leaks into those through the window),
   once the neighbourhood's power-law trend (a least-squares line of log power on log
   frequency) is taken out, so that a red spectrum's own slope reads as no peak
   (`peak_factors`). Each spectrum's statistic is its largest factor and where it lies.

A lathe ring of wavelength L shows in the radius spectrum at L and in the crease spectrum
at L / 2 (its crests and its troughs both bend); lattice rings show in the crease
spectrum at the lattice's spacing. A wall with no relief at all has no spectrum to stand
out of: its factors measure rounding and mean nothing.

Why these numbers: 5 cm stations resolve relief down to 0.1 m; 64 rays put a station's
rays 0.2-0.4 m apart on the wall, as far apart as the finest relief measured; 12.8 m
windows give bins of 0.078 cycles per metre, fine enough that a line at 2 m still has six
neighbours within a factor 2 (a factor 1.5 would leave it two), and short enough that a
20 m tile yields two windows. The band stops at 2 m for the same reason: a line at 5 m
would need windows of 50 m to be told from its neighbours, longer than the tiles.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal

from cavenav.core.types import Pose
from cavenav.world.geodesic import shortest_path
from cavenav.world.mesh import CaveMesh, open_portals
from cavenav.world.procedural import arc_length, resample
from cavenav.world.raycast import RayCaster
from cavenav.world.scenario import ExitPortal, Scenario

__all__ = [
    "ANGLES",
    "BAND_M",
    "RING_LIMIT",
    "STEP_M",
    "WINDOW_M",
    "RingSpectra",
    "Spectrum",
    "axis_frames",
    "centred_axis",
    "portal_axis",
    "peak_factors",
    "ring_spectra",
    "wall_radii",
]

STEP_M = 0.05  # stations along the axis
ANGLES = 64  # rays around the axis at each station
SECTORS = 8  # the crease strength is averaged around each of these parts of the circumference
WINDOW_M = 12.8  # Welch window along the axis (256 stations)
BAND_M = (0.2, 2.0)  # wavelengths searched for a peak
NEIGHBOURS = 2.0  # a peak's neighbourhood: this factor either side in wavelength
AXIS_SMOOTHING_M = 0.5  # Gaussian sigma over the axis's points before frames are taken
CREASE_SIGMA_M = 0.1  # Gaussian sigma of the second derivative along the axis
OFF_WALL_M = 0.6  # a ray this far from its angle's running median met an object, not the wall
OBJECT_SPAN_M = 5.0  # that running median's span: twice the longest object it leaves out
GLANCING = 0.25  # a ray meeting a surface at under this cosine (over 75.5 degrees) is left out
RING_LIMIT = 4.0
"""The largest peak factor a cave's relief may have, in either spectrum: no line stands
4 times above its neighbours.

Relief with no preferred scale, drawn on a 30 m tube (`tests/world/test_rings.py`),
reads 1.7-1.9 in the radius spectrum and 2.2-3.0 in the crease spectrum over 12 draws:
the largest of a few hundred bins strays above the rest by chance. A lathe ring of 1.5 cm
in 5 cm of such relief reads 11 and 9, lattice relief 11 in the crease spectrum. The
third-party meshes cannot set the limit: the SubT tiles are drawn as lofts (the straight
one is rows of 100 vertices every 0.2 m along it) and read 7-19 in the crease spectrum
(benchmarks/ring_spectrum.py)."""


@dataclass(frozen=True)
class Spectrum:
    """One spectrum along the axis and its tallest line.

    Attributes:
        wavelengths: (k,) metres, longest first (the zero frequency left out).
        power: (k,) power per cycle per metre, in the squared unit of the series.
        factors: (k,) the peak factor at each wavelength (NaN outside `BAND_M`).
        peak_factor: the largest of ``factors``.
        peak_wavelength: where it lies, metres.
        line_rms: how much of the series the line above its neighbours' trend holds, RMS
            in the series' unit (metres for the radius: a sinusoidal ring of amplitude
            a reads a / sqrt 2).
    """

    wavelengths: np.ndarray
    power: np.ndarray
    factors: np.ndarray
    peak_factor: float
    peak_wavelength: float
    line_rms: float


@dataclass(frozen=True)
class RingSpectra:
    """The radius and crease spectra of a passage (see the module's notes).

    Attributes:
        radius: the spectrum of the wall's distance from the axis.
        crease: the spectrum of the crease strength around each eighth of the wall.
        length_m: how much axis was measured.
        angles: how many of the `ANGLES` angles were kept.
        off_wall: the fraction of rays left out (escapes, branches, objects).
    """

    radius: Spectrum
    crease: Spectrum
    length_m: float
    angles: int
    off_wall: float

    @property
    def peak_factor(self) -> float:
        """The larger of the two spectra's peak factors: what `RING_LIMIT` bounds."""
        return max(self.radius.peak_factor, self.crease.peak_factor)


def _smoothed(points: np.ndarray, sigma: float) -> np.ndarray:
    """(n, 3) a polyline smoothed along itself (Gaussian, ``sigma`` samples), its ends
    padded by point reflection so that a straight end stays where it is: padding by
    repeating the end point (scipy's "nearest") would pull each end in by about sigma."""
    pad = min(int(4.0 * sigma) + 1, len(points) - 1)
    if pad < 1:
        return points
    head = 2.0 * points[0] - points[pad:0:-1]
    tail = 2.0 * points[-1] - points[-2 : -pad - 2 : -1]
    padded = np.concatenate([head, points, tail])
    return ndimage.gaussian_filter1d(padded, sigma, axis=0, mode="nearest")[pad:-pad]


def axis_frames(
    axis: np.ndarray, step: float = STEP_M, smoothing: float = AXIS_SMOOTHING_M
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stations every ``step`` metres along a centre line, and their frames.

    The polyline is resampled, then smoothed (Gaussian, ``smoothing`` metres) so that its
    tangent turns gradually: the rays of a station at a polyline's corner would otherwise
    turn by the corner's whole angle, a period of the sampling in every radius.

    Returns:
        ((n, 3) stations, (n, 3) unit tangents, (n, 3) horizontal unit normals to the
        left, (n, 3) unit 'up' across the axis).
    """
    points = np.asarray(axis, np.float64)
    points = points[np.r_[True, np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9]]
    stations = _smoothed(resample(points, step)[0], smoothing / step)
    tangent = np.gradient(stations, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.cross(np.array([0.0, 0.0, 1.0]), tangent)
    flat = np.linalg.norm(normal, axis=1) < 1e-6  # a vertical stretch: any horizontal normal
    normal[flat] = np.cross(tangent[flat], np.array([1.0, 0.0, 0.0]))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return stations, tangent, normal, np.cross(tangent, normal)


def _fan(
    normal: np.ndarray, up: np.ndarray, angles: int, turn: float = 2.0 * math.pi
) -> np.ndarray:
    """(n, angles, 3) unit rays across the axis, evenly spread over ``turn`` radians from
    the left normal towards up, half a step in."""
    theta = turn * (np.arange(angles) + 0.5) / angles
    return (
        np.cos(theta)[None, :, None] * normal[:, None] + np.sin(theta)[None, :, None] * up[:, None]
    )


def wall_radii(
    caster: RayCaster, axis: np.ndarray, step: float = STEP_M, angles: int = ANGLES
) -> np.ndarray:
    """(n, angles) distance to the wall from each station of ``axis`` (`axis_frames`),
    along rays evenly spread around it in the plane across it. Angle k points
    (k + 1/2) / angles of a turn from the left, towards up.

    inf where a ray escapes, or meets a surface at a glance (`GLANCING`): the side wall of
    a branch or the flank of an object, not the wall around the axis. Down a side branch
    a ray sweeps the branch's wall at a glance, so that every 5 cm along the axis moves
    its hit by decimetres: the branch's relief would come back squeezed into a false
    short period.
    """
    stations, _, normal, up = axis_frames(axis, step)
    directions = _fan(normal, up, angles)
    rays = np.empty((*directions.shape[:2], 6), np.float32)
    rays[..., :3] = stations[:, None]
    rays[..., 3:] = directions
    found = caster.cast_raw_rays(rays.reshape(-1, 6))
    facing = np.abs(np.einsum("ij,ij->i", found["primitive_normals"], rays.reshape(-1, 6)[:, 3:]))
    t = np.where(facing >= GLANCING, found["t_hit"], np.inf)
    return t.reshape(directions.shape[:2]).astype(np.float64)


def _on_the_wall(
    radii: np.ndarray, step: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The rays that met the wall (see the module's notes, step 2), gaps bridged.

    Returns:
        ((n', k) radii with the gaps bridged, (n', k) which were measured, (k,) the index
        of each kept angle, the fraction of all rays left out); n' stations from the
        first to the last where half the rays met the wall, k the angles that met it at
        70 % of those.
    """
    finite = np.isfinite(radii)
    median = float(np.median(radii[finite])) if finite.any() else 1.0
    r = np.where(finite & (radii < 3.0 * median), radii, np.nan)
    span = int(round(OBJECT_SPAN_M / step)) | 1
    running = ndimage.median_filter(np.nan_to_num(r, nan=median), size=(span, 1), mode="nearest")
    with np.errstate(invalid="ignore"):
        off = ~np.isfinite(r) | (np.abs(r - running) > OFF_WALL_M)
    grow = 2 * int(round(0.3 / step)) + 1
    good = ~ndimage.binary_dilation(off, structure=np.ones((grow, 1), bool))
    rows = np.flatnonzero(good.mean(axis=1) >= 0.5)
    if len(rows) == 0:
        return np.empty((0, 0)), np.empty((0, 0), bool), np.empty(0, np.int64), 1.0
    r, good = r[rows[0] : rows[-1] + 1], good[rows[0] : rows[-1] + 1]
    keep = np.flatnonzero(good.mean(axis=0) >= 0.7)
    index = np.arange(len(r))
    columns = [np.interp(index, index[good[:, k]], r[good[:, k], k]) for k in keep]
    bridged = np.stack(columns, axis=1) if columns else np.empty((len(r), 0))
    return bridged, good[:, keep], keep, 1.0 - float(good[:, keep].sum()) / radii.size


def peak_factors(
    frequencies: np.ndarray,
    power: np.ndarray,
    band: tuple[float, float] = BAND_M,
    neighbours: float = NEIGHBOURS,
) -> np.ndarray:
    """(k,) each bin's power over the median of its neighbours' once their local power-law
    trend is taken out (see the module's notes); NaN outside ``band`` (wavelengths, m)."""
    factors = np.full(len(frequencies), np.nan)
    log_f, log_p = np.log(np.maximum(frequencies, 1e-12)), np.log(np.maximum(power, 1e-300))
    for i, f in enumerate(frequencies):
        if not (f > 0 and band[0] <= 1.0 / f <= band[1]):
            continue
        near = (frequencies >= f / neighbours) & (frequencies <= f * neighbours)
        near &= np.abs(np.arange(len(frequencies)) - i) > 1
        if near.sum() < 3:
            continue
        slope, _ = np.polyfit(log_f[near], log_p[near], 1)
        trended = log_p[near] + slope * (log_f[i] - log_f[near])  # each moved to f
        factors[i] = math.exp(log_p[i] - float(np.median(trended)))
    return factors


def _spectrum(series: np.ndarray, step: float, window: float) -> Spectrum:
    """The Welch spectrum of the (n, k) ``series`` along n, averaged over k, and its line."""
    frequencies, power = signal.welch(
        series, fs=1.0 / step, window="hann", nperseg=int(round(window / step)),
        detrend="linear", axis=0,
    )  # fmt: skip
    frequencies, power = frequencies[1:], power[1:].mean(axis=1)
    factors = peak_factors(frequencies, power)
    best = int(np.nanargmax(factors))
    around = slice(max(best - 2, 0), best + 3)  # the Hann window spreads a line over 5 bins
    trend = power[best] / factors[best]
    excess = float(np.clip(power[around] - trend, 0.0, None).sum()) * frequencies[0]
    return Spectrum(
        wavelengths=1.0 / frequencies,
        power=power,
        factors=factors,
        peak_factor=float(factors[best]),
        peak_wavelength=float(1.0 / frequencies[best]),
        line_rms=math.sqrt(excess),
    )


def _creases(
    radii: np.ndarray, measured: np.ndarray, angles: np.ndarray, step: float
) -> np.ndarray:
    """(n, sectors) the crease strength |d2r/ds2| averaged over each sector's measured rays
    (``angles``: each column's angle index), bridged stretches left out, and the same
    where a sector has none measured at a station."""
    sigma = CREASE_SIGMA_M / step
    bend = np.abs(ndimage.gaussian_filter1d(radii, sigma, axis=0, order=2)) / step**2
    reach = 2 * int(math.ceil(3.0 * sigma)) + 1  # the derivative's reach into a bridge
    weight = ndimage.binary_erosion(measured, np.ones((reach, 1), bool), border_value=1)
    sector = angles * SECTORS // ANGLES
    out = []
    for part in range(SECTORS):
        w = weight[:, sector == part].astype(np.float64)
        if w.shape[1] == 0:
            continue
        total = w.sum(axis=1)
        mean = (bend[:, sector == part] * w).sum(axis=1) / np.maximum(total, 1.0)
        out.append(np.where(total > 0, mean, np.median(mean[total > 0]) if total.any() else 0))
    return np.stack(out, axis=1)


def ring_spectra(
    caster: RayCaster,
    axis: np.ndarray,
    step: float = STEP_M,
    window: float = WINDOW_M,
    floor: bool = True,
) -> RingSpectra:
    """The radius and crease spectra of the passage along ``axis`` in ``caster``'s mesh.

    ``floor=False`` leaves out the rays within 45 degrees of straight down, where a
    sediment floor lies: its ripples repeat as a real ripple field does, and this says
    whether the rock around them repeats too.

    Raises:
        ValueError: less than one window of axis where the rays meet the wall.
    """
    raw = wall_radii(caster, axis, step, ANGLES)
    angles = np.arange(ANGLES)
    if not floor:
        angles = angles[np.sin(2.0 * math.pi * (angles + 0.5) / ANGLES) > -math.sqrt(0.5)]
    radii, measured, kept, off_wall = _on_the_wall(raw[:, angles], step)
    if radii.shape[0] < int(round(window / step)) or radii.shape[1] == 0:
        raise ValueError(
            f"{radii.shape[0] * step:.1f} m of passage measured, under one {window:g} m window"
        )
    return RingSpectra(
        radius=_spectrum(radii, step, window),
        crease=_spectrum(_creases(radii, measured, angles[kept], step), step, window),
        length_m=radii.shape[0] * step,
        angles=radii.shape[1],
        off_wall=off_wall,
    )


def centred_axis(
    caster: RayCaster,
    guide: np.ndarray,
    spacing: float = 0.5,
    rounds: int = 5,
    smoothing: float = 1.5,
) -> np.ndarray:
    """A centre line for a mesh that comes without one, from any path along its passage.

    ``guide`` (a polyline inside the passage: the shortest path of
    `cavenav.world.geodesic`, a line between portals) is resampled every ``spacing``
    metres; then, ``rounds`` times, each point moves to the mean of the midpoints of the
    chords that `ANGLES` / 2 pairs of opposite rays cut across the passage, and the line
    is smoothed over ``smoothing`` metres. In a round section the chords' midpoints
    through a point lie on the circle whose diameter joins the point to the middle, so
    each round halves the distance to the middle. A chord with an end beyond three times
    the median ray (a side branch, a portal) is left out, so openings do not pull the
    axis out of the passage.

    Returns:
        (n, 3) the centred line, points ``spacing`` apart.

    Raises:
        ValueError: a guide no longer than ``spacing``.
    """
    points = np.asarray(guide, np.float64)
    if arc_length(points)[-1] <= spacing:
        raise ValueError("the guide is no longer than one spacing")
    half = ANGLES // 2
    for _ in range(rounds):
        stations, _, normal, up = axis_frames(points, spacing, smoothing)
        ahead = _fan(normal, up, half, math.pi)
        origins = np.broadcast_to(stations[:, None], ahead.shape)
        there = caster.first_hit(origins, ahead).astype(np.float64)
        back = caster.first_hit(origins, -ahead).astype(np.float64)
        both = np.concatenate([there, back], axis=1)
        with warnings.catch_warnings(), np.errstate(invalid="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)  # a row of escapes: no median
            median = np.nanmedian(np.where(np.isfinite(both), both, np.nan), axis=1)[:, None]
            good = (there < 3.0 * median) & (back < 3.0 * median)
        shift = np.where(good, 0.5 * (there - back), 0.0)[..., None] * ahead
        counts = good.sum(axis=1)
        moved = stations + shift.sum(axis=1) / np.maximum(counts, 1)[:, None]
        points = np.where((counts >= half // 2)[:, None], moved, stations)
    return axis_frames(points, spacing, smoothing)[0]


def portal_axis(mesh: CaveMesh, caster: RayCaster | None = None) -> np.ndarray:
    """A centre line through an open mesh that comes without one (a tile, a survey): from
    its two portals (`open_portals` wider than 1 m across) farthest apart, the shortest
    path through its free space (`cavenav.world.geodesic`) from 1.5 m inside one to the
    other, centred by `centred_axis`.

    Raises:
        ValueError: fewer than two portals.
        cavenav.world.geodesic.NoPath: no way between them.
    """
    caster = caster or RayCaster(mesh)
    portals = [p for p in open_portals(mesh) if p.radius > 0.5]
    if len(portals) < 2:
        raise ValueError(f"{mesh.name}: {len(portals)} portals; an axis needs two")
    pairs = [(a, b) for k, a in enumerate(portals) for b in portals[k + 1 :]]
    first, last = max(pairs, key=lambda ab: float(np.linalg.norm(ab[0].centre - ab[1].centre)))
    start = first.centre - 1.5 * first.normal
    tour = Scenario(
        name=mesh.name,
        mesh=mesh,
        start=Pose.facing(start, -first.normal),
        exits=(ExitPortal(tuple(last.centre), tuple(last.normal), last.radius + 0.5),),
    )
    return centred_axis(caster, shortest_path(tour, caster).points)

"""How our frames compare with real underwater photographs: issue 25's statistics.

For each water preset (clear, ocean, coastal, turbid), renders the forward colour frame
with the project's own sensor rig (640x480, default optics but the water) at poses evenly
spaced along the geometric pilot's path through S1-S5 (seed 0; `cavenav render` picks
its views the same way, `cavenav.episode.gallery.passage_poses`), and prints every
statistic of `cavenav.sensors.image_stats` at 320x240, as mean and standard deviation
over the frames, beside the real photographs' figures (`REAL` below).

Then the one physical check a cave allows: in clear water, pixels whose rock lies beyond
the lamps' reach should be near black (max(R, G, B) < 16), and those within it should not.
The reach is taken from the lamp, water and camera model in the code, per frame:

    A wall facing the lamps on their axis (every lamp at its on-axis power, incidence
    cos = 1) at range r, with the palest of the rock palette and silt albedos rho
    (`lighting.ROCK_PALETTE` in its palest stratum, `Optics.sediment_colour`), sends
    back per channel (`kernels._surface_light`; the lamps sit within 0.25 m of the
    camera, so their path is taken as r):

        L_c(r) = rho_c * P_c * exp(-2 k_c r) / r^2,   P_c = the lamps' summed power
                                                        (`Optics.lamp_power`)

    with k the water's attenuation on the way out and back, less the light it scatters
    forward, which still arrives about the spot and about its image (`Water.
    kept_attenuation`: the straight light exp(-c r) plus forward scatter's halo).
    The camera multiplies by the frame's white balance w_c and exposure gain g
    (`rig.camera_response`, from the frame's metered mean, recomputed here from the
    frame's linear radiance at the shading grid's pixels, with the lens's vignetting),
    clamps black on luma (`Optics.black_level`, see `optics.black_clamp`) and applies its
    curve, linear below the knee, then sRGB. The reach is the largest r at which the
    brightest channel still reaches the near-black level: max_c sRGB(black_clamp(g w L(r))_c)
    >= 16/255.
    Beyond it, lamp light alone cannot lift even the best-placed, palest rock out of
    near black; closer, rock the lamps face squarely is brighter than that.

    This reach is the lamps' upper bound, not one 8-bit level: a pixel below 16 is
    "near black" by the table's own measure, so a reach defined by one level would call
    rock "within reach" that the statistic counts as black. Rock grain (up to about
    +-50% albedo), the wet rock's glint, the veil of backscatter, daylight from exits,
    marine snow and sensor noise can still lift a pixel beyond the reach; rock seen
    obliquely, off the beam, in a crevice or under a mineral coating is darker than the
    bound within it.

Pixels are classed at 640x480 by the range of their ray (planar depth x the ray's length
per unit depth); a 320x240 pixel counts as beyond (within) when all four of its source
pixels are; mixed pixels and open water (rays that leave the cave: no rock to light) are
left out.

Nothing a pixel shows is darker than the water's own veil of backscatter in front of it,
which the lamps light from the lens on. So the frames looking beyond the reach are split
by the veil's luma there at the frame's exposure (`veil_luma`, before the black clamp):
where it lies below the black level, rock beyond the reach should read near black; where
it lies above, the veil shows instead, and the frame cannot be black there.

Last, on one pose per scenario: Jerlov's water types (`optics.jerlov_water`), with the
lamps' reach in each, and turbid water's contrast as the lamps' beams narrow.

Run: python benchmarks/image_stats.py [--poses N]   (about 3 minutes; the first run
     per water also builds the lighting tables, then cached with the caves)
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, fields

import numpy as np

from cavenav.core.types import Pose
from cavenav.episode.gallery import passage_poses
from cavenav.sensors.image_stats import NEAR_BLACK, FrameStats, downscale, frame_stats
from cavenav.sensors.kernels import SHARE
from cavenav.sensors.lighting import DEFAULT_ROCK, ROCK_PALETTE, backscatter_table
from cavenav.sensors.optics import (
    CAVE_WATERS,
    JERLOV_KD,
    LUMA,
    WATER_TYPES,
    Optics,
    black_clamp,
)
from cavenav.sensors.rig import Frame, SensorConfig, SensorRig, camera_response
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import load_scenario

SCENARIOS = ("S1", "S2", "S3", "S4", "S5")


@dataclass(frozen=True)
class Real:
    """A real photographs' figure: mean, standard deviation where known, and a note."""

    mean: float
    sd: float | None = None
    note: str = ""


# Real underwater photographs: the U45 set (40 daylight images, not caves; the only real
# set at hand; no licensed underwater-cave frames were found in any reachable store), at
# 320x240. Source: /work/shared/NOTES.md ("Facts gathered in turn 3") and the table of
# issue 25 (the standard deviations). The implementations that produced them are not
# known: UIQM and UCIQE vary between implementations, so compare those with care.
REAL: dict[str, Real] = {
    "mean_value": Real(0.60, 0.08),
    "near_black": Real(0.004),
    "structure": Real(5.8, 2.2),
    "noise": Real(0.8, 0.4),
    "highlights": Real(0.02, note="about 2%"),
    "contrast": Real(0.126, note="hazy ones about 0.10"),
    "uiqm": Real(2.47),
    "uciqe": Real(0.35),
}
LABELS = {
    "mean_value": "mean HSV value",
    "near_black": "max(R,G,B) < 16",
    "structure": "structure (Sobel / 8)",
    "noise": "noise sigma (Immerkaer)",
    "highlights": "max(R,G,B) >= 250",
    "contrast": "RMS contrast of luma",
    "uiqm": "UIQM",
    "uciqe": "UCIQE",
}
DIGITS = {"near_black": 3, "highlights": 4, "contrast": 3, "uciqe": 3}


def _tone_inverse(level: float, optics: Optics) -> float:
    """The camera's signal, after its black clamp, whose developed sRGB is ``level`` of
    255: the curve is linear below the knee (`optics.camera_curve`)."""
    s = level / 255.0
    mapped = s / 12.92 if s <= 0.04045 else ((s + 0.055) / 1.055) ** 2.4
    return mapped / (1.0 - mapped) if optics.tone == "soft" else mapped


def palest_rock(optics: Optics) -> np.ndarray:
    """(3,) the palest rock of the palette (`lighting.ROCK_PALETTE`) in its palest stratum
    (+8%), scaled as `lighting.rock_albedo` scales it by `Optics.rock_colour`."""
    scale = np.asarray(optics.rock_colour) / np.asarray(DEFAULT_ROCK)
    return 1.08 * np.max(np.asarray(ROCK_PALETTE), axis=0) * scale


def metered_mean(frame: Frame, config: SensorConfig) -> np.ndarray:
    """(3,) the mean the camera meters: radiance at the shading grid's pixels (every
    SHARE-th row and column, and the last ones; see `kernels.shade_grid`) times the
    lens's vignetting."""
    assert frame.radiance is not None
    h, w = frame.radiance.shape[:2]
    rows = np.minimum(np.arange(-(-h // SHARE) + 1) * SHARE, h - 1)
    cols = np.minimum(np.arange(-(-w // SHARE) + 1) * SHARE, w - 1)
    lens = lens_factor(config)[np.ix_(rows, cols)]
    return (frame.radiance[np.ix_(rows, cols)] * lens[..., None]).reshape(-1, 3).mean(axis=0)


def lens_factor(config: SensorConfig) -> np.ndarray:
    """(H, W) the share of a pixel's light the lens passes: vignetting by the cos^4 law,
    as `kernels._lens` takes it before the sensor."""
    length = np.linalg.norm(config.camera.directions, axis=2)
    return 1.0 - config.optics.vignetting * (1.0 - 1.0 / length**4)


def lamp_reach(optics: Optics, gains: np.ndarray, gain: float, level: float = NEAR_BLACK) -> float:
    """Metres beyond which lamp light cannot lift rock to ``level`` (see the module's
    docstring): the largest r with max_c black_clamp(g w_c rho_c P_c exp(-2 k_c r) / r^2)
    >= T^-1(level) (see `optics.black_clamp`, `_tone_inverse`)."""
    power = optics.lamp_power.astype(np.float64).sum(axis=0)  # (3,) on the lamps' axes
    albedo = np.maximum(palest_rock(optics), optics.sediment_colour)
    attenuation = optics.medium.kept_attenuation.astype(np.float64)
    scale = gain * gains.astype(np.float64) * albedo * power
    need = _tone_inverse(level, optics)

    def bright(r: float) -> bool:
        signal = scale * np.exp(-2.0 * attenuation * r) / (r * r)
        return bool(black_clamp(signal, optics.black_level).max() >= need)

    lo, hi = 0.01, 1000.0
    if not bright(lo):
        return 0.0
    for _ in range(60):  # bisection: the returned light falls monotonically with r
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if bright(mid) else (lo, mid)
    return lo


BEYOND_SHARE = 0.01  # a frame looks beyond the lamps' reach when 1% of its pixels do
DARK_ENOUGH = 0.02  # issue 25: such a frame should be more than 2% near black


@dataclass(frozen=True)
class Exposure:
    """How the camera exposed a frame: its white balance (3,), gain, and the lamps' reach
    at that exposure (`lamp_reach`)."""

    gains: np.ndarray
    gain: float
    reach: float


def veil_luma(config: SensorConfig, exposure: Exposure) -> np.ndarray:
    """(H, W) the luma of the water's whole veil of backscatter (integrated to the
    table's far end, `lighting.backscatter_table`; within 0.3% of a pixel's own beyond
    13 m) through the lens and at a frame's exposure, before the black clamp: about the
    least a pixel beyond the lamps' reach can show, whatever lies behind it."""
    table = backscatter_table(config.camera, config.optics)
    rows = np.arange(config.camera.height) // table.block
    columns = np.arange(config.camera.width) // table.block
    veil = table.values[..., -1, :][np.ix_(rows, columns)] * lens_factor(config)[..., None]
    return (veil * exposure.gain * exposure.gains) @ np.asarray(LUMA)


@dataclass(frozen=True)
class BeyondFrame:
    """A frame looking beyond the lamps' reach: its near-black fraction, its pixels beyond
    the reach and how many of those are near black, the median there of the veil's luma
    (`veil_luma`) over the camera's black level, and the median range of the rock within
    the reach (what the camera exposes for), metres."""

    black: float
    far: int
    far_black: int
    veil: float
    lit_range: float


@dataclass
class Check:
    """Near-black pixels among those beyond and within the lamps' reach, summed; and each
    frame where the passage runs beyond the reach (at least `BEYOND_SHARE` of its pixels)."""

    beyond: int = 0
    beyond_black: int = 0
    within: int = 0
    within_black: int = 0
    frames_beyond: list[BeyondFrame] = field(default_factory=list)

    def add(
        self, frame: Frame, small_rgb: np.ndarray, exposure: Exposure, config: SensorConfig
    ) -> None:
        length = np.linalg.norm(config.camera.directions, axis=2)
        distance = frame.depth_m * length  # inf where the ray leaves the cave
        rock = np.isfinite(distance)
        far = downscale((rock & (distance > exposure.reach)).astype(np.float64)) == 1.0
        near = downscale((rock & (distance <= exposure.reach)).astype(np.float64)) == 1.0
        black = small_rgb.max(axis=2) < NEAR_BLACK
        self.beyond += int(far.sum())
        self.beyond_black += int((far & black).sum())
        self.within += int(near.sum())
        self.within_black += int((near & black).sum())
        if far.mean() >= BEYOND_SHARE:
            veil = downscale(veil_luma(config, exposure))[far] / config.optics.black_level
            lit = distance[rock & (distance <= exposure.reach)]
            self.frames_beyond.append(
                BeyondFrame(
                    float(black.mean()), int(far.sum()), int((far & black).sum()),
                    float(np.median(veil)), float(np.median(lit)) if lit.size else math.nan,
                )
            )  # fmt: skip

    def print_frames(self) -> None:
        """The frames looking beyond the reach, against the issue's aim; then split by
        whether the water's veil lies below the black clamp there."""
        seen = [f.black for f in self.frames_beyond]
        if not seen:
            return
        print(
            f"frames looking beyond the reach ({BEYOND_SHARE:.0%} of their pixels or more): "
            f"{len(seen)}; their near-black fraction {min(seen):.3f}-{max(seen):.3f}, "
            f"median {statistics.median(seen):.3f}; above the issue's {DARK_ENOUGH}: "
            f"{sum(fraction > DARK_ENOUGH for fraction in seen)}"
        )
        for label, below in (("below", True), ("above", False)):
            group = [f for f in self.frames_beyond if (f.veil < 1.0) == below]
            if not group:
                continue
            far, black = sum(f.far for f in group), sum(f.far_black for f in group)
            veils, lit = [f.veil for f in group], [f.lit_range for f in group]
            print(
                f"  the veil {label} the black level there ({min(veils):.2f}-{max(veils):.2f} "
                f"of it): {len(group)} frames, {black / far:.3f} of their {far:,} pixels "
                f"beyond the reach near black, {sum(f.black > DARK_ENOUGH for f in group)} "
                f"frames above {DARK_ENOUGH}; the lit rock's median range {min(lit):.1f}-"
                f"{max(lit):.1f} m"
            )


def sensed(
    poses: dict[str, list[Pose]], optics: Optics
) -> Iterator[tuple[Frame, np.ndarray, Exposure]]:
    """Every frame at ``poses`` with ``optics``: the frame, its 320x240 copy, and how the
    camera exposed it."""
    config = SensorConfig(optics=optics)
    for name, where in poses.items():
        rig = SensorRig(RayCaster(load_scenario(name, seed=0).mesh), config)
        for pose in where:
            frame = rig.render(pose, radiance=True)
            gains, gain = camera_response(metered_mean(frame, config), optics)
            yield (
                frame,
                downscale(frame.rgb),
                Exposure(gains, gain, lamp_reach(optics, gains, gain)),
            )


def measure(poses: dict[str, list[Pose]]) -> tuple[dict[str, list[FrameStats]], Check, list[float]]:
    """Statistics of every frame per water; the physical check and reaches in clear water."""
    stats: dict[str, list[FrameStats]] = {water: [] for water in CAVE_WATERS}
    check, reaches = Check(), []
    clear = SensorConfig(optics=Optics(water="clear"))
    for water in CAVE_WATERS:
        for frame, small, exposure in sensed(poses, Optics(water=water)):
            stats[water].append(frame_stats(small))
            if water == "clear":
                reaches.append(exposure.reach)
                check.add(frame, small, exposure, clear)
    return stats, check, reaches


def survey(poses: dict[str, list[Pose]], optics: Optics) -> tuple[list[FrameStats], list[float]]:
    """Statistics of every frame with ``optics``, and the lamps' reach in each frame."""
    frames = list(sensed(poses, optics))
    return [frame_stats(small) for _, small, _ in frames], [e.reach for _, _, e in frames]


def print_waters_and_beams(poses: dict[str, list[Pose]]) -> None:
    """Jerlov's water types, and turbid water under narrower lamps, on fewer frames."""
    count = sum(len(p) for p in poses.values())
    print(f"\nJerlov's water types (Jerlov 1976; `optics.jerlov_water`), {count} frames each")
    columns = ("mean_value", "near_black", "structure", "contrast")
    head = " ".join(f"{LABELS[k]:>22}" for k in columns)
    print(f"{'water':<11} {'c (R, G, B) 1/m':>19} {'reach m':>8} {head}")
    for name in JERLOV_KD:
        water = f"jerlov-{name}"
        frames, reaches = survey(poses, Optics(water=water))
        c = ", ".join(f"{v:.2f}" for v in WATER_TYPES[water].attenuation)
        cells = " ".join(
            f"{_fmt(k, statistics.fmean(getattr(f, k) for f in frames)):>22}" for k in columns
        )
        print(f"{water:<11} {c:>19} {statistics.median(reaches):>8.1f} {cells}")
    print("\nturbid water: the veil's contrast as the lamps' beams narrow (visible beams)")
    for beam in (90.0, 60.0, 30.0):
        frames, _ = survey(poses, Optics(water="turbid", lamp_beam_deg=beam))
        contrast = statistics.fmean(f.contrast for f in frames)
        print(f"beam {beam:>3.0f} degrees: RMS contrast of luma {contrast:.3f}")


def _fmt(key: str, value: float | None) -> str:
    return "-" if value is None else f"{value:.{DIGITS.get(key, 2)}f}"


def print_preset(water: str, frames: list[FrameStats]) -> None:
    print(f"\n{water} water: {len(frames)} frames")
    print(f"{'statistic':<25} {'mean':>7} {'sd':>7} {'min':>7} {'max':>7}   real (U45)")
    for statistic in fields(FrameStats):
        key = statistic.name
        values = [getattr(f, key) for f in frames]
        real = REAL[key]
        real_text = _fmt(key, real.mean) + (f" (sd {_fmt(key, real.sd)})" if real.sd else "")
        real_text += f", {real.note}" if real.note else ""
        row = [statistics.fmean(values), statistics.pstdev(values), min(values), max(values)]
        print(
            f"{LABELS[key]:<25} " + " ".join(f"{_fmt(key, v):>7}" for v in row) + f"   {real_text}"
        )


def print_summary(stats: dict[str, list[FrameStats]]) -> None:
    print("\nmean over frames (sd), every water, beside the real photographs")
    print(f"{'statistic':<25} " + " ".join(f"{w:>15}" for w in stats) + f" {'real':>7}")
    for statistic in fields(FrameStats):
        key = statistic.name
        cells = []
        for frames in stats.values():
            values = [getattr(f, key) for f in frames]
            cells.append(
                f"{_fmt(key, statistics.fmean(values))} ({_fmt(key, statistics.pstdev(values))})"
            )
        print(
            f"{LABELS[key]:<25} "
            + " ".join(f"{c:>15}" for c in cells)
            + f" {_fmt(key, REAL[key].mean):>7}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--poses", type=int, default=5, help="poses per scenario")
    args = parser.parse_args()
    start = time.perf_counter()
    poses = {
        name: [pose for pose, _ in passage_poses(load_scenario(name, seed=0), args.poses)]
        for name in SCENARIOS
    }
    stats, check, reaches = measure(poses)
    print(f"frames of {', '.join(SCENARIOS)} (seed 0), {args.poses} poses each along the "
          "geometric pilot's path, 640x480 measured at 320x240")  # fmt: skip
    for water, frames in stats.items():
        print_preset(water, frames)
    print_summary(stats)
    print(
        f"\nclear water, the lamps' reach (near-black level {NEAR_BLACK}, per frame's exposure): "
        f"{min(reaches):.1f}-{max(reaches):.1f} m, median {statistics.median(reaches):.1f} m"
    )
    for label, total, black in (
        ("beyond the reach", check.beyond, check.beyond_black),
        ("within the reach", check.within, check.within_black),
    ):
        share = f"{black / total:.3f}" if total else "- (no such pixels)"
        print(f"near-black fraction of rock pixels {label}: {share} of {total:,} pixels")
    check.print_frames()
    print_waters_and_beams(
        {name: where[len(where) // 2 : len(where) // 2 + 1] for name, where in poses.items()}
    )
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()

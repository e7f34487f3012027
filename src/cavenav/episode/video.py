"""Episode videos: what the vehicle saw beside where it was, one frame per step.

Each frame puts the step's colour image, its depth PNG and a top-down map side by side,
each panel 480 px high (`PANEL_HEIGHT`), above a caption line (step, action, clearance),
with the pilot's justification over the top of the colour image:
for the default 640x480 camera a frame is 1760 x 512 px (640 + 640 + 480 wide,
480 + 32 high). The map shows the cave's footprint when the scenario can be rebuilt from
summary.json (S1-S5, by name, seed and difficulty), else the path alone, with the exits,
the whole path faintly, the path flown so far coloured by clearance and the vehicle as an
arrow along its heading.

An episode flown with an imaging sonar (its steps' ``sonar_png``) shows the sonar's image
too, between the depth and the map, grey as the device's software draws it: a
multibeam's 726 x 400 fan is 871 px wide at the panel height, a Ping360's disc 480.

The map background is drawn once with matplotlib; each frame only draws the vehicle and
its path into a copy of it, through the axes' data-to-pixel mapping taken once, so a
150-step episode encodes in seconds. Frames are H.264 (yuv420p), through the ffmpeg that
imageio-ffmpeg ships, into a temporary beside the MP4 that is renamed into place once
whole (`cavenav.core.files.write_then_rename`) and only if ffmpeg ended well: a full disk
leaves no part of a video.

A frame image that is missing or cannot be read (cut short, not an image) is shown as a
grey panel, with a one-line warning naming the step and the file: the rest of the episode
is still worth watching, and its map and caption are still right.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import math
import os
import subprocess
import tempfile
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from cavenav.core.errors import (
    CavenavError,
    CavenavWarning,
    ConfigError,
    DependencyError,
    RecordingError,
)
from cavenav.core.files import not_a_file_to_replace, write_then_rename
from cavenav.episode.records import EpisodeSummary, StepRecord, load_steps, load_summary

if TYPE_CHECKING:
    from cavenav.world.scenarios import ExitPortal

__all__ = ["CAPTION_HEIGHT", "PANEL_HEIGHT", "REASON_LINES", "REASON_TOP", "write_video"]

PANEL_HEIGHT = 480  # px: the camera's default height, so its images are not resampled
CAPTION_HEIGHT = 32  # px: one line of 17 px text; 480 + 32 = 512, a multiple of 16
REASON_LINES = 4  # of the pilot's justification, over the top of the colour image
REASON_TOP = 28  # px: under the panel's label
_CMAP = "viridis"  # clearance colours, as in topdown.png (episode/plots.py)
_CLEARANCE_MAX_M = 3.0  # top of the colour scale, as in topdown.png for calm episodes
_MARGIN_M = 3.0  # map margin around the path and the exits
_IMAGES = ("rgb", "depth_png")  # the frames/ files shown, left to right
_SONAR = "sonar_png"  # shown after them in an episode that kept a sonar's images
_LABELS = {"rgb": "colour", "depth_png": "depth (dark = near)", _SONAR: "sonar (bright = echo)"}


@dataclass(frozen=True)
class MapCanvas:
    """A top-down map drawn once: its pixels and the affine data-to-pixel mapping.

    Attributes:
        image: (h, w, 3) uint8.
        affine: (2, 3) float: ``[col, row] = affine @ [x, y, 1]`` for world metres.
    """

    image: np.ndarray
    affine: np.ndarray

    def pixels(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) world x, y in metres -> (n, 2) float image column, row."""
        xy = np.atleast_2d(np.asarray(xy, np.float64))
        return xy @ self.affine[:, :2].T + self.affine[:, 2]


def _rebuild_scenario(summary: EpisodeSummary | Mapping[str, Any]) -> Any:
    """The flown cave, rebuilt from its name, seed and difficulty; None where it cannot be.

    Only the procedural families rebuild from a name. The rebuilt mesh must carry the
    recorded mesh name (which encodes the difficulty), so a map never shows another cave.

    Args:
        summary: summary.json as `load_summary` reads it, or its JSON object.
    """
    from cavenav.world.scenarios import SCENARIOS, Difficulty, load_scenario

    if not isinstance(summary, EpisodeSummary):
        summary = EpisodeSummary.model_validate(summary)
    name, seed = summary.scenario, summary.seed
    if name is None or name not in SCENARIOS or seed is None:
        return None
    try:
        knobs = summary.difficulty or {}
        kwargs = {"difficulty": Difficulty.from_dict(knobs)} if knobs else {}
        scenario = load_scenario(name, seed, **kwargs)
    except (CavenavError, TypeError, ValueError):
        return None
    return scenario if scenario.mesh.name == summary.mesh else None


def _map_limits(points: np.ndarray, exits: Sequence[ExitPortal]) -> np.ndarray:
    """[[xmin, xmax], [ymin, ymax]]: a square around the path and the exits."""
    xy = [points[:, :2]] + [np.asarray(e.point, np.float64)[None, :2] for e in exits]
    every = np.concatenate(xy)
    lo, hi = every.min(axis=0) - _MARGIN_M, every.max(axis=0) + _MARGIN_M
    centre, half = 0.5 * (lo + hi), 0.5 * max(float((hi - lo).max()), 10.0)
    return np.stack([centre - half, centre + half], axis=1)


def _draw_map(
    positions: np.ndarray,
    exits: Sequence[ExitPortal],
    scenario: Any | None,
    size_px: int = PANEL_HEIGHT,
) -> MapCanvas:
    """The map background of a video: footprint (if ``scenario``), exits, whole path faint.

    Args:
        positions: (n, 3) float, every pose of the episode in metres.
        exits: the exits summary.json records.
        scenario: the rebuilt `Scenario`, or None for the path alone.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from cavenav.episode.plots import draw_exits, draw_footprint

    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.1, 0.07, 0.87, 0.9))
    if scenario is not None:  # the cave's footprint, as topdown.png draws it
        draw_footprint(ax, scenario.mesh)
    else:
        ax.set_facecolor("#f2f4f7")
        ax.text(
            0.02,
            0.02,
            "path only (cave not rebuilt)",
            transform=ax.transAxes,
            fontsize=7,
            color="0.45",
        )
    draw_exits(ax, exits)
    ax.plot(positions[:, 0], positions[:, 1], color="0.6", lw=1, ls=":", zorder=3)
    ax.plot(*positions[0, :2], marker="o", color="tab:green", ms=7, zorder=5)
    limits = _map_limits(positions, exits)
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_aspect("equal", adjustable="box")
    ax.tick_params(labelsize=7, length=2, pad=1)
    ax.set_xlabel("x (m)", fontsize=7, labelpad=1)
    ax.set_ylabel("y (m)", fontsize=7, labelpad=1)
    canvas.draw()
    image = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    # Display coordinates have their origin at the bottom left; image rows run down.
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    display = ax.transData.transform(corners)
    height = image.shape[0]
    pix = np.column_stack([display[:, 0], height - display[:, 1]])
    affine = np.column_stack([pix[1] - pix[0], pix[2] - pix[0], pix[0]])
    return MapCanvas(image, affine)


def _viridis(values: np.ndarray) -> list[tuple[int, int, int]]:
    from matplotlib import colormaps

    rgba = colormaps[_CMAP](np.clip(values / _CLEARANCE_MAX_M, 0.0, 1.0))
    return [(int(255 * r), int(255 * g), int(255 * b)) for r, g, b, _ in rgba]


def _map_frame(
    canvas: MapCanvas,
    pixels: np.ndarray,
    colours: Sequence[tuple[int, int, int]],
    k: int,
    yaw_deg: float,
    crash: np.ndarray | None,
) -> Image.Image:
    """The map at step ``k``: path so far in clearance colours, the vehicle as an arrow.

    Args:
        pixels: (n, 2) image coordinates of every pose; colours: one per pose.
        crash: image coordinates of the collision point when it happened at this step.
    """
    image = Image.fromarray(canvas.image)
    draw = ImageDraw.Draw(image)
    for j in range(1, k + 1):
        draw.line([tuple(pixels[j - 1]), tuple(pixels[j])], fill=colours[j], width=3)
    psi = math.radians(yaw_deg)
    heading = canvas.affine[:, :2] @ np.array([math.sin(psi), -math.cos(psi)])  # Pose.forward
    heading /= max(float(np.linalg.norm(heading)), 1e-9)
    side = np.array([-heading[1], heading[0]])
    tip = pixels[k] + 11 * heading
    arrow = [tip, pixels[k] - 6 * heading + 6 * side, pixels[k] - 6 * heading - 6 * side]
    draw.polygon([tuple(p) for p in arrow], fill=(214, 39, 40), outline=(0, 0, 0))
    if crash is not None:
        x, y = crash
        for d in (1, -1):
            draw.line([(x - 7, y - 7 * d), (x + 7, y + 7 * d)], fill=(214, 39, 40), width=4)
    return image


# What reading a frame image can raise: missing or unreadable (OSError, PIL's
# UnidentifiedImageError among them), or too many pixels to decode safely.
_UNREADABLE = (OSError, Image.DecompressionBombError)


def _panel(run_dir: Path, step: StepRecord, key: str, width: int) -> Image.Image:
    """The step's frame ``key`` scaled to the panel, or a grey panel where it has none or
    it cannot be read (with a warning naming the step and the file)."""
    name = step.frames.get(key)
    if name is not None:
        try:
            with Image.open(run_dir / name) as image:
                frame = image.convert("RGB")
            return frame.resize((width, PANEL_HEIGHT), Image.Resampling.BILINEAR)
        except _UNREADABLE as exc:
            why = "is missing" if isinstance(exc, FileNotFoundError) else f"cannot be read ({exc})"
            warnings.warn(
                f"{run_dir}: step {step.step}: {name} {why}; shown as a grey panel",
                CavenavWarning,
                stacklevel=2,
            )
    return Image.new("RGB", (width, PANEL_HEIGHT), (60, 60, 60))


def _panel_width(run_dir: Path, steps: Sequence[StepRecord], key: str) -> int:
    """The width of the episode's frames ``key`` once scaled to the panel height, read
    from the first that can be read (640, the default camera's, when none can)."""
    for step in steps:
        name = step.frames.get(key)
        if name is None:
            continue
        try:
            with Image.open(run_dir / name) as image:
                return round(image.width * PANEL_HEIGHT / image.height)
        except _UNREADABLE:
            continue  # warned of when its frame is drawn
    return 640


def _shown(steps: Sequence[StepRecord]) -> tuple[str, ...]:
    """The frames/ files shown, left to right: the sonar's after the camera's where any
    step kept one (a step without it is a grey panel), so that an episode without a
    sonar is drawn exactly as before sonars were carried."""
    return (*_IMAGES, _SONAR) if any(_SONAR in s.frames for s in steps) else _IMAGES


def _label(step: StepRecord, key: str) -> str:
    """A panel's label; the sonar's names its kind (a fan or a disc) where recorded."""
    kind = (step.sonar or {}).get("kind") if key == _SONAR else None
    return f"{kind} {_LABELS[key]}" if kind else _LABELS[key]


def _caption(step: StepRecord, count: int) -> str:
    def metres(value: float | None) -> str:  # null where the record holds no finite value
        return "-" if value is None else f"{value:.2f}"

    parts = [
        f"step {step.step}/{count - 1}",
        step.action if step.action is not None else "no action (pilot failure)",
        f"clearance {metres(step.clearance_m)} m",
        f"top {metres(step.d_top_m)} m, bottom {metres(step.d_bottom_m)} m",
    ]
    if step.shield:
        parts.append(f"shield replaced {step.shield.get('proposed')}")
    if step.invalid_action:
        parts.append("invalid action: held")
    if step.collision:
        parts.append("COLLISION")
    return "  ·  ".join(parts)


def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """DejaVu Sans, which matplotlib ships, so captions look the same everywhere."""
    from matplotlib import font_manager

    try:
        return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)
    except OSError:
        return ImageFont.load_default()


def _frames(
    run_dir: Path, steps: Sequence[StepRecord], summary: EpisodeSummary
) -> Iterator[np.ndarray]:
    """Yield one (h, w, 3) uint8 frame per step (each with a pose), every frame the same
    even size."""
    from cavenav.world.scenarios import ExitPortal

    poses = [s.pose for s in steps if s.pose is not None]
    positions = np.array([[p.x, p.y, p.z] for p in poses])
    exits = [ExitPortal(e.point, e.normal, e.radius) for e in summary.exits]
    canvas = _draw_map(positions, exits, _rebuild_scenario(summary))
    pixels = canvas.pixels(positions[:, :2])
    colours = _viridis(np.array([s.clearance_m or 0.0 for s in steps], np.float64))
    keys = _shown(steps)
    widths = [_panel_width(run_dir, steps, key) for key in keys]
    widths.append(canvas.image.shape[1])
    width = sum(widths) + sum(widths) % 2  # H.264 with yuv420p needs even sizes
    height = PANEL_HEIGHT + CAPTION_HEIGHT
    font, small = _font(17), _font(13)
    for k, (step, pose) in enumerate(zip(steps, poses, strict=True)):
        frame = Image.new("RGB", (width, height), (16, 16, 16))
        x = 0
        draw = ImageDraw.Draw(frame)
        for key, w in zip(keys, widths, strict=False):
            frame.paste(_panel(run_dir, step, key, w), (x, 0))
            draw.text(
                (x + 8, 6),
                _label(step, key),
                fill="white",
                font=small,
                stroke_width=2,
                stroke_fill="black",
            )
            x += w
        crash = None
        if step.collision and step.next_pose:
            crash = canvas.pixels(np.array([[step.next_pose.x, step.next_pose.y]]))[0]
        frame.paste(_map_frame(canvas, pixels, colours, k, pose.yaw_deg, crash), (x, 0))
        colour = (255, 110, 110) if step.collision else (235, 235, 235)
        draw.text((10, PANEL_HEIGHT + 6), _caption(step, len(steps)), fill=colour, font=font)
        if step.justification:
            _overlay_reason(frame, step.justification, widths[0], small)
        yield np.asarray(frame)


def _overlay_reason(frame: Image.Image, text: str, width: int, font: Any) -> None:  # noqa: ANN401
    """The pilot's justification across the top of the colour panel, under its label (a
    player's controls cover the foot), on a darkened band, wrapped to its width, at most
    `REASON_LINES` lines (the last cut with an ellipsis)."""
    lines: list[str] = []
    for word in f"why: {' '.join(text.split())}".split(" "):
        if lines and font.getlength(f"{lines[-1]} {word}") <= width - 16:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    if len(lines) > REASON_LINES:
        lines = [*lines[: REASON_LINES - 1], lines[REASON_LINES - 1] + " …"]
    top = REASON_TOP
    band = frame.crop((0, top - 4, width, top + 17 * len(lines) + 4))
    frame.paste(Image.blend(band, Image.new("RGB", band.size), 0.6), (0, top - 4))
    draw = ImageDraw.Draw(frame)
    for k, line in enumerate(lines):
        draw.text((8, top + 17 * k), line, fill=(245, 245, 245), font=font)


def _ffmpeg() -> str:
    """The ffmpeg that imageio-ffmpeg ships, or the install hint."""
    try:
        import imageio_ffmpeg
    except ImportError:
        raise DependencyError(
            "writing videos needs imageio-ffmpeg: pip install imageio-ffmpeg"
        ) from None
    return imageio_ffmpeg.get_ffmpeg_exe()


# Why ffmpeg could not write the MP4, as the system says it, looked for in its account.
_WRITE_FAULTS = tuple(
    os.strerror(code) for code in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EIO)
)


def _encode(path: Path, frames: Iterator[np.ndarray], fps: float) -> None:
    """Encode ``frames`` (every one the same size) into the MP4 at ``path``.

    ffmpeg runs here rather than through imageio-ffmpeg's frame writer, which never looks
    at how ffmpeg ended: x264 holds a short episode back until the input closes, so a full
    disk shows only in ffmpeg's exit status, after the last frame was handed over.

    Raises:
        OSError: the file cannot be made, or ffmpeg failed (its reason, in one line).
    """
    path.touch()  # a folder that refuses the file fails here, before ffmpeg says it at length
    first = next(frames)
    height, width = first.shape[:2]
    command = [
        _ffmpeg(),
        "-y",
        "-v", "error",
        "-f", "rawvideo",
        "-vcodec", "rawvideo",
        "-pix_fmt", "rgb24",
        "-s", f"{width}x{height}",
        "-r", str(Fraction(fps).limit_denominator()),
        "-i", "-",
        "-an",
        "-vcodec", "libx264",
        "-pix_fmt", "yuv420p",
        # Legible text, quick encoding; MP4 named, as the temporary's name does not say it.
        "-crf", "23", "-preset", "veryfast",
        "-f", "mp4",
        str(path),
    ]  # fmt: skip
    with tempfile.TemporaryFile() as account:  # a file, not a pipe: ffmpeg never blocks on it
        ffmpeg = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=account
        )
        assert ffmpeg.stdin is not None
        try:
            # Closing stdin ends ffmpeg's input; a broken pipe means ffmpeg gave up, and
            # its exit status says why.
            with contextlib.suppress(BrokenPipeError), ffmpeg.stdin:
                for frame in itertools.chain([first], frames):
                    ffmpeg.stdin.write(np.ascontiguousarray(frame, np.uint8).tobytes())
        except BaseException:
            ffmpeg.kill()
            ffmpeg.wait()
            raise
        status = ffmpeg.wait()
        if status != 0:
            account.seek(0)
            raise OSError(_ffmpeg_reason(account.read().decode(errors="replace"), status))


def _ffmpeg_reason(account: str, status: int) -> str:
    """ffmpeg's many-line account of a failure as one reason: the system's words where
    it gives them ("No space left on device"), else its first line."""
    fault = next((fault for fault in _WRITE_FAULTS if fault in account), None)
    lines = account.strip().splitlines()
    return fault or f"ffmpeg failed (exit status {status}): {lines[0] if lines else 'no account'}"


def _output(out: Path) -> Path:
    """``out`` checked to be a file that can be made: not a folder, under no file.

    Raises:
        ConfigError: ``out`` is a folder or no regular file (/dev/full), or a file
            stands where a folder above it should.
        RecordingError: its folder cannot be made (a read-only folder).
    """
    if out.is_dir():
        raise ConfigError(f"{out} is a folder: name the MP4 to write, e.g. {out / 'episode.mp4'}")
    why = not_a_file_to_replace(out)
    if why:
        raise ConfigError(f"cannot write {out}: {why}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError.cannot_write(out, exc) from None
    return out


def write_video(run_dir: Path, out: Path | None = None, fps: float = 4.0) -> Path:
    """Write an MP4 of the episode in ``run_dir``, one frame per step; returns its path.

    Each frame: colour image | depth PNG | (the sonar's image, where the episode kept
    one) | top-down map with the vehicle's position, heading and path so far, above a
    caption (step, action, clearance, echo sounders). 1760 x 512 px for the default
    640 x 480 camera without a sonar (see the module docstring).

    Args:
        out: the MP4 to write (default ``run_dir/episode.mp4``).
        fps: steps shown per second.

    A frame image that is missing or cannot be read is a grey panel, with a warning
    naming the step (see the module docstring).

    Raises:
        CavenavError: no run folder, or it holds no frames (flown with frames off).
        RecordError: its summary.json or steps.jsonl is damaged (naming the field).
        ConfigError: ``out`` is a folder, or lies under a file.
        RecordingError: ``out`` cannot be written (a read-only folder, a full disk, ffmpeg
            failing); no part of a video is left behind.
        DependencyError: imageio-ffmpeg is not installed (the message has the command).
    """
    run_dir = Path(run_dir)
    if not (run_dir / "summary.json").is_file() or not (run_dir / "steps.jsonl").is_file():
        raise CavenavError(f"{run_dir} is no run folder (no summary.json or steps.jsonl)")
    summary = load_summary(run_dir / "summary.json")
    steps = [s for s in load_steps(run_dir / "steps.jsonl") if s.pose is not None]
    if not any(s.frames for s in steps):
        raise CavenavError(
            f"{run_dir} holds no frames: a video needs the episode flown with frames saved "
            "(cavenav run without --no-frames; cavenav eval --frames png or all)"
        )
    out = _output(Path(out) if out is not None else run_dir / "episode.mp4")
    frames = _frames(run_dir, steps, summary)
    try:
        write_then_rename(out, lambda tmp: _encode(tmp, frames, fps))
    except OSError as exc:
        raise RecordingError.cannot_write(out, exc) from None
    return out

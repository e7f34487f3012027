"""Photographs from outside the simulator (a phone, a GoPro, a dive camera) as observations.

`cavenav ask` sends one such photograph to a model. Three things separate it from a
rendered frame, and each used to go wrong silently:

- Size. A phone writes 8000x6000 pixels; sent as is, that is one 107 MB request, of
  which the model keeps a small fraction. `model_size` shrinks an image to what a
  vision model takes in (OpenAI's documented rule for high-detail images), before it is
  encoded, and the caller says so.
- Orientation. Phones store the sensor's pixels and an EXIF tag that says how to turn
  them upright; the model must see the picture the way the diver saw it.
- Depth. A photograph usually has none. It is then not replaced by a blank image (white
  reads as "nothing within D_max", the most dangerous lie there is): the observation
  says that it has no depth (`Observation.has_depth`), and the VLM pilot sends no depth
  image and tells the model to judge distances without one.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import ExifTags, Image, ImageOps, UnidentifiedImageError

from cavenav.core.errors import CavenavError
from cavenav.core.types import Observation
from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.depth import DEPTH_RANGE_M, denormalise_depth, unknown_depth

__all__ = ["HIGH_DETAIL_FIT", "LOW_DETAIL_FIT", "load_photo", "model_size", "shrink_depth"]

# OpenAI's vision guide, "Calculating costs" for GPT-4o-class models: a high-detail image
# is first scaled to fit within 2048 x 2048, then so that its shortest side is 768 px;
# the model never sees more. Anthropic's limit (1568 px on the long side, about 1.15
# megapixels) and OpenAI's newer patch budget (1536 patches of 32 x 32 px) both admit
# the result, so one rule serves every backend `ask` can talk to. (longest fit, short side)
HIGH_DETAIL_FIT = (2048, 768)
# A low-detail image is one 512 x 512 view of the whole picture.
LOW_DETAIL_FIT = (512, 512)

# Pillow modes of 8-bit images, which convert to grey without losing what they mean; a
# 16-bit or float image (a depth camera's raw millimetres) would clip to white.
_EIGHT_BIT_MODES = frozenset({"1", "L", "LA", "P", "PA", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr"})
# EXIF orientations 5-8 turn the picture by 90 degrees: width and height swap.
_QUARTER_TURNS = frozenset({5, 6, 7, 8})


def model_size(width: int, height: int, detail: str | None = None) -> tuple[int, int]:
    """(width, height) a vision model takes in of a ``width`` x ``height`` image.

    Only ever shrinks, keeping the aspect ratio: an image already small enough, like the
    simulator's 640 x 480 frames, is returned unchanged.

    Args:
        detail: the image detail of the request; "low" fits within 512 x 512, anything
            else (None, "auto", "high") follows `HIGH_DETAIL_FIT`.
    """
    if detail == "low":
        factor = min(1.0, LOW_DETAIL_FIT[0] / max(width, height))
    else:
        longest, short = HIGH_DETAIL_FIT
        factor = min(1.0, longest / max(width, height))  # fit within 2048 x 2048,
        factor = min(factor, short / min(width, height))  # then the short side to 768
    if factor >= 1.0:
        return width, height
    return max(1, round(width * factor)), max(1, round(height * factor))


def shrink_depth(depth_png: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w) uint8 depth image reduced to ``size`` = (w, h), each pixel the nearest
    (darkest) of the block it covers.

    Neither of the usual choices is safe for depth. Nearest-neighbour keeps one pixel in
    eight of an 8000-pixel-wide map, so a rock pillar a few pixels wide can vanish; a box
    filter averages a wall at 1 m with open water at 20 m into a surface at 10 m that does
    not exist. The minimum keeps every obstacle, at worst one output pixel wider, which
    errs on the side a pilot wants.

    Args:
        depth_png: (H, W) uint8, dark = near; H >= h and W >= w.
    """
    w, h = size
    rows = np.arange(h) * depth_png.shape[0] // h  # block starts: a partition of the rows
    cols = np.arange(w) * depth_png.shape[1] // w
    return np.minimum.reduceat(np.minimum.reduceat(depth_png, rows, axis=0), cols, axis=1)


def _open(path: Path) -> Image.Image:
    try:
        return Image.open(path)
    except (OSError, UnidentifiedImageError) as exc:
        raise CavenavError(f"cannot read image {path}: {exc}") from None
    except Image.DecompressionBombError:  # Pillow's guard: its pixels would fill the memory
        raise CavenavError(
            f"cannot read image {path}: over {2 * (Image.MAX_IMAGE_PIXELS or 0):,} pixels, beyond "
            "Pillow's guard against decompression bombs; shrink it first"
        ) from None


def _upright_size(image: Image.Image) -> tuple[tuple[int, int], int]:
    """The size as the picture is meant to be seen, and its EXIF orientation (1 = as stored)."""
    try:
        exif = image.getexif()  # reads on: a truncated file fails here
    except (OSError, SyntaxError, ValueError) as exc:
        where = getattr(image, "filename", "")  # the file an image was opened from
        raise CavenavError(f"cannot read image {where}: {exc}") from None
    orientation = int(exif.get(ExifTags.Base.Orientation, 1) or 1)
    width, height = image.size
    return ((height, width) if orientation in _QUARTER_TURNS else (width, height)), orientation


def _decode(image: Image.Image, path: Path, mode: str, size: tuple[int, int]) -> np.ndarray:
    """Pixels of ``image`` upright, in ``mode``, at ``size``; JPEGs decode straight at a
    fraction of their size (Pillow's draft mode), so 48 megapixels never sit in memory."""
    try:
        if image.format == "JPEG" and size != image.size:
            _, orientation = _upright_size(image)
            image.draft(mode, size[::-1] if orientation in _QUARTER_TURNS else size)
        upright = ImageOps.exif_transpose(image).convert(mode)
        if upright.size != size:
            upright = upright.resize(size, Image.Resampling.LANCZOS, reducing_gap=3.0)
        return np.asarray(upright)
    except (OSError, ValueError) as exc:  # truncated or corrupt pixel data
        raise CavenavError(f"cannot read image {path}: {exc}") from None


def _depth(
    path: Path, image: Path, upright: tuple[int, int], orientation: int, target: tuple[int, int]
) -> np.ndarray:
    """The depth image at ``path`` for the colour image ``image`` of ``upright`` size, at
    ``target`` size; refused unless it is 8-bit and of the colour image's size."""
    with _open(path) as depth:
        size, _ = _upright_size(depth)
        if size != upright:
            raise CavenavError(
                f"depth image {path} is {_size(size)} but the colour image {image} is "
                f"{_size(upright)}{' upright' if orientation != 1 else ''}: give a depth "
                "image of the same view at the same size"
            )
        if depth.mode not in _EIGHT_BIT_MODES:
            raise CavenavError(
                f"depth image {path} is {depth.mode} (more than 8 bits per pixel, raw "
                f"distances?): give it as 8-bit grey, 0 = {DEPTH_RANGE_M[0]:g} m, "
                f"255 = {DEPTH_RANGE_M[1]:g} m or farther"
            )
        pixels = _decode(depth, path, "L", upright)
    return pixels if target == upright else shrink_depth(pixels, target)


def _reading(value: float | None, name: str) -> float:
    """An echo-sounder range in metres, NaN when not measured."""
    if value is None:
        return math.nan
    if not (math.isfinite(value) and value >= 0):
        raise CavenavError(f"{name} = {value} m: a range is a distance, 0 m or more")
    return float(value)


def load_photo(
    image: str | Path,
    depth: str | Path | None = None,
    *,
    d_top: float | None = None,
    d_bottom: float | None = None,
    detail: str | None = None,
) -> tuple[Observation, list[str]]:
    """A photograph (and its depth image, if any) as an Observation a VLM pilot can send.

    The colour image is turned upright as its EXIF orientation says and shrunk to
    `model_size`; a depth image must show the same view at the same size (compared
    upright, before shrinking) and is shrunk with it by `shrink_depth`.

    Args:
        image: a colour photograph (PNG, JPEG, ...).
        depth: a depth image of the same view, 8-bit grey, dark near and bright far over
            `DEPTH_RANGE_M`; None when there is none (the observation then says so).
        d_top: the upward echo-sounder range in metres, None when not measured (NaN in
            the observation, "unknown" in the request); d_bottom: the downward one.
        detail: the image detail the request will ask for (see `model_size`).

    Returns:
        The observation (field of view and depth range of the simulator's camera, which
        is all `ask` knows of a foreign one), and one line for each thing done to the
        images on the way, for the caller to print.

    Raises:
        CavenavError: an unreadable image, a depth image of another size than the
            colour image or not 8-bit, or a negative or non-finite sounder reading.
    """
    image, notes = Path(image), []
    top, bottom = _reading(d_top, "d_top"), _reading(d_bottom, "d_bottom")
    with _open(image) as photo:
        upright, orientation = _upright_size(photo)
        target = model_size(*upright, detail)
        # The depth image first: a mismatch is refused before 48 megapixels are decoded.
        depth_png = (
            None if depth is None else _depth(Path(depth), image, upright, orientation, target)
        )
        rgb = _decode(photo, image, "RGB", target)
    if orientation != 1:
        notes.append(f"turned {image.name} upright, as its EXIF orientation ({orientation}) says")
    if target != upright:
        what = f"{image.name}{' and its depth image' if depth_png is not None else ''}"
        notes.append(f"resized {what} {_size(upright)} -> {_size(target)} (what the model can use)")
    if depth_png is None:
        notes.append("no depth image: the request tells the model to judge distances without one")
    depth_m, depth_shown = _depth_arrays(depth_png, target)
    observation = Observation(
        rgb=rgb,
        depth_m=depth_m,
        depth_png=depth_shown,
        d_top=top,
        d_bottom=bottom,
        depth_range=DEPTH_RANGE_M,
        hfov_deg=CameraIntrinsics().hfov_deg,
        has_depth=depth_png is not None,
    )
    return observation, notes


def _depth_arrays(
    depth_png: np.ndarray | None, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Depth in metres and as shown, (height, width) for ``size`` = (width, height).

    Without a depth image, `unknown_depth`'s.
    """
    if depth_png is None:
        return unknown_depth(*size[::-1])
    return denormalise_depth(depth_png, *DEPTH_RANGE_M), depth_png


def _size(size: tuple[int, int]) -> str:
    return f"{size[0]}x{size[1]}"

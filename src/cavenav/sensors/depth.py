"""Depth images: normalisation for the VLM, and the files frames are written to.

SPEC section 2: ``D_norm = (D_raw - D_min) / (D_max - D_min)`` clipped to [0, 1], written
as 8 bits, dark = near, bright = far; a ray that hits nothing counts as D_max.

File settings, chosen by measurement: the 73 frames of `cavenav run S4` (640x480, 2 cores),
mean time and size per frame:

| file | chosen: time, size | other settings measured |
| --- | --- | --- |
| colour PNG | fpng: 2.0 ms, 343 kB | Pillow at zlib level 1, run-length: 17.5 ms, 266 kB |
| depth PNG | zlib level 1, run-length: 5 ms, 40 kB | level 1: 6 ms, 44 kB; 6: 14 ms, 28 kB |
| depth EXR | no compression: 6 ms, 1237 kB | ZIP: 22 ms, 998 kB; HTJ2K: 11 ms, 402 kB |

Colour timings are of scenario set 4's frames (set 1's noisier ones took Pillow 36 ms,
770 kB; level 0: 21 ms, 922 kB). QOI (imagecodecs) took 2.7 ms and 431 kB, but no
browser shows it, and lossless WebP at its fastest 50 ms and 233 kB. So colour frames go
through fpng (Rich Geldreich's PNG writer, a deflate coder made for images), which
writes a standard PNG that every reader opens in a ninth of the time of zlib's fastest
setting, for a fifth more bytes: the writer thread that saves frames shares two cores
with the ray cast, so its time is the loop's. For the grey depth image (fpng writes
colour only), run-length coding (zlib's Z_RLE, no string search) gets as small as level
6, faster. ZIP saves a fifth of an EXR for three times the time, on a step whose
encoding already competes with the ray cast for two cores; HTJ2K, lossless and a third
of the size, is an option (`EXR_COMPRESSIONS`, ``--exr-compression``) rather than the
default because readers built on OpenEXR before 3.4 (OpenCV, Blender 4) cannot open it.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Literal

import numpy as np

__all__ = [
    "DEPTH_RANGE_M",
    "EXR_COMPRESSIONS",
    "denormalise_depth",
    "normalise_depth",
    "pixel_slopes",
    "read_exr",
    "save_png",
    "write_exr",
]

# (D_min, D_max) of SPEC section 2, metres: the one default every layer reads.
DEPTH_RANGE_M = (0.0, 20.0)


def normalise_depth(
    depth_m: np.ndarray, d_min: float = DEPTH_RANGE_M[0], d_max: float = DEPTH_RANGE_M[1]
) -> np.ndarray:
    """(H, W) float metres (``inf`` = no hit) -> (H, W) uint8, 0 at D_min, 255 at D_max."""
    if not d_max > d_min:
        raise ValueError(f"D_max ({d_max}) must exceed D_min ({d_min})")
    norm = (np.nan_to_num(depth_m, nan=d_max, posinf=d_max) - d_min) / (d_max - d_min)
    return np.round(np.clip(norm, 0.0, 1.0) * 255.0).astype(np.uint8)


def unknown_depth(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The depth arrays of an observation with no depth image (`Observation.has_depth`
    False): metres "unknown" (NaN) and the PNG "touching" (0), so that a reader that
    ignores the flag sees no free space rather than open water."""
    return np.full((height, width), np.nan, np.float32), np.zeros((height, width), np.uint8)


def denormalise_depth(
    depth_png: np.ndarray, d_min: float = DEPTH_RANGE_M[0], d_max: float = DEPTH_RANGE_M[1]
) -> np.ndarray:
    """Inverse of `normalise_depth` up to 8-bit quantisation: (H, W) uint8 -> float32 metres."""
    return (d_min + depth_png.astype(np.float32) / 255.0 * (d_max - d_min)).astype(np.float32)


def pixel_slopes(
    shape: tuple[int, int],
    hfov_deg: float,
    stride: int,
    first: int = 0,
    dtype: type[np.floating] = np.float32,
) -> tuple[np.ndarray, np.ndarray]:
    """Leftward and upward metres per metre of planar depth at every ``stride``-th pixel
    of an (H, W) image from ``first``: multiplied by the depth there, a pixel's point in
    the camera frame (forward, left, up), square pixels of a pinhole of ``hfov_deg``."""
    h, w = shape
    focal = 0.5 * w / math.tan(math.radians(hfov_deg) / 2)
    v, u = np.mgrid[first:h:stride, first:w:stride].astype(dtype) + 0.5
    return -(u - 0.5 * w) / focal, -(v - 0.5 * h) / focal


ExrCompression = Literal["none", "zip", "htj2k"]
# The OpenEXR compressions a run folder may use, by the name the settings give them.
EXR_COMPRESSIONS: dict[str, str] = {
    "none": "NO_COMPRESSION",
    "zip": "ZIP_COMPRESSION",
    "htj2k": "HTJ2K256_COMPRESSION",
}


def save_png(
    image: np.ndarray, target: str | Path | IO[bytes], text: Mapping[str, str] | None = None
) -> None:
    """Write a uint8 (H, W) or (H, W, 3) image as PNG with the settings measured above:
    colour through fpng, grey through Pillow (fpng writes only colour), with ``text`` as
    the PNG's text chunks (a depth image's source; grey images only)."""
    if image.ndim == 3 and image.shape[2] == 3:
        import fpng  # here, as Pillow: pilots read depth images through this module

        data = fpng.from_ndarray(np.ascontiguousarray(image, dtype=np.uint8))
        if isinstance(target, str | Path):
            Path(target).write_bytes(data)
        else:
            target.write(data)
        return
    from PIL import Image, PngImagePlugin

    info = PngImagePlugin.PngInfo()
    for key, value in (text or {}).items():
        info.add_text(key, value)
    Image.fromarray(image).save(
        target, format="PNG", compress_level=1, compress_type=zlib.Z_RLE, pnginfo=info
    )


def write_exr(
    path: str | Path,
    depth_m: np.ndarray,
    compression: ExrCompression = "none",
    text: Mapping[str, str] | None = None,
) -> None:
    """Write raw float32 depth (metres; ``inf`` where no hit, NaN where a stereo camera
    found no match) as a one-channel 'Z' EXR, exactly (every compression offered is
    lossless), with ``text`` as string attributes of its header (the depth's source)."""
    import OpenEXR

    method = getattr(OpenEXR, EXR_COMPRESSIONS[compression])
    header = {"compression": method, "type": OpenEXR.scanlineimage, **(text or {})}
    with OpenEXR.File(header, {"Z": np.ascontiguousarray(depth_m, dtype=np.float32)}) as f:
        f.write(str(path))


def read_exr(path: str | Path) -> np.ndarray:
    """Read a depth EXR written by `write_exr` back as (H, W) float32 metres."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.array(f.channels()["Z"].pixels, dtype=np.float32)

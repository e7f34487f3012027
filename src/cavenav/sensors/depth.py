"""Depth images: normalisation for the VLM and file formats (OpenEXR, 8-bit PNG).

SPEC section 2: ``D_norm = (D_raw - D_min) / (D_max - D_min)`` clipped to [0, 1], written
as 8 bits, dark = near, bright = far; a ray that hits nothing counts as D_max.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["DEPTH_RANGE_M", "denormalise_depth", "normalise_depth", "read_exr", "write_exr"]

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


def denormalise_depth(
    depth_png: np.ndarray, d_min: float = DEPTH_RANGE_M[0], d_max: float = DEPTH_RANGE_M[1]
) -> np.ndarray:
    """Inverse of `normalise_depth` up to 8-bit quantisation: (H, W) uint8 -> float32 metres."""
    return (d_min + depth_png.astype(np.float32) / 255.0 * (d_max - d_min)).astype(np.float32)


def write_exr(path: str | Path, depth_m: np.ndarray) -> None:
    """Write raw float32 depth (metres; ``inf`` where no hit) as a one-channel 'Z' EXR."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Z": np.ascontiguousarray(depth_m, dtype=np.float32)}) as f:
        f.write(str(path))


def read_exr(path: str | Path) -> np.ndarray:
    """Read a depth EXR written by `write_exr` back as (H, W) float32 metres."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.array(f.channels()["Z"].pixels, dtype=np.float32)

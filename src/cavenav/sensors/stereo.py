"""Depth as a stereo camera gives it: only where the colour image has texture to match.

A stereo pair finds a pixel's depth by matching a small window of its left image in the
right one. It fails where the window holds no usable contrast, and that is where the colour
camera fails too: beyond the distance the lamps and the water allow, inside a silt cloud's
veil, on rock with no grain in view. So the depth here is derived from the very colour frame
the camera delivers (after its noise, gain and encoder), in five stages:

1. Texture: the standard deviation of luminance over a `StereoCamera.window_px` window, of
   the image binned 2x2 (a matcher's cost aggregation averages the sensor's noise away;
   the binning does the same) and opened (the specks of marine snow out: a window would
   match a speck at its own depth, which the simulator's depth does not hold; stage 4
   takes those the opening leaves).
   Below `StereoCamera.min_texture` (8-bit levels, about three times the binned noise)
   a window is unmatched.
2. Range: a match's disparity d = f B / z is off by `StereoCamera.disparity_sigma_px`
   (sub-pixel matching's typical error), so the depth's error grows with the square of the
   distance: sigma_z = z^2 sigma_d / (f B). Disparities below `min_disparity_px` (too far)
   are unmatched.
3. Edges: where depth jumps (a rock's edge in front of the far wall) one camera sees what
   the other cannot: pixels within `edge_holes_px` of a jump are unmatched, and a
   `speckle` share of those left at the edge take a depth between the two sides (the
   mixed windows a matcher's speckle filter lets through).
4. Islands of matches smaller than `StereoCamera.min_region_px` are dropped (a matcher's
   speckle filter).
5. Unmatched pixels read NaN in metres and 0 (near) in the PNG: never free space.

Deterministic: the noise is drawn from the frame's own key (seed and pose).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StereoCamera", "stereo_depth"]


@dataclass(frozen=True)
class StereoCamera:
    """A stereo pair's figures (defaults: a 12 cm baseline, as Stereolabs' ZED 2; its
    focal length is the forward camera's).

    Attributes:
        baseline_m: the distance between the two cameras.
        disparity_sigma_px: the matcher's sub-pixel error.
        min_disparity_px: smaller disparities (farther than f B / this) are unmatched.
        window_px: the matching window's side.
        min_texture: the least luminance contrast (standard deviation in 8-bit levels,
            binned 2x2) a window needs to match.
        edge_holes_px: pixels this close to a depth jump are occluded in one view.
        edge_jump: a relative depth change between neighbours that counts as a jump.
        speckle: the share of edge pixels that keep a wrong depth between the two sides.
        min_region_px: matched regions smaller than this are dropped, as a matcher's
            speckle filter drops them (OpenCV's ``filterSpeckles``): a speck of marine
            snow, still lit after the opening and the encoder's ringing, is one.
    """

    baseline_m: float = 0.12
    disparity_sigma_px: float = 0.2
    min_disparity_px: float = 2.0
    window_px: int = 9
    min_texture: float = 1.0
    edge_holes_px: int = 2
    edge_jump: float = 0.1
    speckle: float = 0.02
    min_region_px: int = 400


def texture(rgb: np.ndarray, window_px: int) -> np.ndarray:
    """(H, W) float32 the luminance contrast around each pixel (stage 1), measured on the
    image binned 2x2 (a quarter of the work; the binning averages the noise as a matcher's
    cost aggregation does) and given back at full size."""
    from scipy import ndimage  # here: the configuration imports this module

    h, w = rgb.shape[:2]
    luma = rgb[: h // 2 * 2, : w // 2 * 2].astype(np.float32) @ np.array(
        [0.299, 0.587, 0.114], np.float32
    )
    luma = luma.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
    # Specks of marine snow are points a window would match at the speck's own depth,
    # not at the rock's behind it: an opening takes them out before the contrast.
    luma = ndimage.grey_opening(luma, size=(3, 3))
    side = max(3, window_px // 2 | 1)
    mean = ndimage.uniform_filter(luma, side)
    square = ndimage.uniform_filter(luma * luma, side)
    binned = np.sqrt(np.maximum(square - mean * mean, 0.0))
    full = np.repeat(np.repeat(binned, 2, axis=0), 2, axis=1)
    return np.pad(full, ((0, h - full.shape[0]), (0, w - full.shape[1])), mode="edge")


def _edges(depth: np.ndarray, jump: float, holes: int) -> np.ndarray:
    """(H, W) bool: pixels within ``holes`` of a relative depth ``jump`` (stage 3)."""
    from scipy import ndimage  # here: the configuration imports this module

    finite = np.where(np.isfinite(depth), depth, 1e6)
    across = np.abs(np.diff(finite, axis=1)) > jump * np.minimum(finite[:, 1:], finite[:, :-1])
    down = np.abs(np.diff(finite, axis=0)) > jump * np.minimum(finite[1:], finite[:-1])
    edge = np.zeros(depth.shape, bool)
    edge[:, 1:] |= across
    edge[:, :-1] |= across
    edge[1:] |= down
    edge[:-1] |= down
    if holes > 1:
        edge = ndimage.binary_dilation(edge, iterations=holes - 1)
    return edge


def stereo_depth(
    depth_m: np.ndarray, rgb: np.ndarray, focal_px: float, camera: StereoCamera, key: int
) -> np.ndarray:
    """(H, W) float32 the depth a stereo pair reports where the true planar depth is
    ``depth_m`` and the left camera sees ``rgb``: NaN where it finds no match."""
    from scipy import ndimage  # here: the configuration imports this module

    rng = np.random.default_rng(key)
    fb = focal_px * camera.baseline_m
    matched = texture(rgb, camera.window_px) >= camera.min_texture
    matched &= np.isfinite(depth_m) & (fb / np.maximum(depth_m, 1e-6) >= camera.min_disparity_px)
    edge = _edges(depth_m, camera.edge_jump, camera.edge_holes_px)
    measured = np.full(depth_m.shape, np.nan, np.float32)
    disparity = fb / depth_m[matched] + rng.normal(0.0, camera.disparity_sigma_px, matched.sum())
    measured[matched] = fb / np.maximum(disparity, camera.min_disparity_px)
    speckled = edge & matched & (rng.random(depth_m.shape) < camera.speckle)
    if speckled.any():  # a window across the edge: somewhere between its two sides
        near = ndimage.minimum_filter(np.where(np.isfinite(depth_m), depth_m, 1e6), 5)
        mix = rng.random(int(speckled.sum()))
        measured[speckled] = near[speckled] + mix * (depth_m[speckled] - near[speckled])
    keep = matched & (~edge | speckled)
    labels, count = ndimage.label(keep)
    if count:  # a matcher's speckle filter: small islands of matches are dropped
        sizes = np.bincount(labels.ravel(), minlength=count + 1)
        keep &= sizes[labels] >= camera.min_region_px
    measured[~keep] = np.nan
    return measured

"""The cave line in the camera: a guideline a few millimetres thick, drawn at its true size.

A 3 mm line spans 1.9 pixels at 1 m in the 640-pixel frame (a focal length of 640 px) and
a fifth of a pixel at 10 m. As triangles of the cave's mesh it would fall between the
rays or alias into dashes, so it is drawn in a pass of its own over the cast, before the
frame is shaded (`LineRenderer.draw`):

- Each straight span between tie-offs is clipped to the space in front of the lens,
  projected, and walked along its longer image axis in quarter-pixel steps; each step
  lays the line's band (its projected width, times the secant of its slope) across the
  pixels it crosses, as the fraction of each it covers. The line's line arrows are filled
  triangles, their coverage counted at 4 x 4 points in every pixel.
- Only where the line lies nearer than the rock the pixel's ray hit (a depth test against
  the cast) does it count: it disappears behind a bulge of rock, and appears as a pixel
  or a few only where the geometry leaves it in view.
- Its light is the rock's model (`kernels._surface_light`): the same lamps, their light
  reaching it through the water's kept attenuation and leaving it through the full
  attenuation, the water's veil in front of it, the silt's too, and the daylight the rock
  it is tied to receives. A diffuse cylinder lit from beside the camera shows pi / 4 of
  the light that falls square on it, on average across its visible width, times the sine
  of the light's angle to its axis; an arrow is a flat diffuse plate lit from either side.
- Each covered pixel gets, through the marine snow's buffer (light added before the
  lens's vignetting, the sensor's noise, the white balance and the gain:
  `kernels.splat_particles`), the difference the line makes: its coverage times the
  line's radiance less the rock's that it hides (`kernels._own_light`, with the
  photographed rock's factor). The camera meters the frame without it: the line would
  move the exposure by parts in a thousand, and left out, every pixel it does not cover
  is as it is without the line (`SensorRig._draw_line`).
- The depth image takes the line's planar depth where the line covers half a pixel or
  more, its true size (within 3.8 m of the lens for a 3 mm line, at 640 px), and the
  depth camera's noise there as anywhere (`LineRenderer.lay_depth`, after shading).

Without a line nothing here runs. With one, the pass runs on one thread, in a fixed
order and without fast-math liberties, so the frame does not depend on the number of
threads.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.kernels import (
    _NO_HIT,
    PHOTO_SHARE,
    SHARE,
    _curve,
    _depth_level,
    _noisy_depth,
    _own_light,
    _photo_at,
    _veil,
)
from cavenav.world.guideline import Guideline

__all__ = ["NEAREST_M", "LineRenderer", "draw_guideline", "lay_line_depth"]

NEAREST_M = 0.05  # spans are clipped this far in front of the lens
_STEPS = 4  # steps per pixel along a span; points per pixel side within an arrow
_CYLINDER = math.pi / 4  # a diffuse cylinder's mean light across its width, lit square


@numba.njit(cache=True, nogil=True)
def _to_camera(point, rot, origin):  # noqa: ANN001, ANN202
    """(x, y, z) of a world ``point`` (3) in the camera frame at ``origin`` turned by
    ``rot`` (columns: the camera's axes in the world)."""
    px, py, pz = point[0] - origin[0], point[1] - origin[1], point[2] - origin[2]
    return (
        px * rot[0, 0] + py * rot[1, 0] + pz * rot[2, 0],
        px * rot[0, 1] + py * rot[1, 1] + pz * rot[2, 1],
        px * rot[0, 2] + py * rot[1, 2] + pz * rot[2, 2],
    )


@numba.njit(cache=True, nogil=True)
def _to_world(x, y, z, rot, origin):  # noqa: ANN001, ANN202
    """The world point at camera-frame (x, y, z)."""
    return (
        origin[0] + rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z,
        origin[1] + rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z,
        origin[2] + rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z,
    )


@numba.njit(cache=True, nogil=True)
def _element_light(point, facing, cylinder, origin, lamps, water, albedo):  # noqa: ANN001, ANN202
    """Radiance (R, G, B) from the line (``cylinder``: ``facing`` is its unit axis) or an
    arrow (``facing`` its unit normal) at world ``point``, reaching the lens straight: lamp
    light only, before the veil and the silt (`_blend`)."""
    lamp_pos, lamp_axis, lamp_power, profile = lamps
    attenuation, kept = water[0], water[1]
    px, py, pz = point
    fx, fy, fz = facing
    e0 = e1 = e2 = 0.0
    for k in range(lamp_pos.shape[0]):
        wx, wy, wz = lamp_pos[k, 0] - px, lamp_pos[k, 1] - py, lamp_pos[k, 2] - pz
        d2 = max(wx * wx + wy * wy + wz * wz, 0.01)
        d = math.sqrt(d2)
        cos_axis = -(wx * lamp_axis[k, 0] + wy * lamp_axis[k, 1] + wz * lamp_axis[k, 2]) / d
        spot = _curve(profile, k, cos_axis)
        if spot <= 0.0:
            continue
        along = (wx * fx + wy * fy + wz * fz) / d
        # the cylinder's mean across its width, or the plate's cosine
        square = _CYLINDER * math.sqrt(max(1.0 - along * along, 0.0)) if cylinder else abs(along)
        e = spot * square / d2
        e0 += e * lamp_power[k, 0] * math.exp(-kept[0] * d)
        e1 += e * lamp_power[k, 1] * math.exp(-kept[1] * d)
        e2 += e * lamp_power[k, 2] * math.exp(-kept[2] * d)
    r = math.sqrt((px - origin[0]) ** 2 + (py - origin[1]) ** 2 + (pz - origin[2]) ** 2)
    return (
        albedo[0] * e0 * math.exp(-attenuation[0] * r),
        albedo[1] * e1 * math.exp(-attenuation[1] * r),
        albedo[2] * e2 * math.exp(-attenuation[2] * r),
    )


@numba.njit(cache=True, nogil=True)
def _deposit(i, weight, z, l0, l1, l2, work, count):  # noqa: ANN001, ANN202
    """Add ``weight`` of pixel i's area, covered at planar depth z with radiance (l0, l1,
    l2), to the work buffers; the number of pixels touched so far."""
    cover, light, near, touched = work
    if cover[i] == 0.0:
        touched[count] = i
        count += 1
    cover[i] += weight
    light[i, 0] += weight * l0
    light[i, 1] += weight * l1
    light[i, 2] += weight * l2
    near[i] = min(near[i], z)
    return count


@numba.njit(cache=True, nogil=True)
def _clipped(a, b, rot, origin):  # noqa: ANN001, ANN202
    """The span a-b in the camera frame, clipped to `NEAREST_M` in front of the lens:
    (ok, ax, ay, az, bx, by, bz); ok False where none of it is."""
    ax, ay, az = _to_camera(a, rot, origin)
    bx, by, bz = _to_camera(b, rot, origin)
    if az < NEAREST_M and bz < NEAREST_M:
        return False, ax, ay, az, bx, by, bz
    if az < NEAREST_M:
        f = (NEAREST_M - az) / (bz - az)
        ax, ay, az = ax + f * (bx - ax), ay + f * (by - ay), NEAREST_M
    elif bz < NEAREST_M:
        f = (NEAREST_M - bz) / (az - bz)
        bx, by, bz = bx + f * (ax - bx), by + f * (ay - by), NEAREST_M
    return True, ax, ay, az, bx, by, bz


@numba.njit(cache=True, nogil=True)
def _lay_span(a, b, view, look, cast, lamps, water, work, count):  # noqa: ANN001, ANN202
    """Lay the span from world point ``a`` to ``b`` (3 each) into the work buffers, in
    quarter-pixel steps along its longer image axis (module docstring); the pixels
    touched so far."""
    rot, origin, focal, width, height = view
    albedo, radius = look
    t = cast[0]
    ok, ax, ay, az, bx, by, bz = _clipped(a, b, rot, origin)
    if not ok:
        return count
    xa, ya = focal * ax / az + 0.5 * width, focal * ay / az + 0.5 * height
    xb, yb = focal * bx / bz + 0.5 * width, focal * by / bz + 0.5 * height
    steep = abs(yb - ya) > abs(xb - xa)  # walk the rows, the minor axis the columns
    u0, v0, z0, u1, v1, z1 = (ya, xa, az, yb, xb, bz) if steep else (xa, ya, az, xb, yb, bz)
    if u0 > u1:
        u0, v0, z0, u1, v1, z1 = u1, v1, z1, u0, v0, z0
    major, minor = (height, width) if steep else (width, height)
    du = u1 - u0
    if du < 1e-6:
        return count  # seen end on: a dot at most, which the ties' spans either side draw
    slope = (v1 - v0) / du
    secant = math.sqrt(1.0 + slope * slope)
    lx, ly, lz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    length = math.sqrt(lx * lx + ly * ly + lz * lz)
    axis = (lx / length, ly / length, lz / length)
    first = max(int(math.floor(u0 * _STEPS)), 0)
    last = min(int(math.ceil(u1 * _STEPS)), major * _STEPS)
    for k in range(first, last):
        u = (k + 0.5) / _STEPS
        if u < u0 or u > u1:
            continue
        f = (u - u0) / du
        z = 1.0 / ((1.0 - f) / z0 + f / z1)  # perspective: 1 / z is linear on the image
        v = v0 + f * (v1 - v0)
        half = radius * focal / z * secant  # half the band across the minor axis
        lo, hi = max(int(math.floor(v - half)), 0), min(int(math.floor(v + half)), minor - 1)
        lit = False
        l0 = l1 = l2 = 0.0
        for m in range(lo, hi + 1):
            overlap = min(v + half, m + 1.0) - max(v - half, float(m))
            i = (k // _STEPS) * width + m if steep else m * width + k // _STEPS
            if overlap <= 0.0 or not z < t[i]:
                continue
            if not lit:
                x, y = (v, u) if steep else (u, v)
                point = _to_world(
                    (x - 0.5 * width) * z / focal, (y - 0.5 * height) * z / focal, z, rot, origin
                )
                l0, l1, l2 = _element_light(point, axis, True, origin, lamps, water, albedo)
                lit = True
            count = _deposit(i, overlap / _STEPS, z, l0, l1, l2, work, count)
    return count


@numba.njit(cache=True, nogil=True)
def _edge(x0, y0, x1, y1, x, y):  # noqa: ANN001, ANN202
    """Twice the signed area of the triangle (x0, y0), (x1, y1), (x, y)."""
    return (x1 - x0) * (y - y0) - (y1 - y0) * (x - x0)


@numba.njit(cache=True, nogil=True)
def _inside(xs, ys, col, row):  # noqa: ANN001, ANN202
    """How many of pixel (row, col)'s `_STEPS` x `_STEPS` points lie inside the image
    triangle with corners ``xs``, ``ys``."""
    sign = 1.0 if _edge(xs[0], ys[0], xs[1], ys[1], xs[2], ys[2]) >= 0.0 else -1.0
    inside = 0
    for sy in range(_STEPS):
        y = row + (sy + 0.5) / _STEPS
        for sx in range(_STEPS):
            x = col + (sx + 0.5) / _STEPS
            if (
                sign * _edge(xs[0], ys[0], xs[1], ys[1], x, y) >= 0.0
                and sign * _edge(xs[1], ys[1], xs[2], ys[2], x, y) >= 0.0
                and sign * _edge(xs[2], ys[2], xs[0], ys[0], x, y) >= 0.0
            ):
                inside += 1
    return inside


@numba.njit(cache=True, nogil=True)
def _lay_arrow(corners, view, look, cast, lamps, water, work, count):  # noqa: ANN001, ANN202
    """Lay one arrow, a triangle with world ``corners`` (3, 3), into the work buffers; the
    pixels touched so far. An arrow reaching behind `NEAREST_M` is not drawn."""
    rot, origin, focal, width, height = view
    albedo = look[0]
    t = cast[0]
    cam = np.empty((3, 3))
    xs, ys = np.empty(3), np.empty(3)
    for j in range(3):
        cam[j, 0], cam[j, 1], cam[j, 2] = _to_camera(corners[j], rot, origin)
        if cam[j, 2] < NEAREST_M:
            return count
        xs[j] = focal * cam[j, 0] / cam[j, 2] + 0.5 * width
        ys[j] = focal * cam[j, 1] / cam[j, 2] + 0.5 * height
    e1 = (cam[1, 0] - cam[0, 0], cam[1, 1] - cam[0, 1], cam[1, 2] - cam[0, 2])
    e2 = (cam[2, 0] - cam[0, 0], cam[2, 1] - cam[0, 1], cam[2, 2] - cam[0, 2])
    n = (
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    )
    size = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    if size < 1e-12:
        return count
    plane = n[0] * cam[0, 0] + n[1] * cam[0, 1] + n[2] * cam[0, 2]
    normal = _to_world(n[0] / size, n[1] / size, n[2] / size, rot, np.zeros(3))
    for row in range(max(int(ys.min()), 0), min(int(ys.max()), height - 1) + 1):
        for col in range(max(int(xs.min()), 0), min(int(xs.max()), width - 1) + 1):
            inside = _inside(xs, ys, col, row)
            dx, dy = (col + 0.5 - 0.5 * width) / focal, (row + 0.5 - 0.5 * height) / focal
            facing = n[0] * dx + n[1] * dy + n[2]
            i = row * width + col
            if inside == 0 or abs(facing) < 1e-12:
                continue
            z = plane / facing  # the plane's depth along the pixel's ray
            if not (NEAREST_M <= z < t[i]):
                continue
            point = _to_world(dx * z, dy * z, z, rot, origin)
            l0, l1, l2 = _element_light(point, normal, False, origin, lamps, water, albedo)
            count = _deposit(i, inside / (_STEPS * _STEPS), z, l0, l1, l2, work, count)
    return count


@numba.njit(cache=True, nogil=True)
def _blend(i, width, look, cast, rays, scene, lamps, water, work):  # noqa: ANN001, ANN202
    """The radiance (R, G, B) the line adds to pixel i, which it covers in part: its
    coverage times the line's light less the rock's (or open water's) it hides, each
    with the veil in front of it."""
    cover, light, near, _ = work
    t, triangle, normals, _ = cast
    row, col = i // width, i % width
    f = min(cover[i], 1.0)
    z = near[i]
    l0, l1, l2, _, _, _, _, r0, r1, r2 = _own_light(i, row, col, cast, rays, scene, lamps, water)
    if triangle[i] != _NO_HIT:
        more = _photo_at(i, normals[i, 0], normals[i, 1], normals[i, 2], cast, rays, scene, PHOTO_SHARE) - 1.0  # fmt: skip  # noqa: E501
        l0, l1, l2 = l0 + more * r0, l1 + more * r1, l2 + more * r2
    own0, own1, own2 = light[i, 0] / cover[i], light[i, 1] / cover[i], light[i, 2] / cover[i]
    attenuation, _, backscatter, block, far, _, _, silt_veil, silt_light = water
    if triangle[i] != _NO_HIT:  # the daylight that reaches the rock the line is tied to
        directions = rays[0]
        side = 1 if (normals[i, 0] * directions[i, 0] + normals[i, 1] * directions[i, 1]
                     + normals[i, 2] * directions[i, 2]) > 0.0 else 0  # fmt: skip
        surface, tri = scene[2], triangle[i]
        r = z * rays[1][i]
        own0 += look[0][0] * surface[tri, side, 3] * math.exp(-attenuation[0] * r)
        own1 += look[0][1] * surface[tri, side, 4] * math.exp(-attenuation[1] * r)
        own2 += look[0][2] * surface[tri, side, 5] * math.exp(-attenuation[2] * r)
    v0, v1, v2 = _veil(backscatter, row // block, col // block, z, far)
    if silt_veil.shape[0] > 1:
        s0, s1, s2 = _veil(silt_veil, row // block, col // block, z, far)
        t0, t1, t2 = _veil(silt_light, row // block, col // block, z, far)
        own0, own1, own2 = t0 * own0 + s0, t1 * own1 + s1, t2 * own2 + s2
    return f * (own0 + v0 - l0), f * (own1 + v1 - l1), f * (own2 + v2 - l2)


@numba.njit(cache=True, nogil=True)
def draw_guideline(spans, arrows, view, look, cast, rays, scene, lamps, water, work, specks, speck_blocks):  # fmt: skip  # noqa: ANN001, ANN201, E501
    """Draw the line's ``spans`` (m, 6: each from its first three numbers to its last
    three, world) and its ``arrows`` (a, 3, 3: triangles, world) into the marine snow's
    buffers ``specks`` (n, 3) and ``speck_blocks`` (module docstring).

    ``view``: (rot, origin, focal px, width, height) of the camera; ``look``: (albedo (3),
    radius m); ``cast``, ``rays``, ``scene``, ``lamps``, ``water`` as `kernels.shade_frame`
    takes them, before shading; ``work``: (cover (n,) float32 zeros, light (n, 3) float32
    zeros, near (n,) float32 inf, touched (n,) int64), left as found but for ``touched``
    and ``near``: returns (pixels drawn, k), the first k of ``touched`` the pixels the
    line covers half of or more, whose planar depth ``near`` holds (`lay_line_depth`).
    """
    cover, light, near, touched = work
    width = view[3]
    count = 0
    for s in range(spans.shape[0]):
        count = _lay_span(spans[s, :3], spans[s, 3:], view, look, cast, lamps, water, work, count)
    for a in range(arrows.shape[0]):
        count = _lay_arrow(arrows[a], view, look, cast, lamps, water, work, count)
    deep = 0
    for j in range(count):
        i = touched[j]
        d0, d1, d2 = _blend(i, width, look, cast, rays, scene, lamps, water, work)
        specks[i, 0] += d0
        specks[i, 1] += d1
        specks[i, 2] += d2
        speck_blocks[(i // width) // SHARE, (i % width) // SHARE] = 1
        if cover[i] >= 0.5:
            touched[deep] = i  # j >= deep: the pixels still to blend are not overwritten
            deep += 1
        else:
            near[i] = np.inf
        cover[i] = 0.0
        light[i, 0] = light[i, 1] = light[i, 2] = 0.0
    return count, deep


@numba.njit(cache=True, nogil=True)
def lay_line_depth(touched, deep, near, t, depth_png, depth_range, frame_key):  # noqa: ANN001, ANN201
    """Write the line's planar depth into the depth ``t`` (n,) and its PNG where it
    covers half a pixel or more (the first ``deep`` of ``touched``), with the depth
    camera's noise as `kernels._finish` gives it, and set ``near`` back to inf there."""
    d_min, d_max, _, depth_noise = depth_range
    for j in range(deep):
        i = touched[j]
        depth = _noisy_depth(i, near[i], t.shape[0], frame_key, depth_noise)
        t[i] = depth
        depth_png[i] = _depth_level(depth, d_min, d_max)
        near[i] = np.inf


class LineRenderer:
    """Draws one cave's guideline into a rig's frames (module docstring); holds the line
    as the kernels take it and the work buffers, one frame's worth, reused."""

    def __init__(self, guideline: Guideline, camera: CameraIntrinsics):
        self.guideline = guideline
        ties = np.asarray(guideline.ties, np.float64)
        self._spans = np.ascontiguousarray(np.concatenate([ties[:-1], ties[1:]], axis=1))
        self._arrows = np.ascontiguousarray(guideline.arrow_triangles(), np.float64)
        self._look = (np.asarray(guideline.albedo, np.float64), float(guideline.radius_m))
        self._camera = (float(camera.focal_px), int(camera.width), int(camera.height))
        n = camera.width * camera.height
        self._work = (
            np.zeros(n, np.float32),
            np.zeros((n, 3), np.float32),
            np.full(n, np.inf, np.float32),
            np.empty(n, np.int64),
        )
        self._deep = 0  # pixels whose depth `lay_depth` writes

    def draw(
        self,
        cast: tuple,
        rays: tuple,
        scene: tuple,
        lamps: tuple,
        water: tuple,
        view: tuple[np.ndarray, np.ndarray],
        specks: np.ndarray,
        speck_blocks: np.ndarray,
    ) -> int:
        """Draw the line into the marine snow's buffers of a frame cast from ``view``
        (the camera's rotation and origin), the other tuples as `kernels.shade_frame`
        takes them; the number of pixels it touches."""
        near, touched = self._work[2], self._work[3]
        near[touched[: self._deep]] = np.inf  # a frame drawn but never finished
        camera = (view[0], view[1], *self._camera)
        drawn, self._deep = draw_guideline(
            self._spans, self._arrows, camera, self._look, cast, rays, scene, lamps, water,
            self._work, specks, speck_blocks,
        )  # fmt: skip
        return int(drawn)

    def lay_depth(
        self, depth: np.ndarray, depth_png: np.ndarray, depth_range: tuple, key: np.uint64
    ) -> None:
        """Write the line's depth into the frame's ``depth`` and ``depth_png`` (n,), once
        they are shaded, where it covers half a pixel or more."""
        if self._deep:
            _, _, near, touched = self._work
            lay_line_depth(touched, self._deep, near, depth, depth_png, depth_range, key)
            self._deep = 0

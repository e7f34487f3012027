"""The sensor rig: renders one Observation for a pose from a single ray cast.

Forward colour and depth share one cast (640x480 pixels unless set otherwise; depth is the
ray parameter, colour is shaded from the same hits); the two echo sounders' few rays ride
along in the same call.
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
import simplejpeg

from cavenav.core.types import Observation, Pose
from cavenav.sensors.camera import CameraIntrinsics, camera_to_world, look_frame
from cavenav.sensors.config import SENSOR_KEYS, SensorConfig
from cavenav.sensors.depth import normalise_depth, unknown_depth
from cavenav.sensors.guideline import LineRenderer
from cavenav.sensors.kernels import (
    PHOTO_SHARE,
    SHARE,
    develop_image,
    fill_rays,
    integrate_silt,
    photograph_rock_grid,
    shade_frame,
    shade_grid,
    splat_particles,
    spread_halo,
)
from cavenav.sensors.lighting import (
    at_vertices,
    backscatter_table,
    lamp_arrays,
    rock_photographs,
    surface_table,
    veil_directions,
    vertex_normals,
)
from cavenav.sensors.optics import HALO_SIGMA_DEG, Optics, tone_lut
from cavenav.sensors.stereo import stereo_depth
from cavenav.sensors.white_balance import white_balance_gains
from cavenav.world.guideline import Guideline
from cavenav.world.procedural import cpu_independent
from cavenav.world.raycast import RayCaster
from cavenav.world.silt import (
    EXTINCTION_M2_PER_G,
    SCATTERING_M2_PER_G,
    SILT_PHASE_G,
    SiltCloud,
)

__all__ = ["SENSOR_KEYS", "Frame", "SensorConfig", "SensorRig", "halo_weights"]

_UP = np.array([0.0, 0.0, 1.0])
PARTICLE_REACH_M = 5.0
# Columns of the backscatter table at any resolution: blocks of 8 pixels at 640 wide, so
# the veil's steps stay 0.7 degrees wide however few pixels the camera has.
_VEIL_COLUMNS = 80
# Frames with fewer pixels are shaded on one thread: waking numba's sleeping second thread
# for each pass costs more than it saves on a small frame. Measured on 2 cores (steps of
# the environment, interleaved): one thread 5% faster at 84x84 (7,056 pixels), two threads
# 7% faster at 160x120 (19,200).
_PARALLEL_PIXELS = 12_000


# The halo is blurred on cells of HALO_CELL x HALO_CELL grid points (16 pixels a side).
HALO_CELL = 4


def halo_weights(focal_px: float) -> np.ndarray:
    """The Gaussian of `HALO_SIGMA_DEG` over the halo's cells, as 1-D weights (3 sigma
    each side), computed with the C library's exp: the same on every CPU."""
    sigma = max(math.radians(HALO_SIGMA_DEG) * focal_px / (HALO_CELL * SHARE), 1e-3)
    radius = max(1, math.ceil(3.0 * sigma))
    weights = cpu_independent(math.exp, -0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    return weights / weights.sum()


@dataclass(frozen=True)
class Frame:
    """One forward frame: what the cameras deliver, plus the light that made it.

    Attributes:
        depth_m: (H, W) float32 planar depth in metres, inf where nothing is in range.
        depth_png: (H, W) uint8 normalised depth, dark = near.
        rgb: (H, W, 3) uint8 colour image.
        radiance: (H, W, 3) float32 linear radiance arriving at the lens, before white
            balance, vignetting, noise and tone curve (for tests and for users who want
            to develop the image themselves); None unless asked for, to spare every
            step the memory traffic.
        particles: marine-snow specks drawn.
    """

    depth_m: np.ndarray
    depth_png: np.ndarray
    rgb: np.ndarray
    radiance: np.ndarray | None
    particles: int


def compress(rgb: np.ndarray, quality: int) -> np.ndarray:
    """(H, W, 3) uint8 ``rgb`` as it comes out of a video camera's lossy encoder: JPEG at
    ``quality`` with 4:2:0 chroma, the intra-frame coding H.264 also does (blocks of DCT
    coefficients, quantised, colour at half resolution); ``quality`` 0 leaves it as is.

    libjpeg-turbo (through simplejpeg) takes about 1.4 ms for 640x480 both ways, half of
    Pillow's time, and gives the same bits every time. The two halves of a frame are coded
    at once, on two cores (0.85 ms), with the same bits as the whole: JPEG codes blocks
    of 16 rows on their own, and the decoder's smooth upsampling of colour reaches one
    row of colour (two of pixels) across a block's edge, so each half is coded with one
    block of the other, then dropped. A thread whose frames are shaded on one core (a
    batched environment's, a sweep's episodes in flight together) codes the frame whole:
    other frames keep the other cores busy.
    """
    if quality <= 0:
        return rgb
    height = rgb.shape[0]
    seam = height // 2 // _JPEG_BLOCK * _JPEG_BLOCK
    if seam < 2 * _JPEG_BLOCK or numba.get_num_threads() == 1:
        return _jpeg_round_trip(rgb, quality)
    below = _jpeg_helper().submit(_jpeg_round_trip, rgb[seam - _JPEG_BLOCK :], quality)
    above = _jpeg_round_trip(rgb[: seam + _JPEG_BLOCK], quality)
    return np.concatenate([above[:seam], below.result()[_JPEG_BLOCK:]])


_JPEG_BLOCK = 16  # rows of a 4:2:0 JPEG's blocks (MCUs)
_jpeg_pool: tuple[int, ThreadPoolExecutor] | None = None


def _jpeg_helper() -> ThreadPoolExecutor:
    """This process's one helper thread for `compress` (a forked worker makes its own)."""
    global _jpeg_pool
    if _jpeg_pool is None or _jpeg_pool[0] != os.getpid():
        _jpeg_pool = (os.getpid(), ThreadPoolExecutor(1, thread_name_prefix="cavenav-jpeg"))
    return _jpeg_pool[1]


def _jpeg_round_trip(rgb: np.ndarray, quality: int) -> np.ndarray:
    coded = simplejpeg.encode_jpeg(
        np.ascontiguousarray(rgb), quality=int(quality), colorspace="RGB", colorsubsampling="420"
    )
    return simplejpeg.decode_jpeg(coded, colorspace="RGB")


def grid_mean(row_sums: np.ndarray, columns: int) -> np.ndarray:
    """The mean colour (3,) over `shade_grid`'s points from its ``row_sums`` (rows, 3) of
    ``columns`` points each, added exactly (`math.fsum`), so in no order that depends on
    how many threads shaded the rows: a sum over each thread's share would."""
    count = len(row_sums) * columns
    return np.array([math.fsum(row_sums[:, c]) / count for c in range(3)])


def camera_response(mean: np.ndarray, optics: Optics) -> tuple[np.ndarray, float]:
    """White-balance gains (3,) and exposure gain for a frame whose mean colour is ``mean``.

    The white balance of `Optics.white_balance_mode` (by default the BlueROV2 camera's own
    auto white balance; `white_balance.white_balance_gains`), then the exposure that
    brings the balanced mean luminance to `Optics.exposure_key` within the gain range.
    """
    mean = np.maximum(mean.astype(np.float64), 1e-9)
    gains = white_balance_gains(mean, optics)
    gain = optics.exposure
    if gain is None:
        low, high = optics.gain_range
        balanced = float((mean * gains) @ (0.25, 0.5, 0.25))
        gain = min(max(optics.exposure_key / balanced, low), high)
    return gains.astype(np.float32), float(gain)


@contextmanager
def _numba_threads(count: int | None) -> Iterator[None]:
    """Numba's parallel passes run on at most ``count`` threads inside (None: as set).

    Numba's setting is per calling thread, so a sweep's other episodes are unaffected.
    """
    if count is None:
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(min(count, before))
    try:
        yield
    finally:
        numba.set_num_threads(before)


def _frame_key(seed: int, pose: Pose) -> np.uint64:
    """A 64-bit key for the noise of one frame: the seed and the pose's exact bits."""
    data = struct.pack("<q4d", seed, pose.x, pose.y, pose.z, pose.psi)
    return np.uint64(int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little"))


def _beam_directions(cone_deg: float, rings: int = 3, per_ring: int = 8) -> np.ndarray:
    """(n, 3) unit directions filling a cone around +z, for the narrow-beam sounder."""
    dirs = [np.array([0.0, 0.0, 1.0])]
    half = np.radians(cone_deg) / 2.0
    for k in range(1, rings + 1):
        theta = half * k / rings
        for j in range(per_ring):
            phi = 2 * np.pi * j / per_ring
            dirs.append(
                np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
            )
    return np.array(dirs)


class SensorRig:
    """Renders observations of one cave; holds the precomputed rays and rock colours."""

    _filled_for: Pose | None = None  # the pose `rays` last filled the ray buffer for

    def __init__(
        self,
        caster: RayCaster,
        config: SensorConfig | None = None,
        guideline: Guideline | None = None,
    ):
        """``guideline``: a diver's line tied along the cave, which the camera draws at its
        true size (`cavenav.sensors.guideline`); None: none, and nothing of it runs."""
        self.caster, self.guideline = caster, guideline
        self.config = config or SensorConfig()
        cfg = self.config
        self._pixel_dirs = cfg.camera.directions.reshape(-1, 3)
        self._ray_length = np.linalg.norm(self._pixel_dirs, axis=1)  # rotation-invariant
        if cfg.sounder == "camera":
            w, h = cfg.sounder_pixels
            focal_mm = (
                0.5 * cfg.camera.sensor_width_mm / math.tan(math.radians(cfg.sounder_fov_deg) / 2)
            )
            sounder = CameraIntrinsics(w, h, focal_mm, cfg.camera.sensor_width_mm)
            self._sounder_dirs = sounder.directions.reshape(-1, 3)
            self._sounder_planar = True
        else:
            self._sounder_dirs = _beam_directions(cfg.sounder_fov_deg)
            self._sounder_planar = False
        # Both sounders' directions at heading 0: an up- (down-) looking camera, optical
        # axis +-z, image x along the vehicle's right. Each pose turns them about z.
        level = Pose(0.0, 0.0, 0.0, 0.0)
        self._sounder_level = np.concatenate(
            [
                self._sounder_dirs @ look_frame(_UP, level.right).T,
                self._sounder_dirs @ look_frame(-_UP, -level.right).T,
            ]
        )
        # A beam sounder reads ranges, a camera planar depths: t times the direction's length.
        lengths = np.linalg.norm(self._sounder_dirs, axis=1)
        scale = np.ones_like(lengths) if self._sounder_planar else lengths
        self._sounder_scale = np.tile(scale, 2)  # up, then down
        # One ray buffer for the forward frame and, behind it, both sounders: an
        # observation is a single cast.
        self._rays = np.empty((len(self._pixel_dirs) + 2 * len(lengths), 6), np.float32)
        optics = cfg.optics
        self._surface = surface_table(caster, optics, cfg.seed)
        self._photos = rock_photographs().as_tuple()
        mesh = caster.mesh
        self._faces = mesh.faces.astype(np.int32)
        self._vertex_normals = vertex_normals(mesh)
        self._surface_at = at_vertices(mesh, self._surface)
        veil_block = max(1, cfg.camera.width // _VEIL_COLUMNS)
        self._backscatter = backscatter_table(cfg.camera, optics, block=veil_block)
        self._veil_directions = veil_directions(cfg.camera, veil_block)
        self._no_silt = np.zeros((1, 1, 2, 3), np.float32)  # the kernels' "no silt"
        self._lamps = lamp_arrays(optics)
        self._attenuation, self._kept = optics.medium.attenuation, optics.medium.kept_attenuation
        self._bounds = caster.mesh.bounds.astype(np.float32)
        self._lut = tone_lut(1.0, optics.tone)
        # Work buffers of the shading passes, reused every frame (see kernels.shade_frame).
        blocks = (-(-cfg.camera.height // SHARE), -(-cfg.camera.width // SHARE))
        self._grid = np.zeros((blocks[0] + 1, blocks[1] + 1, 11), np.float32)
        self._grid_triangle = np.empty((blocks[0] + 1, blocks[1] + 1), np.uint32)
        self._photo = np.empty((*[b * SHARE // PHOTO_SHARE + 1 for b in blocks], 1), np.float32)
        self._halo = np.empty((blocks[0] + 1, blocks[1] + 1, 3), np.float32)
        self._row_sums = np.empty((blocks[0] + 1, 3), np.float64)
        self._halo_weights = halo_weights(cfg.camera.focal_px)
        self._specks = np.zeros((len(self._pixel_dirs), 3), np.float32)
        self._signal = np.empty((len(self._pixel_dirs), 3), np.float32)
        self._luma = np.empty((2, len(self._pixel_dirs)), np.float32)
        self._speck_blocks = np.zeros(blocks, np.uint8)
        self._threads = None if len(self._pixel_dirs) >= _PARALLEL_PIXELS else 1

    def camera_position(self, pose: Pose) -> np.ndarray:
        return pose.position + self.config.camera_offset_m * pose.forward

    def render(self, pose: Pose, *, radiance: bool = False, silt: SiltCloud | None = None) -> Frame:
        """Cast the forward frame at ``pose`` and form its depth and colour images, and
        the linear radiance they were developed from if ``radiance``; ``silt`` hangs in
        the water (none: clear)."""
        return self._render(pose, radiance, silt=silt)[0]

    def _sounder_rays(self, pose: Pose, out: np.ndarray) -> None:
        """Write the up- and then the down-looking sounder's rays into ``out`` (2k, 6)."""
        c, s = math.cos(pose.psi), math.sin(pose.psi)
        out[:, :3] = pose.position
        out[:, 3:] = self._sounder_level @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])

    def _readings(self, t: np.ndarray) -> tuple[float, float]:
        """(d_top, d_bottom) from the ray parameters of `_sounder_rays`."""
        up, down = (t * self._sounder_scale).reshape(2, -1).min(axis=1)
        limit = self.config.sounder_max_range_m
        return float(min(up, limit)), float(min(down, limit))

    def _render(
        self,
        pose: Pose,
        radiance: bool,
        noise_seed: int | None = None,
        silt: SiltCloud | None = None,
        cast: Mapping[str, np.ndarray] | None = None,
    ) -> tuple[Frame, tuple[float, float]]:
        """The forward frame and the sounders' (d_top, d_bottom), from one cast (``cast``:
        what casting `rays` gave, when the caller cast them)."""
        with _numba_threads(self._threads):
            return self._render_on(pose, radiance, noise_seed, silt, cast)

    def rays(self, pose: Pose) -> np.ndarray:
        """The rays an observation at ``pose`` casts, (n, 6) origins and directions: the
        camera's pixels, then the sounders'. For a caller that casts many observations'
        rays in one call (`cavenav.sim.vector_env`) and gives each its part (`observe`'s
        ``cast``); the buffer is this rig's own, overwritten by its next observation."""
        self._fill(pose, *self._camera_at(pose))
        self._filled_for = pose
        return self._rays

    def _camera_at(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """The camera's rotation to the world and its origin at ``pose``."""
        return camera_to_world(pose).astype(np.float32), self.camera_position(pose).astype(
            np.float32
        )

    def _hits(
        self,
        pose: Pose,
        rot: np.ndarray,
        origin: np.ndarray,
        cast: Mapping[str, np.ndarray] | None,
    ) -> Mapping[str, np.ndarray]:
        """The cast at ``pose``: ``cast``, which the caller made of `rays` at this pose just
        now (the buffer still holds them), else the ray buffer filled and cast here."""
        if cast is not None:
            if pose is not self._filled_for:
                raise ValueError("observe(cast=...) takes the cast of rays(pose) at that pose")
            return cast
        self._fill(pose, rot, origin)
        self._filled_for = None  # no longer what `rays` filled
        return self.caster.cast_raw_rays(self._rays)

    def _fill(self, pose: Pose, rot: np.ndarray, origin: np.ndarray) -> None:
        """Write the rays at ``pose`` into the ray buffer Open3D reads."""
        n, rays = len(self._pixel_dirs), self._rays
        fill_rays(self._pixel_dirs, rot, origin, rays)
        self._sounder_rays(pose, rays[n:])  # 0.5% more rays, one call fewer

    def _render_on(
        self,
        pose: Pose,
        radiance: bool,
        noise_seed: int | None,
        silt: SiltCloud | None,
        cast: Mapping[str, np.ndarray] | None = None,
    ) -> tuple[Frame, tuple[float, float]]:
        cfg = self.config
        optics, camera = cfg.optics, cfg.camera
        rot, origin = self._camera_at(pose)
        n, rays = len(self._pixel_dirs), self._rays
        raw = self._hits(pose, rot, origin, cast)
        depth, readings = raw["t_hit"][:n], self._readings(raw["t_hit"][n:])
        lamp_tuple = self._lamps_at(origin, rot)
        # Before shading: the specks need the true surfaces behind them, which a
        # degraded depth image no longer has.
        particles = self._splat_specks(origin, rot, lamp_tuple, depth)
        hit = (raw["primitive_ids"], raw["primitive_normals"], raw["primitive_uvs"])
        surfaces = (depth, *(part[:n] for part in hit))
        ray_tuple = (rays[:n, 3:], self._ray_length, origin)
        scene = (
            self._faces, self._vertex_normals, self._surface, self._surface_at,
            float(optics.specular), float(camera.focal_px), *self._photos,
        )  # fmt: skip
        table = self._backscatter
        water = (
            self._attenuation, self._kept, table.values, table.block, table.far, optics.sky,
            self._bounds, *self._silt_tables(silt, origin, rot),
        )  # fmt: skip
        shade_grid(
            surfaces, ray_tuple, scene, lamp_tuple, water, self._specks, self._speck_blocks,
            optics.vignetting, camera.width, self._grid, self._grid_triangle, self._halo,
            self._row_sums,
        )  # fmt: skip
        spread_halo(self._halo, HALO_CELL, self._halo_weights, self._grid)
        lined = self._draw_line(surfaces, ray_tuple, scene, lamp_tuple, water, (rot, origin))
        gains, gain = camera_response(grid_mean(self._row_sums, self._grid.shape[1]), optics)
        key = _frame_key(cfg.seed if noise_seed is None else noise_seed, pose)
        sensor = (gains, gain, optics.vignetting, optics.noise, key, optics.black_level)
        depth_range = (cfg.depth_min_m, cfg.depth_max_m, optics.depth_dropout, optics.depth_noise_m)
        light = np.empty((n if radiance else 0, 3), np.float32)
        rgb, depth_png = np.empty((n, 3), np.uint8), np.empty(n, np.uint8)
        photograph_rock_grid(surfaces, ray_tuple, scene, camera.width, self._photo)
        shade_frame(
            surfaces, ray_tuple, scene, lamp_tuple, water, self._grid, self._grid_triangle,
            self._photo, self._halo, self._specks, self._speck_blocks,
            sensor, depth_range, camera.width, light, self._signal, depth_png,
        )  # fmt: skip
        signal, work = self._signal, self._luma
        self._lay_line_depth(depth, depth_png, depth_range, key)
        develop_image(signal, camera.width, sensor, optics.denoise, self._lut, rgb, work)
        if particles or lined:
            self._speck_blocks[:] = 0  # shade_frame has zeroed the specks it read
        shape = (camera.height, camera.width)
        image = compress(rgb.reshape(*shape, 3), optics.compression)
        depth_m, png = self._depth_as_seen(
            depth.reshape(shape), depth_png.reshape(shape), image, key
        )
        frame = Frame(
            depth_m, png, image, light.reshape(*shape, 3) if radiance else None, particles
        )
        return frame, readings

    @cached_property
    def _line(self) -> LineRenderer | None:
        """The guideline's renderer and its work buffers, made for the first frame."""
        return None if self.guideline is None else LineRenderer(self.guideline, self.config.camera)

    def _draw_line(
        self, cast: tuple, rays: tuple, scene: tuple, lamps: tuple, water: tuple, view: tuple
    ) -> bool:
        """Draw the guideline into the marine snow's buffers (`LineRenderer.draw`) once the
        camera has metered the frame: the line moves the exposure by parts in a thousand,
        and left out of it, every pixel the line does not cover is as it is without the
        line. Whether it touched a pixel."""
        if self._line is None:
            return False
        buffers = (self._specks, self._speck_blocks)
        return self._line.draw(cast, rays, scene, lamps, water, view, *buffers) > 0

    def _lay_line_depth(
        self, depth: np.ndarray, png: np.ndarray, depth_range: tuple, key: np.uint64
    ) -> None:
        """The line's depth into the shaded frame's, where it covers half a pixel or more."""
        if self._line is not None:
            self._line.lay_depth(depth, png, depth_range, key)

    def _depth_as_seen(
        self, depth: np.ndarray, png: np.ndarray, rgb: np.ndarray, key: np.uint64
    ) -> tuple[np.ndarray, np.ndarray]:
        """The depth image as the configured source gives it (`SensorConfig.depth_source`):
        the ray cast's, a stereo pair's from the colour frame, or none (NaN and 0)."""
        cfg = self.config
        if cfg.depth_source == "exact":
            return depth, png
        if cfg.depth_source == "none":
            return unknown_depth(*depth.shape)
        seen = stereo_depth(depth, rgb, cfg.camera.focal_px, cfg.stereo, int(key))
        png = normalise_depth(seen, cfg.depth_min_m, cfg.depth_max_m)
        png[np.isnan(seen)] = 0  # unmatched: near, never free space
        return seen, png

    def _silt_tables(
        self, silt: SiltCloud | None, origin: np.ndarray, rot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The veil the silt scatters and the light it lets through, as tables shaped like
        the water's backscatter (`kernels.integrate_silt`); tiny zeros for clear water."""
        if silt is None or not silt.puffs:
            return self._no_silt, self._no_silt
        puffs = silt.array()
        puffs[:, :3] = (puffs[:, :3] - origin) @ rot  # world to camera frame
        table, lamps = self._backscatter, self._lamps
        shape = (len(self._veil_directions), table.bins + 1, 3)
        veil, transmission = np.empty(shape, np.float32), np.empty(shape, np.float32)
        integrate_silt(
            self._veil_directions, lamps.position, lamps.axis, lamps.power, lamps.profile,
            puffs, np.asarray(SCATTERING_M2_PER_G), np.asarray(EXTINCTION_M2_PER_G),
            self._kept, SILT_PHASE_G, table.far, table.bins, 2, veil, transmission,
        )  # fmt: skip
        return veil.reshape(table.values.shape), transmission.reshape(table.values.shape)

    def _lamps_at(self, origin: np.ndarray, rot: np.ndarray) -> tuple:
        """The lamps in the world frame of a camera at ``origin`` turned by ``rot``, as the
        kernels take them: (position, axis, power, profile)."""
        lamps = self._lamps
        position = (origin + lamps.position @ rot.T).astype(np.float32)
        axis = (lamps.axis @ rot.T).astype(np.float32)
        return position, axis, lamps.power, lamps.profile

    def _splat_specks(
        self, origin: np.ndarray, rot: np.ndarray, lamp_tuple: tuple, depth: np.ndarray
    ) -> int:
        """Draw the lit marine snow into the speck buffers; the number of specks drawn."""
        if self._speck_blocks.any():  # a render interrupted after drawing its specks
            self._specks[:] = 0.0
            self._speck_blocks[:] = 0
        optics, camera = self.config.optics, self.config.camera
        if not (optics.particles > 0 and self._lamps.power.any()):
            return 0
        return splat_particles(  # type: ignore[call-arg]  # a numba kernel: typed at its call
            origin, rot, *lamp_tuple, self._attenuation, optics.particles, self.config.seed,
            PARTICLE_REACH_M, camera.focal_px, camera.width, camera.height, depth,
            self._specks, self._speck_blocks,
        )  # fmt: skip

    def forward_frame(self, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Planar depth (H, W) float32 metres, its PNG (H, W) uint8 and colour (H, W, 3) uint8."""
        frame = self.render(pose)
        return frame.depth_m, frame.depth_png, frame.rgb

    def echo_sounders(self, pose: Pose) -> tuple[float, float]:
        """(d_top, d_bottom) in metres from the vehicle's centre."""
        rays = np.empty((2 * len(self._sounder_dirs), 6), np.float32)
        self._sounder_rays(pose, rays)
        return self._readings(self.caster.cast_raw_rays(rays)["t_hit"])

    def observe(
        self,
        pose: Pose,
        step: int = 0,
        noise_seed: int | None = None,
        silt: SiltCloud | None = None,
        cast: Mapping[str, np.ndarray] | None = None,
    ) -> Observation:
        """Render everything a pilot sees at ``pose``, from one ray cast.

        Args:
            noise_seed: seeds this observation's sensor noise (an episode's own draw);
                None uses the configuration's seed.
            silt: the silt hanging in the water (`cavenav.world.silt`); None: clear.
            cast: what `RayCaster.cast_raw_rays` gave for `rays` at ``pose``, when the
                caller cast them with others; None casts here.
        """
        cfg = self.config
        frame, (d_top, d_bottom) = self._render(pose, False, noise_seed, silt, cast)
        return Observation(
            rgb=frame.rgb,
            depth_m=frame.depth_m,
            depth_png=frame.depth_png,
            d_top=d_top,
            d_bottom=d_bottom,
            depth_range=(cfg.depth_min_m, cfg.depth_max_m),
            hfov_deg=cfg.camera.hfov_deg,
            camera_offset_m=cfg.camera_offset_m,
            step=step,
            has_depth=cfg.depth_source != "none",
            depth_source=cfg.depth_source,
            guideline=None if self.guideline is None else self.guideline.colour,
        )

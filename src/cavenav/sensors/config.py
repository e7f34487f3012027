"""What the sensors are, before a cave is known: `SensorConfig`.

Kept apart from the rig (`cavenav.sensors.rig`), which compiles its kernels on import, so
that the command line and the episode configuration can name these settings and their
defaults without loading them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from cavenav.core.errors import ConfigError
from cavenav.sensors.camera import CameraIntrinsics, pixel_size
from cavenav.sensors.depth import DEPTH_RANGE_M
from cavenav.sensors.optics import Optics, optics_from_table
from cavenav.sensors.stereo import StereoCamera

__all__ = ["DEPTH_SOURCES", "SENSOR_KEYS", "SIZE_KEYS", "SONAR_KINDS", "SensorConfig"]

# The keys of a scenario file's [sensors] table and of the matching run options: the
# cameras' sizes, then the acoustic instruments the vehicle carries.
SIZE_KEYS = ("resolution", "sounder_resolution")
SENSOR_KEYS = (*SIZE_KEYS, "depth_source", "sonar", "dvl")
# What makes the depth image (`SensorConfig.depth_source`).
DEPTH_SOURCES = ("exact", "stereo", "none")
# The imaging sonars (`cavenav.sensors.sonar.SONARS`).
SONAR_KINDS = ("ping360", "multibeam")


@dataclass(frozen=True)
class SensorConfig:
    """Sensor set-up of SPEC section 2.

    Attributes:
        camera: forward RGB and depth intrinsics (co-located, identical); 640x480 by
            default. `with_resolution` changes the pixel count and keeps the lens: the
            horizontal field of view (53.1 degrees) is the same at every resolution,
            pixels are square and the vertical view follows the aspect ratio (84x84 sees
            53.1 x 53.1 degrees).
        depth_min_m, depth_max_m: range mapped to black and white in the depth PNG.
        camera_offset_m: the camera sits this far ahead of the vehicle's centre (the
            BlueROV2's front dome), so depth is measured from the nose.
        sounder: "camera" emulates each echo sounder as the reference set-up does, with an
            upward or downward depth camera whose minimum planar depth is taken; "beam"
            takes the minimum range over a cone of rays, like a single-beam sounder.
        sounder_fov_deg: full field of view of either model. 25 degrees is the beam width
            of a Ping2-class sounder; with the forward camera's 53 degrees, a round 5 m
            passage reads about 1.7 m to the ceiling from its centre (the side walls).
        sounder_pixels: resolution (width, height) of the emulating depth cameras; the
            minimum of a 32x24 image is as good as a full frame's for a smooth ceiling and
            costs nothing at 640x480 (0.5% of the rays), but 18% of them at 84x84: a
            smaller one (8x6) speeds up low-resolution training. Its field of view is
            kept at any size, as the forward camera's is.
        sounder_max_range_m: reading when nothing is in range.
        optics: water, lamps, daylight, rock, particles and camera of the colour image.
        seed: seeds the rock colours, the marine snow and, unless an observation is
            given a seed of its own, the sensor noise.
        depth_source: what makes the depth image: "exact" (the ray cast's depth, as the
            paper's S1-S5 are flown), "stereo" (a stereo camera's: no depth where the
            colour image has no texture to match, `cavenav.sensors.stereo`) or "none"
            (no depth camera: `Observation.has_depth` false).
        stereo: the stereo pair's figures, for "stereo".
        sonar: the imaging sonar the vehicle carries (`cavenav.sensors.sonar`):
            "ping360", "multibeam" or None.
        dvl: whether it carries a Doppler velocity log (`cavenav.sensors.dvl`).
    """

    camera: CameraIntrinsics = field(default_factory=CameraIntrinsics)
    depth_min_m: float = DEPTH_RANGE_M[0]
    depth_max_m: float = DEPTH_RANGE_M[1]
    camera_offset_m: float = 0.2
    sounder: Literal["camera", "beam"] = "camera"
    sounder_fov_deg: float = 25.0
    sounder_pixels: tuple[int, int] = (32, 24)
    sounder_max_range_m: float = 50.0
    optics: Optics = field(default_factory=Optics)
    seed: int = 0
    depth_source: Literal["exact", "stereo", "none"] = "exact"
    stereo: StereoCamera = field(default_factory=StereoCamera)
    sonar: Literal["ping360", "multibeam"] | None = None
    dvl: bool = False

    def __post_init__(self) -> None:
        # A D_max of 0 flies with every pixel at 0 m; NaN or a negative one breaks the
        # normalisation deep inside a step. Refuse them where they are set.
        lo, hi = self.depth_min_m, self.depth_max_m
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise ConfigError(
                f"depth range D_min = {lo} m, D_max = {hi} m: give finite distances with "
                "0 <= D_min < D_max"
            )
        object.__setattr__(
            self, "sounder_pixels", pixel_size(self.sounder_pixels, "sounder resolution")
        )
        if self.depth_source not in DEPTH_SOURCES:
            raise ConfigError(
                f"depth source {self.depth_source!r}: choose {', '.join(DEPTH_SOURCES)}"
            )
        if self.sonar not in (None, *SONAR_KINDS):
            raise ConfigError(f"sonar {self.sonar!r}: choose {', '.join(SONAR_KINDS)} or none")

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the forward camera in pixels."""
        return self.camera.width, self.camera.height

    def with_resolution(self, width: int, height: int) -> SensorConfig:
        """This set-up with the forward camera at ``width`` x ``height`` pixels, same lens:
        the horizontal field of view is kept, the vertical follows the aspect ratio.

        Raises:
            ConfigError: a size that is not a positive whole number of pixels.
        """
        return replace(self, camera=self.camera.with_resolution(width, height))

    def with_sensors(self, table: Mapping[str, Any], where: str = "[sensors]") -> SensorConfig:
        """This set-up with what ``table`` sets: ``resolution`` (the forward camera) and
        ``sounder_resolution``, each (width, height) in pixels; ``depth_source`` ("exact",
        "stereo" or "none"), ``sonar`` ("ping360",
        "multibeam" or "none") and ``dvl`` (true or false); None keeps the current value.

        Layered twice by the drivers (`for_scenario`), as the optics are: a scenario
        file's [sensors] table, then the flags.

        Raises:
            ConfigError: an unknown key or a bad size, naming ``where``.
        """
        unknown = sorted(set(table) - set(SENSOR_KEYS))
        if unknown:
            raise ConfigError(
                f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; "
                f"the keys are {', '.join(SENSOR_KEYS)}"
            )
        config = self
        if table.get("resolution") is not None:
            config = config.with_resolution(*pixel_size(table["resolution"], f"{where} resolution"))
        if table.get("sounder_resolution") is not None:
            size = pixel_size(table["sounder_resolution"], f"{where} sounder_resolution")
            config = replace(config, sounder_pixels=size)
        if table.get("depth_source") is not None:
            source = table["depth_source"]
            if source not in DEPTH_SOURCES:
                raise ConfigError(
                    f"{where} depth_source: {source!r}; choose {', '.join(DEPTH_SOURCES)}"
                )
            config = replace(config, depth_source=source)
        if table.get("sonar") is not None:
            sonar = table["sonar"]
            if sonar not in ("none", *SONAR_KINDS):
                raise ConfigError(
                    f"{where} sonar: {sonar!r}; choose {', '.join(SONAR_KINDS)} or none"
                )
            config = replace(config, sonar=None if sonar == "none" else sonar)
        if table.get("dvl") is not None:
            if not isinstance(table["dvl"], bool):
                raise ConfigError(f"{where} dvl: {table['dvl']!r}; give true or false")
            config = replace(config, dvl=table["dvl"])
        return config

    def with_optics(self, table: Mapping[str, Any], where: str = "[optics]") -> SensorConfig:
        """This set-up with the optics fields ``table`` sets (None keeps the current value).

        Layered twice by the drivers (`for_scenario`): a scenario file's [optics] table,
        then the flags.

        Raises:
            ConfigError: an unknown key or a bad value, naming ``where``.
        """
        return replace(self, optics=optics_from_table(table, self.optics, where=where))

    def for_scenario(
        self,
        scenario: str,
        scenario_optics: Mapping[str, Any],
        options: Mapping[str, Any],
        scenario_sensors: Mapping[str, Any] | None = None,
        sensor_options: Mapping[str, Any] | None = None,
    ) -> SensorConfig:
        """This set-up with a scenario's [optics] and [sensors] tables, then the run's
        optics and sensor options over them: the one layering `cavenav run`, `render` and
        every episode of a sweep share.

        Args:
            options: the run's optics options (see `with_optics`).
            scenario_sensors: the scenario's [sensors] table (see `with_sensors`).
            sensor_options: the run's sizes over it (see `with_sensors`).

        Raises:
            ConfigError: an unknown key or a bad value, naming the scenario or "options".
        """
        return (
            self.with_optics(scenario_optics, where=f"{scenario}: [optics]")
            .with_optics(options, where="options")
            .with_sensors(scenario_sensors or {}, where=f"{scenario}: [sensors]")
            .with_sensors(sensor_options or {}, where="options")
        )

"""A simulated BlueROV2's own sensors in a simulated cave, for `cavenav fake-sub --scene`.

`cavenav fly` without ``--sim`` reads a vehicle's camera stream and echo sounders and
nothing else. To fly that very loop with no vehicle, the fake autopilot
(`cavenav.vehicle.fake_sub`) is placed in a cave: `CaveSensors` renders the forward
camera at the fake's true pose and streams it as RTP H.264 (`FakeCamera`, as BlueOS
sends it), and answers as two Ping1Ds with the ranges above and below it
(`FakePing1D`). Asked, it also answers as a Ping360 scanning sonar (`FakePing360`:
each ping's echoes rendered at the angle and range asked, `cavenav.sensors.sonar`) and
streams a Water Linked DVL A50's reports (`FakeDvl`: the velocity over the ground between
its reports, `cavenav.sensors.dvl`). The bridge then knows only what a real vehicle would
tell it: no mesh, no true pose, no depth image (a monocular model makes one from the
stream, if asked).

The fake sub's start (north, east, down and heading) is paired with the scenario's start
pose (`cavenav.vehicle.frames.NedFrame`). The fake sub is kinematic and passes through
rock: the status line shows the true clearance, and says when the vehicle is inside rock.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from dataclasses import replace
from types import TracebackType

import numpy as np

from cavenav.core.types import Pose
from cavenav.sensors.dvl import DopplerLog
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.sensors.sonar import PING360, Sonar
from cavenav.vehicle.camera import FakeCamera
from cavenav.vehicle.fake_sub import FakeSub
from cavenav.vehicle.frames import NedFrame, NedPose
from cavenav.vehicle.ping import FakePing1D
from cavenav.vehicle.ping360 import FakePing360
from cavenav.vehicle.waterlinked import DvlVelocity, FakeDvl
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import Scenario

__all__ = ["CaveSensors"]


class CaveSensors:
    """The camera stream and the two sounders of ``sub``, rendered in ``scenario``."""

    def __init__(
        self,
        sub: FakeSub,
        scenario: Scenario,
        sensors: SensorConfig,
        camera_port: int,
        ping_ports: tuple[int, int],
        fps: float = 5.0,
        sonar_port: int | None = None,
        dvl_port: int | None = None,
    ):
        """
        Args:
            sonar_port: where a Ping360 answers on 127.0.0.1 (UDP); None: not fitted.
            dvl_port: where a DVL streams on 127.0.0.1 (TCP); None: not fitted.

        Raises:
            ConfigError: a sounder's, the sonar's or the DVL's port is taken.
        """
        self.sub, self.scenario = sub, scenario
        self.caster = RayCaster(scenario.mesh)
        self._rig = SensorRig(self.caster, sensors, scenario.guideline)
        self._lock = threading.Lock()  # the rig's buffers serve one caller at a time
        self._sonars: dict[tuple[int, float], Sonar] = {}  # by the samples and range asked
        start = sub.config
        self._frame = NedFrame(
            NedPose(*start.start_ned, yaw=math.radians(start.start_yaw_deg)), scenario.start
        )
        self._stack = contextlib.ExitStack()
        try:
            self.up = self._stack.enter_context(FakePing1D(self._up, port=ping_ports[0]))
            self.down = self._stack.enter_context(FakePing1D(self._down, port=ping_ports[1]))
            self.sonar = self.dvl = None
            if sonar_port is not None:
                self.sonar = self._stack.enter_context(FakePing360(self._echo, sonar_port))
            if dvl_port is not None:
                self._doppler = DopplerLog(self.caster)
                self._moved_from: tuple[float, Pose] | None = None
                self.dvl = self._stack.enter_context(FakeDvl(self._velocity, port=dvl_port))
        except BaseException:
            self._stack.close()
            raise
        self.camera = FakeCamera(self._image, camera_port, fps)

    def pose(self) -> Pose:
        """Where the fake sub truly is, in the cave's frame."""
        state = self.sub.state()
        return self._frame.to_world(
            NedPose(state.north, state.east, state.down, math.radians(state.yaw_deg))
        )

    def clearance_m(self) -> float:
        """The body centre's distance to the nearest rock; negative inside rock."""
        position = self.pose().position[None].astype(np.float32)
        distance = float(self.caster.distance(position)[0])
        # In water, a ray straight up leaves through an odd number of surfaces.
        up = self.caster.count_intersections(position, np.array([[0.0, 0.0, 1.0]], np.float32))
        return distance if int(up[0]) % 2 else -distance

    def _image(self, index: int) -> np.ndarray:
        with self._lock:
            return self._rig.render(self.pose()).rgb

    def _up(self) -> float:
        with self._lock:
            return self._rig.echo_sounders(self.pose())[0]

    def _down(self) -> float:
        with self._lock:
            return self._rig.echo_sounders(self.pose())[1]

    def _echo(self, angle_deg: float, samples: int, range_m: float) -> np.ndarray:
        """One Ping360 ping's echoes at ``angle_deg`` (clockwise from ahead) over
        ``range_m`` in ``samples`` bins, at the sub's true pose."""
        bearing = (angle_deg + 180.0) % 360.0 - 180.0
        key = (samples, round(range_m, 3))
        with self._lock:
            sonar = self._sonars.get(key)
            if sonar is None:
                sonar = Sonar(self.caster, replace(PING360, samples=samples, range_m=range_m))
                self._sonars[key] = sonar
            return sonar.ping(self.pose(), np.array([bearing]))[0]

    def _velocity(self) -> DvlVelocity:
        """The DVL's report: the mean velocity over the ground since the last one, in its
        frame (x forward, y right, z down), ranged at the sub's true pose."""
        now, pose = time.time(), self.pose()
        then, before = self._moved_from or (now, pose)
        self._moved_from = (now, pose)
        with self._lock:
            reading = self._doppler.measure(before, pose, now - then)
        forward, left, up = np.nan_to_num(reading.velocity_m_s) * reading.locked
        ranges = reading.beam_ranges_m
        return DvlVelocity(
            time_s=now,
            velocity=np.array([forward, -left, -up]),
            valid=reading.locked,
            fom=reading.sigma_m_s if reading.locked else 0.0,
            altitude_m=reading.altitude_m if reading.locked else -1.0,
            beam_distances_m=np.where(np.isfinite(ranges), ranges, 0.0),
            beam_valid=np.isfinite(ranges),
        )

    def __enter__(self) -> CaveSensors:
        self._stack.enter_context(self.camera)
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self._stack.close()

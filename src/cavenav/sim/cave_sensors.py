"""A simulated BlueROV2's own sensors in a simulated cave, for `cavenav fake-sub --scene`.

`cavenav fly` without ``--sim`` reads a vehicle's camera stream and echo sounders and
nothing else. To fly that very loop with no vehicle, the fake autopilot
(`cavenav.vehicle.fake_sub`) is placed in a cave: `CaveSensors` renders the forward
camera at the fake's true pose and streams it as RTP H.264 (`FakeCamera`, as BlueOS
sends it), and answers as two Ping1Ds with the ranges above and below it
(`FakePing1D`). The bridge then knows only what a real vehicle would tell it: no mesh,
no true pose, no depth image (a monocular model makes one from the stream, if asked).

The fake sub's start (north, east, down and heading) is paired with the scenario's start
pose (`cavenav.vehicle.frames.NedFrame`). The fake sub is kinematic and passes through
rock: the status line shows the true clearance, and says when the vehicle is inside rock.
"""

from __future__ import annotations

import contextlib
import math
import threading
from types import TracebackType

import numpy as np

from cavenav.core.types import Pose
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.vehicle.camera import FakeCamera
from cavenav.vehicle.fake_sub import FakeSub
from cavenav.vehicle.frames import NedFrame, NedPose
from cavenav.vehicle.ping import FakePing1D
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
    ):
        """
        Raises:
            ConfigError: a sounder's port is taken.
        """
        self.sub, self.scenario = sub, scenario
        self.caster = RayCaster(scenario.mesh)
        self._rig = SensorRig(self.caster, sensors)
        self._lock = threading.Lock()  # the rig's buffers serve one caller at a time
        start = sub.config
        self._frame = NedFrame(
            NedPose(*start.start_ned, yaw=math.radians(start.start_yaw_deg)), scenario.start
        )
        self._stack = contextlib.ExitStack()
        try:
            self.up = self._stack.enter_context(FakePing1D(self._up, port=ping_ports[0]))
            self.down = self._stack.enter_context(FakePing1D(self._down, port=ping_ports[1]))
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

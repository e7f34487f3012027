"""A vehicle's own imaging sonar and DVL, as each step's observation carries them.

`cavenav fly --sonar udp:HOST:PORT` reads a Ping360 (`cavenav.vehicle.ping360`) and
`--dvl tcp:HOST:16171` a Water Linked DVL (`cavenav.vehicle.waterlinked`). Both run on
threads of their own between the steps, as the devices do: the sonar's head keeps
sweeping its sector, and the DVL keeps reporting. At each step:

- `SweptSonar.image` gives the disc as Ping Viewer shows it: every angle's latest echoes,
  their age (0 for those swept since the last step, as the simulator counts them), and
  the fan image (`cavenav.sensors.sonar.fan_lookup`);
- `DvlFeed.reading` gives the mean velocity over the ground since the last step, from the
  valid reports in between (each weighted by the time to the next), in the body frame the
  simulator's DVL uses (forward, left, up: the A50's x forward, y right, z down turned
  over), with its lock (most of the time locked) and latest altitude.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np

from cavenav.core.errors import VehicleError
from cavenav.core.types import DvlReading, SonarImage
from cavenav.sensors.sonar import GRADIANS, PING360, fan_lookup

__all__ = ["DvlFeed", "SweptSonar"]


class SweptSonar:
    """A Ping360 (a `cavenav.vehicle.ping360.Ping360Sonar`) swept on a thread of its own."""

    def __init__(self, sonar: Any, image_size: int = 400):  # noqa: ANN401 - lazily imported
        settings = sonar.settings
        samples = settings.timing.number_of_samples
        self.config = replace(
            PING360, range_m=settings.timing.range_m, samples=samples,
            sector_deg=settings.sector_deg, step_grad=settings.step_grad,
        )  # fmt: skip
        self._sonar = sonar
        self._echoes = np.zeros((GRADIANS // settings.step_grad, samples), np.uint8)
        self._pinged_at = np.full(len(self._echoes), -math.inf)
        self._shown_at = -math.inf  # when `image` was last asked for
        self._lookup = fan_lookup(self.config, image_size)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._failure: VehicleError | None = None
        self._thread = threading.Thread(target=self._sweep, daemon=True, name="cavenav-ping360")
        self._thread.start()

    def _sweep(self) -> None:
        while not self._stop.is_set():
            try:
                pings = self._sonar.sweep(1)
            except VehicleError as exc:
                self._failure = exc
                return
            with self._lock:
                for angle, data in pings:
                    row = (angle // self._sonar.settings.step_grad) % len(self._echoes)
                    self._echoes[row] = data[: self._echoes.shape[1]]
                    self._pinged_at[row] = time.monotonic()

    def image(self) -> SonarImage:
        """The disc as swept so far (module docstring).

        Raises:
            VehicleError: the sonar stopped answering.
        """
        if self._failure is not None:
            raise self._failure
        now = time.monotonic()
        with self._lock:
            echoes, pinged_at = self._echoes.copy(), self._pinged_at.copy()
        # The angles swept since the last step are this step's, as the simulator's are.
        age = np.where(pinged_at > self._shown_at, 0.0, now - pinged_at)
        self._shown_at = now
        flat = np.append(echoes.ravel(), np.uint8(0))
        cfg = self.config
        return SonarImage(
            kind="ping360", echoes=echoes, bearings_deg=cfg.bearings_deg(),
            range_m=cfg.range_m, fan=flat[self._lookup], age_s=age,
            frequency_khz=cfg.frequency_khz, beam_width_deg=cfg.beam_width_deg,
            aperture_deg=cfg.aperture_deg,
        )  # fmt: skip

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._sonar.close()


class DvlFeed:
    """A Water Linked DVL (`cavenav.vehicle.waterlinked.WaterLinkedDvl`) read between
    steps on a thread of its own."""

    def __init__(self, dvl: Any):  # noqa: ANN401 - lazily imported
        self._dvl = dvl
        self._lock = threading.Lock()
        self._reports: list[Any] = []
        self._stop = threading.Event()
        self._failure: VehicleError | None = None
        self._since = time.monotonic()
        self._thread = threading.Thread(target=self._read, daemon=True, name="cavenav-dvl")
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                report = self._dvl.next_velocity(timeout_s=2.0)
            except VehicleError as exc:
                self._failure = exc
                return
            with self._lock:
                self._reports.append(report)

    def reading(self) -> DvlReading | None:
        """The mean velocity since the last reading (module docstring); None before the
        first report.

        Raises:
            VehicleError: the DVL stopped reporting.
        """
        if self._failure is not None:
            raise self._failure
        now = time.monotonic()
        with self._lock:
            reports, self._reports = self._reports, self._reports[-1:]
        seconds, self._since = now - self._since, now
        if not reports:
            return None
        return _mean_reading(reports, seconds)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._dvl.close()


def _mean_reading(reports: list[Any], seconds: float) -> DvlReading:
    """The reports' time-weighted mean velocity, turned into the body frame."""
    times = np.array([r.time_s for r in reports])
    weights = np.diff(
        times, append=times[-1] + (np.median(np.diff(times)) if len(times) > 1 else 1.0)
    )
    valid = np.array([r.valid for r in reports])
    latest = reports[-1]
    locked = bool(weights[valid].sum() >= 0.5 * weights.sum())
    velocity = np.full(3, np.nan)
    if locked:
        mean = np.average(
            [r.velocity for r in np.array(reports)[valid]], axis=0, weights=weights[valid]
        )
        velocity = np.array([mean[0], -mean[1], -mean[2]])  # x fwd, y right, z down -> f, l, u
    return DvlReading(
        velocity_m_s=velocity,
        locked=locked,
        altitude_m=float(latest.altitude_m) if latest.valid else math.nan,
        beam_ranges_m=np.where(latest.beam_valid, latest.beam_distances_m, np.inf),
        seconds=seconds,
        sigma_m_s=float(latest.fom) / math.sqrt(max(int(valid.sum()), 1)),
    )

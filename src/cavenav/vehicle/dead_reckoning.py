"""Where a vehicle with no position estimate is: dead reckoning, with its uncertainty.

A BlueROV2 without a DVL measures its depth (the Bar30 pressure sensor, in
``SCALED_PRESSURE2``; see `cavenav.vehicle.mavlink`) and its heading (``ATTITUDE.yaw``),
but not where it is across the cave: ArduSub then sends no ``LOCAL_POSITION_NED``. The horizontal
position is reckoned from the commanded motion: each move's forward and sideways
metres, turned by the heading measured after the move (ALT_HOLD holds the heading while
it translates), added up. Depth and heading are measured, so they do not drift.

The uncertainty (one standard deviation, metres, horizontal) has two parts, each a
setting of the bridge:

- the speed calibration (``distance_error``, a fraction): manual moves are timed stick
  holds over a calibrated rate, and a rate that is off by a fraction is off on every
  move alike, so this part grows with the distance flown, not its square root;
- the heading (``heading_error_deg``): the compass's error, taken as independent from
  move to move (the vehicle's own steel, lamps and tether change with its attitude),
  so this part adds in quadrature, each move's length times the angle.

Neither is a measurement of the vehicle: they say what a calibration of that quality
implies. A current's drift, which a vehicle without a DVL cannot see, is not in them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from cavenav.vehicle.frames import body_to_ned

__all__ = ["DeadReckoning"]


@dataclass(frozen=True)
class DeadReckoning:
    """The reckoned horizontal position (north, east; metres from where it began).

    Attributes:
        flown_m: horizontal metres commanded so far.
        heading_variance_m2: the heading errors' part of the variance, summed.
    """

    distance_error: float = 0.1
    heading_error_deg: float = 3.0
    north: float = 0.0
    east: float = 0.0
    flown_m: float = 0.0
    heading_variance_m2: float = 0.0

    def moved(self, forward: float, right: float, yaw: float) -> DeadReckoning:
        """After a translation of ``forward`` and ``right`` metres (body frame) at the
        heading ``yaw`` (radians clockwise from north, as measured)."""
        north, east = body_to_ned(forward, right, yaw)
        length = math.hypot(forward, right)
        return replace(
            self,
            north=self.north + north,
            east=self.east + east,
            flown_m=self.flown_m + length,
            heading_variance_m2=self.heading_variance_m2
            + (length * math.radians(self.heading_error_deg)) ** 2,
        )

    @property
    def sigma_m(self) -> float:
        """One standard deviation of the horizontal position, metres."""
        return math.sqrt((self.distance_error * self.flown_m) ** 2 + self.heading_variance_m2)

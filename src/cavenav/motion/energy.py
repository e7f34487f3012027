"""What a move costs a BlueROV2's battery: thrusters, electronics and lamps.

A BlueROV2 (standard frame) carries six T200 thrusters: four horizontal ones vectored at
45 degrees, which share surge and sway, and two vertical ones. Its pack is 4S lithium-ion,
14.8 V and 18 Ah (266 Wh).

- **Drag.** The vehicle's drag grows as the square of its speed through the water. Its
  coefficient along the vehicle is set by Blue Robotics' published figures: at its top
  speed of 1.5 m/s the four vectored thrusters at full thrust balance the drag. Across
  and up-down the coefficient scales with the face the body shows the flow
  (`cavenav.core.types.VehicleBody`'s 0.46 x 0.34 x 0.25 m), at the same drag coefficient.
  Turning in place costs only the electronics over its duration: the drag torque of a
  0.46 m body turning at 30 degrees a second is about 0.06 N m.
- **Thrusters.** Each T200 draws power as thrust to the power 1.5 (momentum theory for a
  propeller at rest in the water), scaled to the full-throttle points of Blue Robotics'
  T200 performance table: 3.71 kgf at 205 W at 12 V, 5.25 kgf at 390 W at 16 V, taken
  linearly at the pack's 14.8 V. Reverse thrust is taken as efficient as forward (the
  T200 is somewhat less so in reverse).
- **Hotel load.** The electronics (an estimate of 15 W: the companion computer, the flight
  controller, the camera and the tether interface) and the lamps. A Lumen light gives
  1,500 lm for 15 W, so each lamp draws lumens / 100 W.

Energy is counted for the time a move lasts through the water (`cavenav.world.current`).
The time the pilot takes to decide is not counted: it is a property of the model and the
machine it ran on, not of the vehicle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cavenav.core.errors import ConfigError
from cavenav.core.types import VehicleBody

__all__ = [
    "BATTERY_WH",
    "T200",
    "PowerModel",
    "Thruster",
    "checked_budget",
    "lamp_watts",
    "thrusters_w",
]

KGF_N = 9.80665
BATTERY_VOLTS, BATTERY_AH = 14.8, 18.0
BATTERY_WH = BATTERY_VOLTS * BATTERY_AH  # 266.4 Wh
TOP_SPEED_M_S = 1.5  # a BlueROV2's published top speed
HOTEL_W = 15.0
LUMENS_PER_WATT = 100.0  # a Lumen light: 1,500 lm for 15 W
VECTORED = math.cos(math.radians(45.0))


@dataclass(frozen=True)
class Thruster:
    """A thruster's draw: ``max_power_w`` at ``max_thrust_n``, as thrust^1.5 below it."""

    max_thrust_n: float
    max_power_w: float

    def power_w(self, thrust_n: np.ndarray) -> np.ndarray:
        """Electrical power for each thrust (either sign), capped at full throttle."""
        share = np.minimum(np.abs(thrust_n) / self.max_thrust_n, 1.0)
        return self.max_power_w * share * np.sqrt(share)  # sqrt is exact on every CPU


def _at_pack_voltage(at_12v: float, at_16v: float) -> float:
    return at_12v + (at_16v - at_12v) * (BATTERY_VOLTS - 12.0) / 4.0


T200 = Thruster(
    max_thrust_n=_at_pack_voltage(3.71, 5.25) * KGF_N, max_power_w=_at_pack_voltage(205.0, 390.0)
)


def thrusters_w(force_n: np.ndarray, thruster: Thruster) -> np.ndarray:
    """(k,) what six ``thruster`` draw to push (k, 3) body-frame forces (forward, right,
    up): surge and sway shared by the four vectored at 45 degrees, heave by the two
    vertical."""
    surge, sway, heave = force_n[:, 0], force_n[:, 1], force_n[:, 2]
    power, vectored = thruster.power_w, 4.0 * VECTORED
    return 2.0 * (
        power((surge + sway) / vectored) + power((surge - sway) / vectored) + power(heave / 2.0)
    )


def checked_budget(battery_wh: float | None) -> float | None:
    """An energy budget as given, or None for none.

    Raises:
        ConfigError: a budget that is not a finite energy above 0.
    """
    if battery_wh is not None and not (math.isfinite(battery_wh) and battery_wh > 0):
        raise ConfigError(f"battery {battery_wh} Wh: give a finite energy above 0")
    return battery_wh


def lamp_watts(count: int, lumens: float) -> float:
    """What ``count`` lamps of ``lumens`` each draw."""
    return count * lumens / LUMENS_PER_WATT


@dataclass(frozen=True)
class PowerModel:
    """A BlueROV2's electrical power as it flies (module docstring).

    Attributes:
        lamps_w: the lamps' draw (`lamp_watts`).
        hotel_w: the electronics' draw.
        thruster: each of the six thrusters.
        body: the vehicle's size, for drag across and up-down.
    """

    lamps_w: float = lamp_watts(2, 1500.0)
    hotel_w: float = HOTEL_W
    thruster: Thruster = T200
    body: VehicleBody = field(default_factory=VehicleBody)

    @property
    def drag_n_s2_m2(self) -> np.ndarray:
        """(3,) quadratic drag coefficients forward, right and up, N s^2 / m^2."""
        surge = 4.0 * VECTORED * self.thruster.max_thrust_n / TOP_SPEED_M_S**2
        b = self.body
        front = b.width * b.height
        return surge * np.array([1.0, b.length * b.height / front, b.length * b.width / front])

    def drag_n(self, through_water: np.ndarray) -> np.ndarray:
        """(k, 3) the drag at each (k, 3) body-frame velocity through the water, N."""
        return self.drag_n_s2_m2 * through_water * np.abs(through_water)

    def thrust_power_w(self, through_water: np.ndarray) -> np.ndarray:
        """(k,) the thrusters' draw at each (k, 3) body-frame velocity through the water."""
        return thrusters_w(self.drag_n(through_water), self.thruster)

    def energy_wh(self, dt: np.ndarray, through_water: np.ndarray) -> float:
        """Energy over time steps ``dt`` (k,) at velocities ``through_water`` (k, 3), Wh."""
        watts = self.thrust_power_w(through_water) + self.hotel_w + self.lamps_w
        return float((watts * dt).sum() / 3600.0)

    def straight_wh_per_m(self, speed_m_s: float) -> float:
        """What a metre straight ahead at ``speed_m_s`` costs, Wh."""
        return self.energy_wh(np.array([1.0 / speed_m_s]), np.array([[speed_m_s, 0.0, 0.0]]))

"""Multicopter land detector, PX4 style: landed is inferred from the estimate and the controller.

Three stages, each needing its condition to hold for a while (hysteresis): ground contact (asked to
descend but not moving down), maybe landed (thrust near the minimum, not rotating), landed (maybe
landed for LNDMC_TRIG_TIME). Never from JSBSim's truth: a real autopilot has no contact sensor.
"""

from __future__ import annotations

import math

from .params import ParamDef

LAND_PARAMS: list[ParamDef] = [
    ParamDef("LNDMC_Z_VEL_MAX", 0.5, 0.1, 10.0, "m/s", description="max vertical speed when landed"),
    ParamDef("LNDMC_XY_VEL_MAX", 1.5, 0.1, 10.0, "m/s", description="max horizontal speed when landed"),
    ParamDef("LNDMC_ROT_MAX", 20.0, 0.1, 180.0, "deg/s", description="max rotation rate when landed"),
    ParamDef("LNDMC_TRIG_TIME", 1.0, 0.1, 10.0, "s", description="maybe-landed time before landed"),
]

GROUND_CONTACT_TIME_S = 0.35
MAYBE_LANDED_TIME_S = 0.25


class LandDetector:
    def __init__(self, params):
        self.params = params
        self.landed = True
        self.maybe_landed = True
        self.ground_contact = True
        self._t_contact = 0.0
        self._t_maybe = 0.0
        self._t_landed = 0.0

    def reset_flying(self) -> None:
        """Takeoff: everything false until the conditions build up again."""
        self.landed = self.maybe_landed = self.ground_contact = False
        self._t_contact = self._t_maybe = self._t_landed = 0.0

    def update(self, dt: float, vel_ned, rates_frd, thrust: float, thrust_hover: float, thrust_min: float,
               descend_commanded: bool) -> bool:
        p = self.params
        vz_ok = abs(vel_ned[2]) < p["LNDMC_Z_VEL_MAX"]
        xy_ok = math.hypot(vel_ned[0], vel_ned[1]) < p["LNDMC_XY_VEL_MAX"]
        rot_max = math.radians(p["LNDMC_ROT_MAX"])
        rot_ok = abs(rates_frd[0]) < rot_max and abs(rates_frd[1]) < rot_max and abs(rates_frd[2]) < rot_max
        contact = descend_commanded and vz_ok and thrust < thrust_min + 0.6 * (thrust_hover - thrust_min)
        low_thrust = thrust < thrust_min + 0.3 * (thrust_hover - thrust_min)
        self._t_contact = self._t_contact + dt if contact else 0.0
        self.ground_contact = self._t_contact >= GROUND_CONTACT_TIME_S
        maybe = self.ground_contact and low_thrust and xy_ok and rot_ok
        self._t_maybe = self._t_maybe + dt if maybe else 0.0
        self.maybe_landed = self._t_maybe >= MAYBE_LANDED_TIME_S
        self._t_landed = self._t_landed + dt if self.maybe_landed else 0.0
        self.landed = self._t_landed >= p["LNDMC_TRIG_TIME"]
        return self.landed

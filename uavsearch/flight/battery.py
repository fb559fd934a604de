"""Simulated LiPo battery: current follows rotor power, so the charge drains with thrust.

Rotor power from momentum theory grows as thrust^1.5; the constant is set so that this 1.5 kg
airframe draws about 12 A at hover on 4S, a typical figure for the class.
"""

from __future__ import annotations

from .params import ParamDef

BATTERY_PARAMS: list[ParamDef] = [
    ParamDef("BAT1_CAPACITY", 5000.0, 50.0, 100000.0, "mAh", description="battery capacity"),
    ParamDef("BAT1_N_CELLS", 4, 1, 14, "", type="int", description="cells in series"),
    ParamDef("BAT1_V_CHARGED", 4.2, 3.5, 4.4, "V", description="cell voltage when full"),
    ParamDef("BAT1_V_EMPTY", 3.5, 2.5, 4.0, "V", description="cell voltage when empty"),
    ParamDef("BAT1_R_INTERNAL", 0.02, 0.0, 0.5, "Ohm", description="pack internal resistance"),
]

AVIONICS_CURRENT_A = 0.5
ROTOR_CURRENT_A_PER_N15 = 0.41  # A per N^1.5 of each rotor's thrust


class Battery:
    def __init__(self, params):
        self.params = params
        self.discharged_mah = 0.0
        self.current_a = 0.0

    def update(self, rotor_thrusts_n, dt: float, armed: bool) -> None:
        i = AVIONICS_CURRENT_A
        if armed:
            i += ROTOR_CURRENT_A_PER_N15 * sum(t**1.5 for t in rotor_thrusts_n if t > 0.0)
        self.current_a = i
        self.discharged_mah += i * dt / 3.6

    @property
    def remaining(self) -> float:
        return max(0.0, 1.0 - self.discharged_mah / self.params["BAT1_CAPACITY"])

    @property
    def voltage_v(self) -> float:
        p = self.params
        cell = p["BAT1_V_EMPTY"] + (p["BAT1_V_CHARGED"] - p["BAT1_V_EMPTY"]) * self.remaining
        return max(0.0, p["BAT1_N_CELLS"] * cell - self.current_a * p["BAT1_R_INTERNAL"])

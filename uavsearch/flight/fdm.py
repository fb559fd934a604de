"""JSBSim wrapper for the quadrotor: the only module that sees JSBSim's imperial units and property names.

Everything crossing this module's boundary is SI: metres, m/s, radians, newtons, scene ENU for positions
and NED for velocities (what a GPS would see). Property nodes are looked up once: reading them is
cheap, name lookups per step are not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import UavsearchError
from ..geometry import GeodeticOrigin
from ..paths import AIRCRAFT_DIR

import jsbsim

FT = 0.3048
LBF = 4.4482216152605
LBFFT = 1.3558179483314  # N*m per lbf*ft
N_ROTORS = 4
# Touching the ground faster than this (m/s, down) is a crash, not a landing: PX4's landings descend at
# 0.7 m/s and never exceed 3 m/s; a vehicle disarmed in the air hits at tens of m/s. JSBSim's contact model is
# not made for such impacts (the body rates diverge to overflow within seconds), so a crashed vehicle is held
# as a wreck at rest where it hit instead of being integrated further.
CRASH_SPEED_M_S = 6.0


def _quiet_jsbsim() -> None:
    """No banner on stdout when an FGFDMExec is made: JSBSim's own (process-wide, static) debug level, which a
    JSBSIM_DEBUG the user exported still overrides; the environment is never touched."""
    jsbsim.FGJSBBase().debug_lvl = 0


@dataclass(frozen=True)
class AirframeInfo:
    """Constants of the airframe that the controllers and battery need (must match the XML)."""

    mass_kg: float = 1.5
    rotor_thrust_max_n: float = 7.5
    arm_x_m: float = 0.18  # rotor offsets from the CG along body x and y
    arm_y_m: float = 0.18
    yaw_moment_per_thrust_m: float = 0.016
    inertia_kg_m2: tuple = (0.029, 0.029, 0.055)
    # PX4 quad-x order: (x forward, y right) position and spin (+1 = CCW from above -> +yaw reaction)
    rotors: tuple = ((1, 1, +1), (-1, -1, +1), (1, -1, -1), (-1, 1, -1))


QUADX = AirframeInfo()


class QuadFdm:
    """One JSBSim instance of the `quadx` airframe, stepped one physics tick at a time."""

    def __init__(
        self,
        home: GeodeticOrigin,
        physics_hz: int,
        start_enu=(0.0, 0.0, 0.0),
        start_yaw_rad: float = 0.0,
        model: str = "quadx",
        airframe: AirframeInfo = QUADX,
    ):
        if not (isinstance(physics_hz, int) and 50 <= physics_hz <= 2000):
            raise UavsearchError(f"physics_hz must be an integer in [50, 2000], got {physics_hz!r}")
        root = str(AIRCRAFT_DIR)
        self.airframe = airframe
        self.home = home
        self.dt = 1.0 / physics_hz
        _quiet_jsbsim()
        fdm = jsbsim.FGFDMExec(root)
        fdm.set_debug_level(0)
        fdm.set_aircraft_path(root)
        if not fdm.load_model(model):
            raise UavsearchError(f"JSBSim could not load aircraft {model!r} from {root}")
        fdm.set_dt(self.dt)
        lla = home.enu_to_geodetic(np.array([start_enu[0], start_enu[1], 0.0]))
        fdm["ic/lat-geod-deg"] = float(lla[0])
        fdm["ic/long-gc-deg"] = float(lla[1])
        fdm["ic/terrain-elevation-ft"] = home.alt_m / FT
        # start just above the feet so the contacts settle within a few steps without a bounce
        fdm["ic/h-agl-ft"] = max(float(start_enu[2]), 0.117) / FT
        fdm["ic/psi-true-deg"] = math.degrees(start_yaw_rad) % 360.0
        fdm["ic/u-fps"] = fdm["ic/v-fps"] = fdm["ic/w-fps"] = 0.0
        if not fdm.run_ic():
            raise UavsearchError("JSBSim rejected the initial conditions")
        self._fdm = fdm
        pm = fdm.get_property_manager()
        node = lambda name: pm.get_node(name, False)  # noqa: E731
        self._cmd = [node(f"fcs/esc-cmd-{i}") for i in range(N_ROTORS)]
        self._rotor = [node(f"fcs/rotor-{i}-norm") for i in range(N_ROTORS)]
        self._lat = node("position/lat-geod-deg")
        self._lon = node("position/long-gc-deg")
        self._agl = node("position/h-agl-ft")
        self._vn, self._ve, self._vd = (node(f"velocities/v-{a}-fps") for a in ("north", "east", "down"))
        self._phi, self._theta, self._psi = (node(f"attitude/{a}-rad") for a in ("phi", "theta", "psi"))
        self._p, self._q, self._r = (node(f"velocities/{a}-rad_sec") for a in ("p", "q", "r"))
        self._fx, self._fy, self._fz = (node(f"forces/fb{a}-total-lbs") for a in ("x", "y", "z"))
        self._fz_gear = node("forces/fbz-gear-lbs")
        self._mass_node = node("inertia/mass-slugs")
        self._g_node = node("accelerations/gravity-ft_sec2")
        s = math.sin(math.radians(home.lat_deg))
        d = 1.0 - 6.69437999014e-3 * s * s
        # same tangent plane as GeodeticOrigin (radii in m per degree), inlined because it runs every step
        self._m_per_deg_lat = math.radians(1.0) * 6378137.0 * (1.0 - 6.69437999014e-3) / d**1.5
        self._m_per_deg_lon = math.radians(1.0) * 6378137.0 / math.sqrt(d) * math.cos(math.radians(home.lat_deg))
        self.steps = 0
        self.crashed = False  # hit the ground at CRASH_SPEED_M_S or faster: a wreck at rest from then on
        self._crash_vd_fps = CRASH_SPEED_M_S / FT

    # ---------------------------------------------------------------- inputs
    def set_motor_commands(self, cmds) -> None:
        """Normalised thrust per rotor in [0, 1] (PX4 quad-x order); the ESC lag is inside JSBSim."""
        for node, c in zip(self._cmd, cmds):
            node.set_double_value(0.0 if c < 0.0 else (1.0 if c > 1.0 else float(c)))

    def step(self) -> None:
        self.steps += 1
        if self.crashed:
            return
        self._fdm.run()
        if self._fz_gear.get_double_value() < 0.0 and self._vd.get_double_value() > self._crash_vd_fps:  # in the air: one read
            self._wreck()

    def _wreck(self) -> None:
        """Hold the vehicle at rest on the ground where it hit, level, its rotors stopped."""
        e, n, _ = self.position_enu_m()
        g = self.gravity_m_s2
        self._held = {"position": (e, n, 0.0), "euler": (0.0, 0.0, self.euler_rad()[2]),
                      "specific_force": (0.0, 0.0, -g), "ground_force": self.mass_kg * g}
        self.crashed = True

    def set_wind_ned(self, north_m_s: float, east_m_s: float, down_m_s: float = 0.0) -> None:
        """Steady wind (the air's velocity over ground); the body drag acts on the airspeed."""
        self._fdm["atmosphere/wind-north-fps"] = north_m_s / FT
        self._fdm["atmosphere/wind-east-fps"] = east_m_s / FT
        self._fdm["atmosphere/wind-down-fps"] = down_m_s / FT

    # ---------------------------------------------------------------- truth (SI)
    @property
    def mass_kg(self) -> float:
        return self._mass_node.get_double_value() * 14.59390294

    @property
    def gravity_m_s2(self) -> float:
        return self._g_node.get_double_value() * FT

    def position_enu_m(self) -> tuple[float, float, float]:
        if self.crashed:
            return self._held["position"]
        return (
            (self._lon.get_double_value() - self.home.lon_deg) * self._m_per_deg_lon,
            (self._lat.get_double_value() - self.home.lat_deg) * self._m_per_deg_lat,
            self._agl.get_double_value() * FT,
        )

    def velocity_ned_m_s(self) -> tuple[float, float, float]:
        if self.crashed:
            return (0.0, 0.0, 0.0)
        return (self._vn.get_double_value() * FT, self._ve.get_double_value() * FT, self._vd.get_double_value() * FT)

    def euler_rad(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw) of body FRD in NED; yaw wrapped to [-pi, pi)."""
        if self.crashed:
            return self._held["euler"]
        psi = self._psi.get_double_value()
        if psi >= math.pi:
            psi -= 2.0 * math.pi
        return self._phi.get_double_value(), self._theta.get_double_value(), psi

    def body_rates_rad_s(self) -> tuple[float, float, float]:
        if self.crashed:
            return (0.0, 0.0, 0.0)
        return self._p.get_double_value(), self._q.get_double_value(), self._r.get_double_value()

    def specific_force_frd_m_s2(self) -> tuple[float, float, float]:
        """What an ideal accelerometer at the CG reads: non-gravitational force / mass."""
        if self.crashed:
            return self._held["specific_force"]
        k = LBF / (self._mass_node.get_double_value() * 14.59390294)
        return self._fx.get_double_value() * k, self._fy.get_double_value() * k, self._fz.get_double_value() * k

    def ground_force_n(self) -> float:
        """Upward force of the ground on the feet (0 in the air)."""
        if self.crashed:
            return self._held["ground_force"]
        return -self._fz_gear.get_double_value() * LBF

    def rotor_thrusts_n(self) -> list[float]:
        if self.crashed:
            return [0.0] * N_ROTORS
        tmax = self.airframe.rotor_thrust_max_n
        return [n.get_double_value() * tmax for n in self._rotor]

    def property(self, name: str) -> float:
        """Raw JSBSim property (imperial), for diagnostics only."""
        return float(self._fdm[name])

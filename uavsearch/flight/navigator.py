"""Navigator: the autopilot's flight modes as small classes (PX4's navigator and flight tasks).

Each mode turns the estimate into a TrajectorySetpoint (local NED, NaN = not controlled) on every
autopilot tick; the commander decides which mode runs. Positions move along a trapezoidal "carrot"
(speed and acceleration limited, with velocity feed-forward) so that a position controller tuned for
small steps also flies long legs smoothly, as PX4's jerk-limited auto trajectories do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..geometry import GeodeticOrigin, wrap_pi
from .messages import TrajectorySetpoint, VehicleLandDetected, VehicleLocalPosition
from .mission import (
    DO_CHANGE_SPEED,
    DO_LAND_START,
    IMAGE_START_CAPTURE,
    NAV_LAND,
    NAV_LOITER_TIME,
    NAV_LOITER_UNLIM,
    NAV_RETURN_TO_LAUNCH,
    NAV_TAKEOFF,
    NAV_WAYPOINT,
    Mission,
)
from .params import ParamDef, ParamStore

NAV_PARAMS = [
    ParamDef("MIS_TAKEOFF_ALT", 2.5, 0.0, 200.0, "m", description="takeoff altitude above home"),
    ParamDef("NAV_ACC_RAD", 1.0, 0.05, 50.0, "m", description="horizontal acceptance radius of waypoints"),
    ParamDef("NAV_MC_ALT_RAD", 0.8, 0.05, 20.0, "m", description="vertical acceptance radius of waypoints"),
    ParamDef("RTL_RETURN_ALT", 60.0, 0.0, 500.0, "m", description="return altitude above home"),
    ParamDef("RTL_DESCEND_ALT", 30.0, 2.0, 500.0, "m", description="altitude above home before landing"),
    ParamDef("RTL_LAND_DELAY", 0.0, -1.0, 300.0, "s", description="hover above home before landing (-1: never land)"),
]

_NAN3 = np.full(3, math.nan)
_NAN3.flags.writeable = False

# Flight-core limits the navigator follows; used with these fallbacks if no table declares them.
_FALLBACKS = {
    "MPC_XY_CRUISE": 5.0,
    "MPC_Z_V_AUTO_UP": 3.0,
    "MPC_Z_V_AUTO_DN": 1.5,
    "MPC_ACC_HOR": 3.0,
    "MPC_ACC_UP_MAX": 4.0,
    "MPC_ACC_DOWN_MAX": 3.0,
    "MPC_LAND_SPEED": 0.7,
    "MPC_LAND_ALT1": 10.0,
    "MPC_LAND_ALT2": 5.0,
}


_ALIASES = {"MPC_Z_V_AUTO_UP": "MPC_Z_VEL_MAX_UP", "MPC_Z_V_AUTO_DN": "MPC_Z_VEL_MAX_DN"}


def param(params: ParamStore, name: str) -> float:
    if name in params:
        return params[name]
    alias = _ALIASES.get(name)
    if alias is not None and alias in params:
        return params[alias]
    return _FALLBACKS[name]


@dataclass
class NavState:
    """What every mode reads on each tick."""

    now_us: int
    local: VehicleLocalPosition
    landed: VehicleLandDetected


@dataclass
class NavEvent:
    kind: str  # "item_reached", "mission_current", "mission_finished", "capture", "done", "rtl", "text"
    value: object = None


class Carrot:
    """A position setpoint that travels to a target with speed and acceleration limits.

    Plain floats, not numpy: this runs on every autopilot tick and 3-vectors are cheaper as floats.
    """

    def __init__(self):
        self.reset((0.0, 0.0, 0.0))

    @property
    def pos(self) -> np.ndarray:
        return np.array(self._p)

    @property
    def vel(self) -> np.ndarray:
        return np.array(self._v)

    def reset(self, pos_ned, vel_ned=None) -> None:
        self._p = [float(pos_ned[0]), float(pos_ned[1]), float(pos_ned[2])]
        self._v = [0.0, 0.0, 0.0] if vel_ned is None else [float(vel_ned[0]), float(vel_ned[1]), float(vel_ned[2])]
        self.speed_xy = math.hypot(self._v[0], self._v[1])
        self.speed_z = abs(self._v[2])

    def step(self, target_ned, dt: float, v_xy: float, v_up: float, v_down: float, a_xy: float, a_z: float):
        p, v = self._p, self._v
        tx, ty, tz = float(target_ned[0]), float(target_ned[1]), float(target_ned[2])
        dx, dy = tx - p[0], ty - p[1]
        dist = math.hypot(dx, dy)
        self.speed_xy = min(v_xy, self.speed_xy + a_xy * dt, math.sqrt(2.0 * a_xy * dist))
        if dist > 1e-9:
            move = min(dist, self.speed_xy * dt)
            ux, uy = dx / dist, dy / dist
            p[0] += ux * move
            p[1] += uy * move
            if move < dist:
                v[0], v[1] = ux * self.speed_xy, uy * self.speed_xy
            else:
                v[0] = v[1] = 0.0
        else:
            v[0] = v[1] = 0.0
            self.speed_xy = 0.0
        dz = tz - p[2]
        vmax = v_down if dz > 0 else v_up
        self.speed_z = min(vmax, self.speed_z + a_z * dt, math.sqrt(2.0 * a_z * abs(dz)))
        move = min(abs(dz), self.speed_z * dt)
        p[2] += math.copysign(move, dz)
        v[2] = math.copysign(self.speed_z, dz) if move < abs(dz) else 0.0

    def arrived(self, target_ned) -> bool:
        return all(abs(a - float(b)) <= 1e-6 for a, b in zip(self._p, target_ned))


class Mode:
    """on_activation once when the commander selects the mode; on_active every tick."""

    def __init__(self, nav: "Navigator"):
        self.nav = nav

    def on_activation(self, s: NavState) -> None:
        pass

    def on_active(self, s: NavState) -> TrajectorySetpoint | None:
        raise NotImplementedError


class Hold(Mode):
    """Loiter at a point (PX4 AUTO_LOITER); DO_REPOSITION moves the point (PX4 keeps Hold mode)."""

    target: np.ndarray | None = None

    def on_activation(self, s: NavState) -> None:
        self.target = None if s.landed.landed else self.nav.braking_point(s)
        self.yaw = self.nav.current_yaw(s)
        self.speed = None
        self.nav.carrot_from_estimate(s)
        if self.nav.pending_hold is not None:
            self.reposition(*self.nav.pending_hold)
            self.nav.pending_hold = None

    def reposition(self, target_ned, yaw_rad: float, speed_m_s: float | None) -> None:
        self.target = np.asarray(target_ned, dtype=float)
        if math.isfinite(yaw_rad):
            self.yaw = yaw_rad
        self.speed = speed_m_s

    def on_active(self, s: NavState) -> TrajectorySetpoint | None:
        if self.target is None:
            return self.nav.ground_idle(s)
        return self.nav.follow(s, self.target, self.yaw, self.speed)


class Takeoff(Mode):
    """Climb vertically to home + MIS_TAKEOFF_ALT (or higher when asked), then report done."""

    requested_alt_amsl: float = math.nan

    def on_activation(self, s: NavState) -> None:
        p = s.local.position_ned_m
        home_alt_amsl = self.nav.origin.alt_m - self.nav.home_ned[2]
        min_alt = home_alt_amsl + self.nav.params["MIS_TAKEOFF_ALT"]
        alt = self.requested_alt_amsl if math.isfinite(self.requested_alt_amsl) else min_alt
        alt = max(alt, min_alt)  # PX4: a takeoff below MIS_TAKEOFF_ALT is raised to it
        if not s.landed.landed:
            alt = max(alt, self.nav.origin.alt_m - p[2])  # already flying: a takeoff never descends
        self.target = np.array([p[0], p[1], self.nav.origin.alt_m - alt])
        self.yaw = self.nav.current_yaw(s)
        self.nav.carrot.reset([p[0], p[1], p[2]])
        self.requested_alt_amsl = math.nan

    def on_active(self, s: NavState) -> TrajectorySetpoint:
        sp = self.nav.follow(s, self.target, self.yaw, None)
        if abs(s.local.position_ned_m[2] - self.target[2]) < self.nav.params["NAV_MC_ALT_RAD"] and not s.landed.landed:
            self.nav.emit("done", self.target.copy())
        return sp


class Land(Mode):
    """Descend at MPC_Z_V_AUTO_DN, slowing to MPC_LAND_SPEED near the ground, holding x/y."""

    def on_activation(self, s: NavState) -> None:
        self.xy = self.nav.braking_point(s)[:2]
        self.yaw = self.nav.current_yaw(s)

    def on_active(self, s: NavState) -> TrajectorySetpoint:
        if s.landed.landed:
            self.nav.emit("done")
        return self.nav.descend(s, self.xy, self.yaw)


class ReturnToLaunch(Mode):
    """Climb to RTL_RETURN_ALT, fly home, descend to RTL_DESCEND_ALT, wait RTL_LAND_DELAY, land."""

    phase = "climb"

    def on_activation(self, s: NavState) -> None:
        p = s.local.position_ned_m
        home = self.nav.home_ned
        rel_alt = home[2] - p[2]
        self.return_alt = max(rel_alt, self.nav.params["RTL_RETURN_ALT"])
        dist = float(np.hypot(*(p[:2] - home[:2])))
        if dist < self.nav.params["NAV_ACC_RAD"]:
            self.return_alt = max(rel_alt, min(self.nav.params["RTL_DESCEND_ALT"], rel_alt))
        self.phase = "climb"
        self.yaw = self.nav.current_yaw(s)
        self.nav.carrot_from_estimate(s)
        self.wait_start_us = None

    def on_active(self, s: NavState) -> TrajectorySetpoint:
        p = s.local.position_ned_m
        home = self.nav.home_ned
        if s.landed.landed and self.phase in ("climb",):
            return self.nav.ground_idle(s)
        if self.phase == "climb":
            tgt = np.array([self.nav.carrot.pos[0], self.nav.carrot.pos[1], home[2] - self.return_alt])
            if abs(p[2] - tgt[2]) < self.nav.params["NAV_MC_ALT_RAD"]:
                self.phase = "return"
            return self.nav.follow(s, tgt, self.yaw, None)
        if self.phase == "return":
            tgt = np.array([home[0], home[1], home[2] - self.return_alt])
            if self.nav.reached(s, tgt):
                self.phase = "descend"
            return self.nav.follow(s, tgt, self.yaw, None)
        if self.phase == "descend":
            alt = min(self.return_alt, self.nav.params["RTL_DESCEND_ALT"])
            tgt = np.array([home[0], home[1], home[2] - alt])
            if self.nav.reached(s, tgt):
                self.phase = "wait"
                self.wait_start_us = s.now_us
            return self.nav.follow(s, tgt, self.yaw, None)
        if self.phase == "wait":
            delay = self.nav.params["RTL_LAND_DELAY"]
            tgt = self.nav.carrot.pos.copy()
            if delay >= 0 and (s.now_us - self.wait_start_us) * 1e-6 >= delay:
                self.phase = "land"
            return self.nav.follow(s, tgt, self.yaw, None)
        if s.landed.landed:
            self.nav.emit("done")
        return self.nav.descend(s, home[:2], self.yaw)


class MissionMode(Mode):
    """Fly the stored mission item by item; DO items run at once; report reached / current.

    If started on the ground, it first climbs to max(MIS_TAKEOFF_ALT, first waypoint altitude) as
    PX4 does for a mission without a takeoff item.
    """

    def on_activation(self, s: NavState) -> None:
        m = self.nav.mission
        if m.finished:  # restarting a finished mission starts it over
            m.set_current(0)
        self.item_started = False
        self.loiter_start_us = None
        self.speed = None
        self.yaw = self.nav.current_yaw(s)
        self.nav.carrot_from_estimate(s)
        self.ground_start = bool(s.landed.landed)
        self.nav.emit("mission_current", m.current_seq)

    def _advance(self, s: NavState) -> None:
        m = self.nav.mission
        m.reached_seq = m.current_seq
        self.nav.emit("item_reached", m.current_seq)
        if m.current_seq + 1 >= len(m.items):
            m.finished = True
            self.nav.emit("mission_finished", m.current_seq)
        else:
            m.current_seq += 1
            self.nav.emit("mission_current", m.current_seq)
        self.item_started = False
        self.loiter_start_us = None

    def on_active(self, s: NavState) -> TrajectorySetpoint | None:
        m = self.nav.mission
        nav = self.nav
        for _ in range(len(m.items) + 1):  # DO items complete within the same tick
            if m.finished or not m.items:
                if s.landed.landed:
                    return nav.ground_idle(s)
                return nav.follow(s, nav.carrot.pos.copy(), self.yaw, None)
            it = m.items[m.current_seq]
            if it.command == DO_CHANGE_SPEED:
                if it.param2 > 0:
                    self.speed = float(it.param2)
                self._advance(s)
                continue
            if it.command == IMAGE_START_CAPTURE:
                nav.emit("capture", it)
                self._advance(s)
                continue
            if it.command == DO_LAND_START:  # a marker only
                self._advance(s)
                continue
            if it.command == NAV_RETURN_TO_LAUNCH:
                self._advance(s)
                nav.emit("rtl")
                return nav.follow(s, nav.carrot.pos.copy(), self.yaw, None)
            break
        tgt = it.position_ned(nav.origin, nav.home_ned)
        p = s.local.position_ned_m
        if not self.item_started:
            self.item_started = True
            if math.isfinite(it.param4) and it.command in (NAV_WAYPOINT, NAV_LOITER_TIME, NAV_TAKEOFF):
                self.yaw = float(wrap_pi(math.radians(it.param4)))
            self.item_target = tgt
            if it.command in (NAV_TAKEOFF, NAV_LAND, NAV_LOITER_UNLIM) and tgt is None:
                self.item_target = np.array([p[0], p[1], p[2]])
            if it.command == NAV_TAKEOFF:
                home_alt = nav.origin.alt_m - nav.home_ned[2]
                rel = it.z if it.frame in (3, 6) else it.z - home_alt
                rel = max(rel, nav.params["MIS_TAKEOFF_ALT"])
                self.item_target = np.array([p[0], p[1], nav.home_ned[2] - rel])
            if self.ground_start and it.command not in (NAV_TAKEOFF, NAV_LAND):
                rel = max(nav.params["MIS_TAKEOFF_ALT"], nav.home_ned[2] - self.item_target[2])
                self.climb_target = np.array([p[0], p[1], nav.home_ned[2] - rel])
            else:
                self.climb_target = None
            self.ground_start = False
        if self.climb_target is not None:
            if abs(p[2] - self.climb_target[2]) < nav.params["NAV_MC_ALT_RAD"] and not s.landed.landed:
                self.climb_target = None
            else:
                return nav.follow(s, self.climb_target, self.yaw, None)
        if it.command == NAV_LAND:
            if s.landed.landed:
                self._advance(s)
                return nav.ground_idle(s)
            if not hasattr(self, "land_xy_reached") or self.land_xy_reached is not it:
                tgt_air = np.array([self.item_target[0], self.item_target[1], p[2]])
                if nav.reached(s, tgt_air):
                    self.land_xy_reached = it
                return nav.follow(s, tgt_air, self.yaw, self.speed)
            return nav.descend(s, self.item_target[:2], self.yaw)
        sp = nav.follow(s, self.item_target, self.yaw, self.speed)
        if it.command == NAV_LOITER_UNLIM:
            return sp
        if self.loiter_start_us is None and nav.reached(s, self.item_target) and not s.landed.landed:
            self.loiter_start_us = s.now_us
        if self.loiter_start_us is not None:
            hold_s = it.param1 if it.command in (NAV_WAYPOINT, NAV_LOITER_TIME) else 0.0
            if (s.now_us - self.loiter_start_us) * 1e-6 >= hold_s:
                self._advance(s)
        return sp


class Offboard(Mode):
    """Follow setpoints streamed by an external client (SET_POSITION_TARGET_LOCAL_NED)."""

    def on_activation(self, s: NavState) -> None:
        pass

    def on_active(self, s: NavState) -> TrajectorySetpoint | None:
        sp = self.nav.offboard_setpoint
        if sp is None:
            return self.nav.ground_idle(s)
        return TrajectorySetpoint(
            s.now_us, sp.position_ned_m, sp.velocity_ned_m_s, sp.acceleration_ned_m_s2, sp.yaw_rad, sp.yawspeed_rad_s
        )


@dataclass
class Navigator:
    """Owns the modes, the carrot and the mission; the commander activates modes by name."""

    params: ParamStore
    origin: GeodeticOrigin
    mission: Mission = field(default_factory=Mission)
    dt_s: float = 0.02

    def __post_init__(self):
        self.home_ned = np.zeros(3)
        self.carrot = Carrot()
        self.events: list[NavEvent] = []
        self.pending_hold = None  # (target_ned, yaw_rad, speed) applied when Hold activates
        self.offboard_setpoint: TrajectorySetpoint | None = None
        self.modes = {
            "HOLD": Hold(self),
            "TAKEOFF": Takeoff(self),
            "LAND": Land(self),
            "RTL": ReturnToLaunch(self),
            "MISSION": MissionMode(self),
            "OFFBOARD": Offboard(self),
        }
        self.active_name = "HOLD"
        self._needs_activation = True
        self.cruise_speed: float | None = None  # DO_CHANGE_SPEED outside missions
        self._limits_cache = None
        self._held = None  # (key, setpoint) of the last follow()
        self.params.on_change(self._params_changed)

    def _params_changed(self, _name, _value) -> None:
        self._limits_cache = None

    # ---- used by the commander
    def activate(self, name: str) -> None:
        self.active_name = name
        self._needs_activation = True
        self._held = None

    def update(self, s: NavState) -> TrajectorySetpoint | None:
        mode = self.modes[self.active_name]
        if self._needs_activation:
            self._needs_activation = False
            mode.on_activation(s)
        return mode.on_active(s)

    def reposition(self, target_ned, yaw_rad: float = math.nan, speed_m_s: float | None = None) -> None:
        """Move Hold's point now if Hold runs, else when it next activates."""
        if self.active_name == "HOLD" and not self._needs_activation:
            self.modes["HOLD"].reposition(target_ned, yaw_rad, speed_m_s)
        else:
            self.pending_hold = (np.asarray(target_ned, dtype=float), yaw_rad, speed_m_s)

    def drain_events(self) -> list[NavEvent]:
        ev, self.events = self.events, []
        return ev

    # ---- shared by the modes
    def emit(self, kind: str, value=None) -> None:
        self.events.append(NavEvent(kind, value))

    def current_yaw(self, s: NavState) -> float:
        return float(s.local.heading_rad)

    def braking_point(self, s: NavState) -> np.ndarray:
        """Where the vehicle stops when braking at the horizontal acceleration limit."""
        p = np.array(s.local.position_ned_m, dtype=float)
        v = np.array(s.local.velocity_ned_m_s, dtype=float)
        a = param(self.params, "MPC_ACC_HOR")
        p[:2] += v[:2] * np.hypot(v[0], v[1]) / (2.0 * a)
        return p

    def carrot_from_estimate(self, s: NavState) -> None:
        self.carrot.reset(s.local.position_ned_m, s.local.velocity_ned_m_s)

    def reached(self, s: NavState, target_ned) -> bool:
        p = s.local.position_ned_m
        return (
            float(np.hypot(p[0] - target_ned[0], p[1] - target_ned[1])) <= self.params["NAV_ACC_RAD"]
            and abs(p[2] - target_ned[2]) <= self.params["NAV_MC_ALT_RAD"]
            and self.carrot.arrived(target_ned)
        )

    def _limits(self) -> tuple:
        """(cruise, up, down, acc_xy, acc_z), re-read only after a parameter change."""
        if self._limits_cache is None:
            p = self.params
            self._limits_cache = (
                param(p, "MPC_XY_CRUISE"),
                param(p, "MPC_Z_V_AUTO_UP"),
                param(p, "MPC_Z_V_AUTO_DN"),
                param(p, "MPC_ACC_HOR"),
                min(param(p, "MPC_ACC_UP_MAX"), param(p, "MPC_ACC_DOWN_MAX")),
            )
        return self._limits_cache

    def follow(self, s: NavState, target_ned, yaw_rad: float, speed_m_s: float | None) -> TrajectorySetpoint:
        cruise, up, down, acc_xy, acc_z = self._limits()
        self.carrot.step(target_ned, self.dt_s, speed_m_s or self.cruise_speed or cruise, up, down, acc_xy, acc_z)
        key = (tuple(self.carrot._p), tuple(self.carrot._v), yaw_rad)
        if self._held is not None and self._held[0] == key:
            return self._held[1]  # at rest on the target: the same setpoint object, nothing to resend
        sp = TrajectorySetpoint(s.now_us, self.carrot.pos, self.carrot.vel, _NAN3, yaw_rad)
        self._held = (key, sp)
        return sp

    def descend(self, s: NavState, xy, yaw_rad: float) -> TrajectorySetpoint:
        """x/y held, z velocity-controlled: MPC_Z_V_AUTO_DN above MPC_LAND_ALT1, MPC_LAND_SPEED below
        MPC_LAND_ALT2 and linearly between the two in between (PX4's gradual landing speed)."""
        alt = self.home_ned[2] - s.local.position_ned_m[2]
        slow, fast = param(self.params, "MPC_LAND_SPEED"), param(self.params, "MPC_Z_V_AUTO_DN")
        alt1, alt2 = param(self.params, "MPC_LAND_ALT1"), param(self.params, "MPC_LAND_ALT2")
        if alt >= alt1:
            vz = fast
        elif alt <= alt2 or alt1 <= alt2:
            vz = slow
        else:
            vz = slow + (fast - slow) * (alt - alt2) / (alt1 - alt2)
        self.carrot.reset([xy[0], xy[1], s.local.position_ned_m[2]])
        return TrajectorySetpoint(
            s.now_us,
            np.array([xy[0], xy[1], math.nan]),
            np.array([0.0, 0.0, vz]),
            yaw_rad=yaw_rad,
        )

    def ground_idle(self, s: NavState) -> TrajectorySetpoint:
        """On the ground and armed: push gently down so that thrust stays low (PX4's spool-up idle)."""
        p = s.local.position_ned_m
        self.carrot.reset(p)
        return TrajectorySetpoint(
            s.now_us,
            np.array([math.nan, math.nan, math.nan]),
            np.array([0.0, 0.0, param(self.params, "MPC_LAND_SPEED")]),
            yaw_rad=self.current_yaw(s),
        )

"""Commander: arming checks, the mode state machine and the failsafes (PX4's commander).

It receives VehicleCommands (MAV_CMD numbers, already translated from MAVLink by the endpoint),
answers each with a MAV_RESULT, picks the navigator mode, and every autopilot tick checks the
failsafes (datalink loss, offboard setpoint loss, geofence breach, battery) before handing the
navigator's setpoint to the vehicle.

Link timeouts (datalink loss, offboard setpoint loss) must elapse both in simulation time and in
wall-clock time: the client lives on the wall clock, so at --speed max a 1 Hz ground-station
heartbeat arrives every ~50 simulated seconds and must not look like a lost link; in real time or
slower than real time, simulation time decides as in PX4 lockstep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from ..errors import UavsearchError
from ..geometry import GeodeticOrigin, enu_to_ned, ned_to_enu, wrap_pi
from .messages import TrajectorySetpoint
from .mission import MISSION_DENIED, MISSION_INVALID, Mission, MissionItemError, MissionItem, check_item
from .navigator import NAV_PARAMS, NavState, Navigator
from .params import ParamDef, ParamStore


class Result(IntEnum):
    """MAV_RESULT numbers."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


# MAV_CMD numbers handled here.
CMD_NAV_LOITER_UNLIM = 17
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_DO_CHANGE_SPEED = 178
CMD_DO_SET_HOME = 179
CMD_DO_REPOSITION = 192
CMD_DO_LAND_START = 189
CMD_DO_PAUSE_CONTINUE = 193
CMD_DO_SET_MISSION_CURRENT = 224
CMD_MISSION_START = 300
CMD_COMPONENT_ARM_DISARM = 400
FORCE_MAGIC = 21196

# PX4 custom modes: name -> (main, sub); custom_mode = sub << 24 | main << 16.
PX4_MODES = {
    "POSCTL": (3, 0),
    "TAKEOFF": (4, 2),
    "HOLD": (4, 3),
    "MISSION": (4, 4),
    "RTL": (4, 5),
    "LAND": (4, 6),
    "OFFBOARD": (6, 0),
}
PX4_AUTO = 4

MAX_RANGE_M = 10_000.0  # targets farther from the origin, or higher above home, are nonsense
MAX_REL_ALT_M = 1_000.0
FAILSAFE_HZ = 10.0  # failsafe checks run at PX4 commander's rate, the navigator at the autopilot rate

# MAV_LANDED_STATE numbers.
LANDED_ON_GROUND = 1
LANDED_IN_AIR = 2
LANDED_TAKEOFF = 3
LANDED_LANDING = 4

# MAV_SEVERITY numbers for status texts.
SEV_CRITICAL = 2
SEV_WARNING = 4
SEV_INFO = 6

COMMANDER_PARAMS = [
    ParamDef("MAV_SYS_ID", 1, 1, 250, type="int", description="MAVLink system id (read at start)"),
    ParamDef("COM_DISARM_LAND", 2.0, -1.0, 20.0, "s", description="auto-disarm this long after touchdown"),
    ParamDef("COM_DISARM_PRFLT", 10.0, -1.0, 60.0, "s", description="auto-disarm if armed without takeoff"),
    ParamDef("COM_DL_LOSS_T", 10.0, 1.0, 300.0, "s", description="datalink loss time-out"),
    ParamDef("NAV_DLL_ACT", 0, 0, 3, type="int", description="datalink loss: 0 off, 1 hold, 2 return, 3 land"),
    ParamDef("COM_OF_LOSS_T", 1.0, 0.0, 60.0, "s", description="offboard setpoint loss time-out"),
    ParamDef("COM_OBL_RC_ACT", 5, 0, 5, type="int", description="offboard loss: 3 return, 4 land, else hold"),
    ParamDef("GF_ACTION", 2, 0, 5, type="int", description="geofence: 0 none, 1 warn, 2 hold, 3 return, 4 terminate, 5 land"),
    ParamDef("GF_MAX_HOR_DIST", 300.0, 0.0, 10000.0, "m", description="max horizontal distance from home (0: off)"),
    ParamDef("GF_MAX_VER_DIST", 120.0, 0.0, 10000.0, "m", description="max altitude above home (0: off)"),
    ParamDef("COM_LOW_BAT_ACT", 3, 0, 3, type="int", description="0 warn, 1 return, 2 land, 3 return then land"),
    ParamDef("BAT_LOW_THR", 0.15, 0.12, 0.5, description="low battery: warning, no arming"),
    ParamDef("BAT_CRIT_THR", 0.07, 0.05, 0.5, description="critical battery: return"),
    ParamDef("BAT_EMERGEN_THR", 0.05, 0.03, 0.5, description="emergency battery: land"),
]


def autopilot_params(*tables) -> list[ParamDef]:
    """The autopilot's parameter tables, minus names already declared by `tables` (flight core)."""
    taken = {d.name for t in tables for d in t}
    return [d for d in NAV_PARAMS + COMMANDER_PARAMS if d.name not in taken]


@dataclass(frozen=True)
class VehicleCommand:
    """A MAV_CMD with its seven parameters; positions in degrees and metres (not degE7)."""

    command: int
    param1: float = math.nan
    param2: float = math.nan
    param3: float = math.nan
    param4: float = math.nan
    param5: float = math.nan
    param6: float = math.nan
    param7: float = math.nan
    frame: int = 0  # MAV_FRAME of param5-7 (COMMAND_INT); 0 = GLOBAL (AMSL)
    source_system: int = 0
    source_component: int = 0


@dataclass
class StatusText:
    severity: int
    text: str


class Commander:
    """Owns arming state, the current mode and the failsafes; drives the navigator and the vehicle."""

    def __init__(self, params: ParamStore, vehicle, origin: GeodeticOrigin, autopilot_hz: float = 50.0):
        self.params = params
        self.vehicle = vehicle
        self.origin = origin
        self.dt_s = 1.0 / autopilot_hz
        self.mission = Mission()
        self.navigator = Navigator(params, origin, self.mission, dt_s=self.dt_s)
        self.mode = "HOLD"
        self.home_ned = np.zeros(3)
        self.home_set = False
        self.texts: list[StatusText] = []
        self.mission_events: list[tuple[str, int]] = []  # ("current"|"reached", seq)
        self.captures: list[MissionItem] = []  # IMAGE_START_CAPTURE items the mission asked for
        self.state_changed = True  # tells the endpoint to send a heartbeat at once
        self.now_us = 0
        self.wall_s = 0.0
        self._armed_at = (0, 0.0)
        self._took_off = False
        self._landed_since_us: int | None = None
        self._gcs_seen: tuple[int, float] | None = None  # (sim us, wall s) of the last GCS heartbeat
        self._dl_lost = False
        self._offboard_sp_at: tuple[int, float] | None = None
        self._fence_breached = False
        self._battery_stage = 0
        self._last_sp: TrajectorySetpoint | None = None
        self.local_position = None  # the estimate read at the last tick
        self._tick = 0
        self._failsafe_div = max(1, int(round(autopilot_hz / FAILSAFE_HZ)))
        self.separation = None  # callable(target_ned) -> why a goto is too close to another vehicle, or None

    # ------------------------------------------------------------------ state for telemetry
    @property
    def armed(self) -> bool:
        return bool(self.vehicle.armed)

    @property
    def custom_mode(self) -> int:
        main, sub = PX4_MODES[self.mode]
        return (sub << 24) | (main << 16)

    @property
    def landed_state(self) -> int:
        if not self.armed or self.vehicle.land_detected.landed:
            if self.armed and self.mode == "TAKEOFF":
                return LANDED_TAKEOFF
            return LANDED_ON_GROUND
        if self.mode == "TAKEOFF":
            return LANDED_TAKEOFF
        if self.mode == "LAND" or (self.mode == "RTL" and self.navigator.modes["RTL"].phase == "land"):
            return LANDED_LANDING
        return LANDED_IN_AIR

    @property
    def home_alt_amsl_m(self) -> float:
        """Relative altitudes (GLOBAL_POSITION_INT, camera captures) are above this home, as in PX4."""
        return float(self.origin.alt_m - self.home_ned[2])

    def home_lla(self) -> np.ndarray:
        return self.origin.enu_to_geodetic(ned_to_enu(self.home_ned))

    def text(self, severity: int, text: str) -> None:
        self.texts.append(StatusText(severity, text[:50]))

    def _set_mode(self, mode: str, reason: str | None = None) -> None:
        if mode != self.mode or mode in ("TAKEOFF", "RTL", "LAND", "MISSION"):
            self.navigator.activate(mode)
        self.mode = mode
        self.state_changed = True
        if reason:
            self.text(SEV_WARNING, reason)

    # ------------------------------------------------------------------ checks
    def arming_failures(self) -> list[str]:
        """Every failed pre-arm check, one short reason each (empty = may arm)."""
        v = self.vehicle
        fails = []
        h = v.sensor_health
        for name in ("gyro", "accel", "mag", "baro", "gps"):
            if not getattr(h, name):
                fails.append(f"{name} unhealthy")
        lp = v.local_position
        if not (lp.xy_valid and lp.z_valid):
            fails.append("position estimate invalid")
        if not v.land_detected.landed:
            fails.append("not landed")
        if v.battery.remaining < self.params["BAT_LOW_THR"]:
            fails.append("battery low")
        if not self.inside_fence(lp.position_ned_m):
            fails.append("outside geofence")
        if self.mode in ("RTL", "LAND"):
            fails.append(f"cannot arm in {self.mode}")
        if self.mode == "OFFBOARD" and not self._offboard_fresh():
            fails.append("no offboard setpoint")
        return fails

    def plausible(self, p_ned) -> bool:
        """A finite target within MAX_RANGE_M of the origin and -100 .. MAX_REL_ALT_M m about home."""
        n, e, d = (float(x) for x in p_ned)
        if not all(math.isfinite(x) for x in (n, e, d)):
            return False
        rel = float(self.home_ned[2]) - d
        return math.hypot(n, e) <= MAX_RANGE_M and -100.0 <= rel <= MAX_REL_ALT_M

    def inside_fence(self, p_ned) -> bool:
        hor, ver = self.params["GF_MAX_HOR_DIST"], self.params["GF_MAX_VER_DIST"]
        h = self.home_ned
        d = math.hypot(float(p_ned[0]) - float(h[0]), float(p_ned[1]) - float(h[1]))
        alt = float(h[2]) - float(p_ned[2])
        return not ((hor > 0 and d > hor) or (ver > 0 and alt > ver))

    def _elapsed_link_s(self, stamp: tuple[int, float] | None) -> float:
        if stamp is None:
            return math.inf
        return min((self.now_us - stamp[0]) * 1e-6, self.wall_s - stamp[1])

    def _offboard_fresh(self) -> bool:
        return self._elapsed_link_s(self._offboard_sp_at) <= self.params["COM_OF_LOSS_T"]

    # ------------------------------------------------------------------ inputs from the endpoint
    def on_gcs_heartbeat(self) -> None:
        if self._dl_lost:
            self._dl_lost = False
            self.text(SEV_INFO, "Data link regained")
        self._gcs_seen = (self.now_us, self.wall_s)

    def set_offboard_setpoint(self, sp: TrajectorySetpoint) -> None:
        self.navigator.offboard_setpoint = sp
        self._offboard_sp_at = (self.now_us, self.wall_s)

    def upload_mission(self, items: list[MissionItem]) -> tuple[int, str | None]:
        """Check and store a complete mission; returns (MAV_MISSION_RESULT, reason)."""
        try:
            for it in items:
                check_item(it)
        except MissionItemError as e:
            return e.mission_result, str(e)
        probe = Mission()
        probe.replace(items)
        for p in probe.positions_ned(self.origin, self.home_ned):
            if not self.plausible(p):
                return MISSION_INVALID, "mission position out of range"
            if not self.inside_fence(p):
                self.text(SEV_CRITICAL, "Mission rejected: outside geofence")
                return MISSION_DENIED, "mission outside geofence"
        self.mission.replace(items)
        if self.mode == "MISSION":
            self.navigator.activate("MISSION")
        self.mission_events.append(("current", 0))
        return 0, None

    def clear_mission(self) -> None:
        self.mission.clear()
        if self.mode == "MISSION":
            self._set_mode("HOLD")

    def set_mission_current(self, seq: int) -> bool:
        if not self.mission.set_current(seq):
            return False
        if self.mode == "MISSION":
            self.navigator.activate("MISSION")
        self.mission_events.append(("current", seq))
        return True

    # ------------------------------------------------------------------ commands
    def handle_command(self, cmd: VehicleCommand) -> Result:
        handler = {
            CMD_COMPONENT_ARM_DISARM: self._cmd_arm,
            CMD_NAV_TAKEOFF: self._cmd_takeoff,
            CMD_NAV_LAND: self._cmd_land,
            CMD_NAV_RETURN_TO_LAUNCH: self._cmd_rtl,
            CMD_DO_SET_MODE: self._cmd_set_mode,
            CMD_DO_REPOSITION: self._cmd_reposition,
            CMD_NAV_LOITER_UNLIM: self._cmd_hold,
            CMD_DO_CHANGE_SPEED: self._cmd_change_speed,
            CMD_MISSION_START: self._cmd_mission_start,
            CMD_DO_SET_MISSION_CURRENT: self._cmd_mission_current,
            CMD_DO_PAUSE_CONTINUE: self._cmd_pause_continue,
            CMD_DO_SET_HOME: self._cmd_set_home,
            CMD_DO_LAND_START: self._cmd_land_start,
        }.get(cmd.command)
        if handler is None:
            return Result.UNSUPPORTED
        return handler(cmd)

    def arm(self) -> Result:
        fails = self.arming_failures()
        if fails:
            self.text(SEV_CRITICAL, "Arming denied: " + ", ".join(fails))
            return Result.DENIED
        self.vehicle.arm()
        self._last_sp = None
        self.home_ned = np.array(self.vehicle.local_position.position_ned_m, dtype=float)
        self.home_set = True
        self.navigator.home_ned = self.home_ned.copy()
        self._armed_at = (self.now_us, self.wall_s)
        self._took_off = False
        self._landed_since_us = None
        self._fence_breached = False
        self._battery_stage = 0
        self.navigator.activate(self.mode)
        self.state_changed = True
        self.text(SEV_INFO, "Armed")
        return Result.ACCEPTED

    def disarm(self, reason: str = "Disarmed") -> None:
        self.vehicle.disarm()
        self._last_sp = None
        if self.mode in ("LAND", "RTL", "TAKEOFF"):
            self.mode = "HOLD"
        self.navigator.activate(self.mode)
        self.state_changed = True
        self.text(SEV_INFO, reason)

    def _cmd_arm(self, cmd: VehicleCommand) -> Result:
        force = cmd.param2 == FORCE_MAGIC
        if cmd.param1 == 1.0:
            if self.armed:
                return Result.ACCEPTED
            return self.arm()
        if cmd.param1 == 0.0:
            if not self.armed:
                return Result.ACCEPTED
            if not self.vehicle.land_detected.landed and not force:
                self.text(SEV_CRITICAL, "Disarming denied: not landed")
                return Result.DENIED
            self.disarm()
            return Result.ACCEPTED
        return Result.DENIED

    def _cmd_takeoff(self, cmd: VehicleCommand) -> Result:
        if not self.armed:
            self.text(SEV_CRITICAL, "Takeoff denied: disarmed")
            return Result.DENIED
        alt = cmd.param7
        home_alt = self.origin.alt_m - self.home_ned[2]
        in_air = not self.vehicle.land_detected.landed
        if math.isinf(alt) or (math.isfinite(alt) and not -MAX_REL_ALT_M <= alt - home_alt <= MAX_REL_ALT_M):
            self.text(SEV_CRITICAL, "Takeoff denied: altitude out of range")
            return Result.DENIED
        if math.isnan(alt) and in_air:  # no altitude given and already flying: nothing to climb to
            self.text(SEV_CRITICAL, "Takeoff denied: already flying (give an altitude)")
            return Result.DENIED
        tgt_rel = max(alt - home_alt if math.isfinite(alt) else 0.0, self.params["MIS_TAKEOFF_ALT"])
        ver = self.params["GF_MAX_VER_DIST"]
        if ver > 0 and tgt_rel > ver:
            self.text(SEV_CRITICAL, "Takeoff denied: above geofence")
            return Result.DENIED
        if tgt_rel > MAX_REL_ALT_M:
            self.text(SEV_CRITICAL, "Takeoff denied: altitude out of range")
            return Result.DENIED
        self.navigator.modes["TAKEOFF"].requested_alt_amsl = alt
        self._set_mode("TAKEOFF")
        return Result.ACCEPTED

    def _cmd_land(self, cmd: VehicleCommand) -> Result:
        if not self.armed:
            return Result.ACCEPTED if self.vehicle.land_detected.landed else Result.DENIED
        self._set_mode("LAND")
        return Result.ACCEPTED

    def _cmd_land_start(self, cmd: VehicleCommand) -> Result:
        """DO_LAND_START (MAVProxy's `land`): fly the mission's landing sequence, as PX4 does. Without one PX4
        only warns; a ground station that says `land` means land, so this vehicle lands where it is."""
        seq = self.mission.land_start_index()
        if seq is not None and self.armed:
            self.mission.set_current(seq)
            return self.request_mode("MISSION")
        if self.armed and not self.vehicle.land_detected.landed:
            self.text(SEV_INFO, "No mission landing sequence: landing here")
        return self._cmd_land(cmd)

    def _cmd_rtl(self, cmd: VehicleCommand) -> Result:
        if not self.armed or self.vehicle.land_detected.landed:
            self.text(SEV_CRITICAL, "Return denied: not flying")
            return Result.DENIED
        self._set_mode("RTL")
        return Result.ACCEPTED

    def _cmd_hold(self, cmd: VehicleCommand) -> Result:
        self._set_mode("HOLD")
        return Result.ACCEPTED

    def _cmd_set_mode(self, cmd: VehicleCommand) -> Result:
        if not int(cmd.param1) & 1:  # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            return Result.UNSUPPORTED
        main, sub = int(cmd.param2), int(cmd.param3) if math.isfinite(cmd.param3) else 0
        name = next((n for n, ms in PX4_MODES.items() if ms == (main, sub)), None)
        if name is None and main == PX4_AUTO and sub == 0:
            name = "HOLD"
        if name is None or name == "POSCTL":
            self.text(SEV_CRITICAL, f"Mode {main}/{sub} not available (no RC)")
            return Result.DENIED
        return self.request_mode(name)

    def request_mode(self, name: str) -> Result:
        """Mode switch with PX4's preconditions; DENIED when the mode cannot run now."""
        if name == "MISSION":
            if not self.mission.items:
                self.text(SEV_CRITICAL, "Mission denied: no mission")
                return Result.DENIED
            for p in self.mission.positions_ned(self.origin, self.home_ned):
                if not self.inside_fence(p):
                    self.text(SEV_CRITICAL, "Mission denied: outside geofence")
                    return Result.DENIED
        if name == "OFFBOARD" and not self._offboard_fresh():
            self.text(SEV_CRITICAL, "Offboard denied: no setpoint")
            return Result.DENIED
        if name == "TAKEOFF" and not self.armed:
            return Result.DENIED
        if name == "RTL" and (not self.armed or self.vehicle.land_detected.landed):
            self.text(SEV_CRITICAL, "Return denied: not flying")
            return Result.DENIED
        if name == "LAND" and not self.armed and not self.vehicle.land_detected.landed:
            return Result.DENIED
        if name == "TAKEOFF":
            self.navigator.modes["TAKEOFF"].requested_alt_amsl = math.nan
        if name == self.mode and name in ("MISSION", "TAKEOFF"):
            return Result.ACCEPTED  # PX4 does not restart a running mode on a repeated request
        self._set_mode(name)
        return Result.ACCEPTED

    def _cmd_reposition(self, cmd: VehicleCommand) -> Result:
        if not self.armed or self.vehicle.land_detected.landed:
            self.text(SEV_CRITICAL, "Reposition denied: not flying")
            return Result.DENIED
        lat, lon, alt = cmd.param5, cmd.param6, cmd.param7
        p = self.vehicle.local_position.position_ned_m
        if math.isfinite(lat) and math.isfinite(lon):
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                return Result.DENIED
            if not math.isfinite(alt):
                alt_amsl = self.origin.alt_m - p[2]
            elif cmd.frame in (3, 6):  # relative to home
                alt_amsl = self.origin.alt_m - self.home_ned[2] + alt
            else:
                alt_amsl = alt
            tgt = enu_to_ned(self.origin.geodetic_to_enu([lat, lon, alt_amsl]))
        elif math.isfinite(alt):
            tgt = np.array([p[0], p[1], p[2]], dtype=float)
            tgt[2] = self.origin.alt_m - alt if cmd.frame not in (3, 6) else self.home_ned[2] - alt
        else:
            return Result.DENIED
        if not self.plausible(tgt):
            self.text(SEV_CRITICAL, "Reposition denied: target out of range")
            return Result.DENIED
        if not self.inside_fence(tgt):
            self.text(SEV_CRITICAL, "Reposition denied: outside geofence")
            return Result.DENIED
        crowded = None if self.separation is None else self.separation(tgt)
        if crowded is not None:
            self.text(SEV_CRITICAL, f"Reposition denied: {crowded}")
            return Result.DENIED
        speed = cmd.param1 if math.isfinite(cmd.param1) and cmd.param1 > 0 else None
        yaw = float(wrap_pi(cmd.param4)) if math.isfinite(cmd.param4) else math.nan
        if self.mode != "HOLD":
            self._set_mode("HOLD")
        self.navigator.reposition(tgt, yaw, speed)
        return Result.ACCEPTED

    def _cmd_change_speed(self, cmd: VehicleCommand) -> Result:
        if not (math.isfinite(cmd.param2) and cmd.param2 > 0):
            return Result.DENIED
        self.navigator.cruise_speed = float(cmd.param2)
        hold = self.navigator.modes["HOLD"]
        if self.mode == "HOLD" and getattr(hold, "speed", None) is not None:
            hold.speed = float(cmd.param2)
        return Result.ACCEPTED

    def _cmd_mission_start(self, cmd: VehicleCommand) -> Result:
        if math.isfinite(cmd.param1) and int(cmd.param1) > 0 and not self.mission.set_current(int(cmd.param1)):
            return Result.DENIED
        return self.request_mode("MISSION")

    def _cmd_mission_current(self, cmd: VehicleCommand) -> Result:
        return Result.ACCEPTED if self.set_mission_current(int(cmd.param1)) else Result.DENIED

    def _cmd_pause_continue(self, cmd: VehicleCommand) -> Result:
        return self.request_mode("MISSION" if cmd.param1 == 1.0 else "HOLD")

    def _cmd_set_home(self, cmd: VehicleCommand) -> Result:
        if cmd.param1 == 1.0:
            home = np.array(self.vehicle.local_position.position_ned_m, dtype=float)
        elif all(math.isfinite(x) for x in (cmd.param5, cmd.param6, cmd.param7)) and abs(cmd.param5) <= 90 and abs(cmd.param6) <= 180:
            home = enu_to_ned(self.origin.geodetic_to_enu([cmd.param5, cmd.param6, cmd.param7]))
        else:
            return Result.DENIED
        n, e, d = (float(x) for x in home)
        if not (math.hypot(n, e) <= MAX_RANGE_M and abs(d) <= MAX_REL_ALT_M):
            self.text(SEV_CRITICAL, "Set home denied: out of range")
            return Result.DENIED
        self.home_ned = home
        self.navigator.home_ned = self.home_ned.copy()
        self.home_set = True
        return Result.ACCEPTED

    # ------------------------------------------------------------------ the autopilot tick
    def update(self, wall_s: float) -> None:
        """One autopilot tick at the vehicle's current simulation time."""
        v = self.vehicle
        self.now_us = int(v.time_us)
        self.wall_s = wall_s
        lp = self.local_position = v.local_position  # shared with the endpoint for this instant
        ld = v.land_detected
        self._tick += 1
        if not self.home_set and self._estimate_settled(lp):
            self.home_ned = np.array(lp.position_ned_m, dtype=float)
            self.navigator.home_ned = self.home_ned.copy()
            self.home_set = True
        if self.armed:
            self._check_landing(ld)
        if self.armed and self._tick % self._failsafe_div == 0:
            self._check_failsafes(lp, ld)
        s = NavState(self.now_us, lp, ld)
        sp = self.navigator.update(s)
        self._handle_nav_events()
        if self.armed and sp is not None and sp is not self._last_sp:
            if math.isnan(sp.yaw_rad) and math.isnan(sp.yawspeed_rad_s):
                sp = TrajectorySetpoint(
                    sp.timestamp_us, sp.position_ned_m, sp.velocity_ned_m_s, sp.acceleration_ned_m_s2, lp.heading_rad
                )
            try:
                v.set_setpoint(sp)
            except UavsearchError as e:  # a setpoint the vehicle refuses: keep flying the previous one
                self.text(SEV_CRITICAL, f"setpoint refused: {e}")
                return
            self._last_sp = sp

    def _estimate_settled(self, lp) -> bool:
        """Home is taken once the estimator has converged (its first fix is about a metre off)."""
        return bool(lp.xy_valid and lp.z_valid and lp.eph_m < 1.5 and lp.epv_m < 0.5 and self.now_us >= 1_000_000)

    def _check_landing(self, ld) -> None:
        if not ld.landed:
            self._took_off = True
            self._landed_since_us = None
            return
        if self._landed_since_us is None:
            self._landed_since_us = self.now_us
        landed_s = (self.now_us - self._landed_since_us) * 1e-6
        if self._took_off:
            t = self.params["COM_DISARM_LAND"]
            if t >= 0 and landed_s >= t and self.mode not in ("TAKEOFF",):
                self.disarm("Landed: disarmed")
        else:
            # Waiting for a person or a client to take off: a link-style time-out (both clocks), so that
            # at --speed max an operator still has COM_DISARM_PRFLT wall seconds.
            t = self.params["COM_DISARM_PRFLT"]
            if t >= 0 and self._elapsed_link_s(self._armed_at) >= t and self.mode not in ("TAKEOFF", "MISSION", "OFFBOARD"):
                self.disarm("Disarmed: no takeoff")

    def _failsafe(self, action: str | None, reason: str) -> None:
        if action == "TERMINATE":
            self.text(SEV_CRITICAL, reason + ": terminate")
            self.disarm("Flight terminated")
        elif action and action != self.mode:
            self._set_mode(action, f"{reason}: {action}")
        elif action is None:
            self.text(SEV_WARNING, reason)

    def _check_failsafes(self, lp, ld) -> None:
        in_air = not ld.landed
        # Datalink loss: only once a ground station was seen, as in PX4.
        if self._gcs_seen is not None and not self._dl_lost:
            if self._elapsed_link_s(self._gcs_seen) > self.params["COM_DL_LOSS_T"]:
                self._dl_lost = True
                act = {1: "HOLD", 2: "RTL", 3: "LAND"}.get(int(self.params["NAV_DLL_ACT"]))
                if act and in_air and self.mode not in ("LAND",):
                    self._failsafe(act, "Data link lost")
                else:
                    self.text(SEV_WARNING, "Data link lost")
        # Position lost (no GPS): land where it is, as PX4 does without a position estimate.
        gps_ok = self.vehicle.sensor_health.gps and lp.xy_valid
        if not gps_ok and in_air and self.mode != "LAND":
            self._failsafe("LAND", "GPS lost")
        # Offboard setpoints stopped.
        if self.mode == "OFFBOARD" and not self._offboard_fresh():
            act = {3: "RTL", 4: "LAND"}.get(int(self.params["COM_OBL_RC_ACT"]), "HOLD")
            self._failsafe(act, "Offboard setpoints lost")
        # Geofence breach (edge-triggered; re-armed once back inside).
        inside = self.inside_fence(lp.position_ned_m)
        if not inside and not self._fence_breached and in_air:
            self._fence_breached = True
            act = {2: "HOLD", 3: "RTL", 4: "TERMINATE", 5: "LAND"}.get(int(self.params["GF_ACTION"]))
            if int(self.params["GF_ACTION"]) != 0:
                self._failsafe(act, "Geofence breached")
        elif inside:
            self._fence_breached = False
        # Battery.
        rem = self.vehicle.battery.remaining
        stage = 3 if rem < self.params["BAT_EMERGEN_THR"] else 2 if rem < self.params["BAT_CRIT_THR"] else (
            1 if rem < self.params["BAT_LOW_THR"] else 0
        )
        if stage > self._battery_stage:
            self._battery_stage = stage
            act_p = int(self.params["COM_LOW_BAT_ACT"])
            act = None
            if stage == 2 and act_p in (1, 3):
                act = "RTL"
            elif stage >= 2 and act_p == 2 or stage == 3 and act_p == 3:
                act = "LAND"
            if in_air and act and self.mode != "LAND":
                self._failsafe(act, ["", "Battery low", "Battery critical", "Battery emergency"][stage])
            else:
                self.text(SEV_WARNING, ["", "Battery low", "Battery critical", "Battery emergency"][stage])

    def _handle_nav_events(self) -> None:
        for ev in self.navigator.drain_events():
            if ev.kind == "done" and self.mode == "TAKEOFF":
                self._set_mode("HOLD")
                self.navigator.reposition(ev.value)
            elif ev.kind == "rtl" and self.mode == "MISSION":
                self._set_mode("RTL")
            elif ev.kind == "item_reached":
                self.mission_events.append(("reached", int(ev.value)))
            elif ev.kind in ("mission_current", "mission_finished"):
                self.mission_events.append(("current", int(ev.value)))
            elif ev.kind == "capture":
                self.captures.append(ev.value)

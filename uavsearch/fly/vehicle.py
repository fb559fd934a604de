"""The second vehicle of "one search loop, two vehicles": a real MAVLink client that flies to each view.

`MavlinkVehicle` is a thin facade over the client (connection.py -> system.py -> one plugin per
capability) that does what a ground station would do on a real drone, using only what any MAVLink
client can see and send (no back door into the simulator). `capture(position_enu)`:

1. DO_REPOSITION (COMMAND_INT, GLOBAL_INT, AMSL) to the waypoint, heading north;
2. wait, on the vehicle's telemetry (GLOBAL_POSITION_INT, i.e. its ESTIMATE), until it is within
   `arrive_radius_m` of the waypoint and slower than `settle_speed_m_s` for `settle_time_s` of
   simulation time (telemetry's time_boot_ms), or fail the step after `step_timeout_s`;
3. IMAGE_START_CAPTURE to the camera (compid 100), wait for CAMERA_IMAGE_CAPTURED, load the PNG its
   file:// URL names, and build the View with the pose the camera REPORTED (lat/lon/alt + attitude
   quaternion), so the estimator's error becomes projection error as on a real drone.

The facade flies one System of its connection: `system_id`, or the first autopilot that heartbeats;
other vehicles on the same link never change what it sees. The scene frame's origin is the mission's
home (the centre of the search area), not wherever the vehicle was armed. Timeouts are in simulation
time (so they mean the same at --speed 1 and max) with a wall-clock backstop for a vehicle that stopped
talking. Every packet both ways goes to the tlog when one is given.

With `lockstep` (and a vehicle started with `uavsearch sitl --lockstep`) the client is the clock master
(lockstep.py); a vehicle without lockstep answers UNSUPPORTED and the client falls back to free-running.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..flight.mavlink import wire_units as wire
from ..geometry import GeodeticOrigin, camera_pose_from_vehicle
from ..search.config import SearchConfig
from ..search.views import View, make_view
from .camera import image_path
from .connection import MavlinkConnection
from .dialect import AUTOPILOT_COMPID, CAMERA_COMPID, M
from .errors import CommandError, FlightError, StepFailed, VehicleDown, VehicleLost
from .system import PROGRESS_EVERY_S, PROGRESS_FIRST_S
from .telemetry import HEALTH_BITS, MODE_HOLD, MODE_LAND, MODE_RTL, MODE_TAKEOFF, STREAM_RATES_HZ


# Faster than any reported motion can be: the autopilot's speed limits at the top of their ranges allow 20 m/s
# horizontally and 8 m/s up (MPC_XY_VEL_MAX, MPC_Z_VEL_MAX_UP), and the estimate follows the vehicle.
APPROACH_SPEED_BOUND_M_S = 30.0
TAKEOFF_ALT_TOL_M = 1.0  # a take-off has arrived within this of its altitude (and in HOLD)
BATTERY_CRITICAL_PCT = 7  # SYS_STATUS battery_remaining at or below this: the autopilot's BAT_CRIT_THR (7 %)
IN_AIR_M = 2.0  # above home by more than this when it disarmed: it fell


def ticks_until(system, tick_s: float, earliest_s: float | None) -> float:
    """A lockstep grant of whole ticks that ends no later than vehicle time `earliest_s`, before which the
    awaited condition cannot hold (at least one tick; one when `earliest_s` is None: it may hold any moment).
    No tick inside the grant could have seen the condition, so the wait ends at the same tick as with one
    tick per grant, and the flight is the same."""
    if earliest_s is None or not system.lockstep.enabled:
        return tick_s
    ticks = math.floor((earliest_s - system.lockstep.clock_ms / 1000.0) / tick_s + 1e-9)
    return tick_s * max(1, ticks)


def climb_grant(vehicles: list[MavlinkVehicle]) -> float:
    """The take-off's grant on the first vehicle's clock (in lockstep its grants run every vehicle): the ticks
    before the last of them could be up (all must be)."""
    lead = vehicles[0]
    bounds = [t for t in (v._at_takeoff_alt_earliest_s() for v in vehicles) if t is not None]
    return ticks_until(lead.system, lead.settings.lockstep_tick_s, max(bounds) if bounds else None)


@dataclass(frozen=True)
class FlightSettings:
    """How the client flies: arrival thresholds and time-outs (mission parameters)."""

    arrive_radius_m: float = 0.5
    settle_speed_m_s: float = 0.3
    settle_time_s: float = 0.5  # the thresholds must hold this long (simulation time)
    step_timeout_s: float = 60.0  # simulation time from goto to settled
    takeoff_timeout_s: float = 120.0
    connect_timeout_s: float = 30.0  # wall clock: heartbeat, health
    wall_timeout_s: float = 120.0  # wall-clock backstop for any single wait
    capture_timeout_s: float = 10.0  # wall clock for CAMERA_IMAGE_CAPTURED
    end_action: str = "land"  # land | rtl | none
    yaw_deg: float = 0.0  # heading at every view (paper: fixed north)
    lockstep: bool = False  # drive the vehicle's clock (when it supports MAV_CMD_SIM_ADVANCE)
    lockstep_tick_s: float = 0.1  # simulation time per grant: conditions are judged at this spacing
    land_tick_s: float = 1.0  # the same while landing: nothing but its end is judged, and grants cost wall time


@dataclass
class CaptureInfo:
    """What the last capture step did, for the flight log."""

    index: int
    waypoint_enu: list
    reported_position_enu: list
    reported_rpy_rad: list
    image_path: str
    camera_dir: str  # where the camera wrote the image (a simulated camera keeps captures.jsonl there)
    time_boot_s: float  # simulation time of the capture (vehicle clock)
    flight_time_s: float  # simulation time from the goto to settled
    wall_s: float


class _Settle:
    """Arrived and settled: every position report within the radius and below the speed for settle_s."""

    def __init__(self, target, radius_m: float, speed_m_s: float, settle_s: float):
        self.target, self.radius_m, self.speed_m_s, self.settle_s = target, radius_m, speed_m_s, settle_s
        self.since: float | None = None
        self.done_at: float | None = None
        self.t_min = -math.inf

    def reset_before(self, t_s: float) -> None:
        """Reports from before the vehicle accepted the goto do not count."""
        self.t_min = t_s
        if self.since is not None and self.since < t_s:
            self.since, self.done_at = None, None

    def update(self, p, v, t_s: float) -> None:
        if self.done_at is not None or p is None:
            return
        ok = np.linalg.norm(p - self.target) < self.radius_m and np.linalg.norm(v) < self.speed_m_s
        if not ok or t_s < self.t_min:
            self.since = None
            return
        if self.since is None:
            self.since = t_s
        if t_s - self.since >= self.settle_s:
            self.done_at = t_s


class MavlinkVehicle:
    """views.Vehicle over MAVLink: connect, arm, take off, fly to views, land (one System of one connection)."""

    def __init__(self, url: str, config: SearchConfig | None = None, origin: GeodeticOrigin | None = None,
                 settings: FlightSettings | None = None, tlog=None, source_system: int = 245,
                 source_component: int = 190, image_dir: Path | None = None, progress=None,
                 system_id: int | None = None, connection: MavlinkConnection | None = None):
        """`connection`: fly one System of a connection someone else owns (a team's vehicles share one; closing
        the vehicle leaves it open)."""
        self.config = config or SearchConfig()
        self.origin = origin or GeodeticOrigin()
        self.settings = settings or FlightSettings()
        self.url = url if connection is None else connection.url
        self.tlog = tlog
        self.image_dir = Path(image_dir) if image_dir else None
        self.progress = progress  # callable(str) for status lines, or None
        self.system_id = system_id  # None: the first autopilot that heartbeats
        self.owns_connection = connection is None
        self.connection = connection if connection is not None else \
            MavlinkConnection(url, source_system, source_component, tlog=tlog)
        self.system = None  # the System this vehicle flies, once its heartbeat came
        self.watchdog = None  # callable() raising VehicleLost when the vehicle process is known dead
        self.last_capture: CaptureInfo | None = None
        self.captures_done = 0
        self.in_air = False
        self.closed = False
        self.connected_sim_s: float | None = None  # vehicle clock when the link came up healthy
        self._settle: _Settle | None = None
        self._goto_t0 = 0.0
        self.down: str | None = None  # why it left the search (trouble()), once it has
        self.link_lost = False  # it stopped answering: no end action can reach it
        self.end_state: str | None = None  # what its end action did (the mission controller's landing)

    @property
    def conn(self) -> MavlinkConnection:
        return self.connection

    @property
    def link_text(self) -> str:
        """The URL with the port this client really listens on (`udpin:HOST:0` binds a free one)."""
        return self.connection.link_text

    def _say(self, text: str) -> None:
        if self.progress:
            self.progress(text)

    def _wait(self, cond, wall_timeout_s: float, what: str, **kw):
        return self.system.wait_until(cond, wall_timeout_s, what, say=self._say, **kw)

    def watch(self, check) -> None:
        """check() raises VehicleLost once the vehicle is known dead; every wait calls it."""
        self.watchdog = check
        if self.system is not None:
            self.system.watchdog = check

    # ------------------------------------------------------------------ state
    @property
    def sim_time_s(self) -> float | None:
        """The vehicle's clock (time since boot) from its last position report."""
        return None if self.system is None else self.system.telemetry.sim_time_s

    def position_enu(self) -> np.ndarray | None:
        """The vehicle's reported position in the scene frame (its estimate)."""
        return None if self.system is None else self.system.telemetry.position_enu(self.origin)

    def velocity_enu(self) -> np.ndarray | None:
        return None if self.system is None else self.system.telemetry.velocity_enu_m_s()

    def mode(self):
        """The autopilot's FlightMode (a (main, sub) tuple printed as PX4's name), None before its heartbeat."""
        return None if self.system is None else self.system.telemetry.mode()

    @property
    def armed(self) -> bool:
        return self.system is not None and self.system.telemetry.armed

    @property
    def photos_asked(self) -> int:
        return 0 if self.system is None else self.system.camera.photos_asked

    @property
    def photos_received(self) -> int:
        return 0 if self.system is None else self.system.camera.photos_received

    def _distance_to(self, target) -> float:
        p = self.position_enu()
        return math.nan if p is None else float(np.linalg.norm(p - target))

    def _where(self, elapsed_s: float) -> str:
        """'at E .. N .. U .. m  flew .. s', the per-step lines' style, for progress lines."""
        p = self.position_enu()
        at = "no position yet" if p is None else f"at E {p[0]:6.1f} N {p[1]:6.1f} U {p[2]:5.1f} m"
        return f"{at}  flew {elapsed_s:5.1f} s"

    def trouble(self) -> str | None:
        """Why this flying vehicle cannot go on with the search, from what it reports (None: it can): disarmed
        (in the air: it fell), a LAND / RTL mode the mission did not ask for (a failsafe: GPS lost, battery, an
        operator's command), or a critical battery."""
        if self.system is None or not self.in_air or self.system.telemetry.heartbeat is None:
            return None
        t = self.system.telemetry
        if not t.armed:
            p = self.position_enu()
            if p is not None and p[2] > IN_AIR_M:
                return f"crashed: disarmed in the air at U {p[2]:.1f} m"
            return "disarmed on the ground"
        mode = t.mode()
        if mode in (MODE_LAND, MODE_RTL):
            said = self.system.last_texts(1)
            return f"failsafe: {'LAND' if mode == MODE_LAND else 'RTL'} mode it was not asked for" + \
                (f" (the vehicle said: {said})" if said else "")
        battery = getattr(t.sys_status, "battery_remaining", -1)
        if 0 <= battery <= BATTERY_CRITICAL_PCT:
            return f"failsafe: battery critical ({battery} %)"
        return None

    def _at_alt(self, alt_amsl: float, tol_m: float = TAKEOFF_ALT_TOL_M) -> bool:
        return abs(self.system.telemetry.altitude_amsl_m() - alt_amsl) < tol_m

    def _on_position(self, m) -> None:
        if self._settle is not None:
            self._settle.update(self.position_enu(), self.velocity_enu(), wire.seconds(m.time_boot_ms))

    @property
    def target_system(self) -> int | None:
        """The system id this vehicle flies (None before its heartbeat)."""
        return None if self.system is None else self.system.sysid

    @property
    def lockstep(self) -> bool:
        """This client drives the vehicle's clock (the vehicle accepted a grant)."""
        return self.system is not None and self.system.lockstep.enabled

    def pump(self, timeout_s: float = 0.05) -> None:
        """Read the link for up to timeout_s."""
        (self.system or self.connection).pump(timeout_s)

    def command_long(self, command: int, *params: float, **kw) -> int:
        """COMMAND_LONG to the vehicle (system.commands.long); its MAV_RESULT."""
        return self._need_system().commands.long(command, *params, **kw)

    def command_int(self, command: int, *args, **kw) -> int:
        """COMMAND_INT to the vehicle (system.commands.int); its MAV_RESULT."""
        return self._need_system().commands.int(command, *args, **kw)

    # ------------------------------------------------------------------ queries
    def read_param(self, name: str) -> float | None:
        """A parameter's value (int32 parameters decoded bytewise, as PX4 sends them), None if the vehicle has none."""
        return self._need_system().params.get(name)

    def camera_information(self):
        """The camera's CAMERA_INFORMATION (REQUEST_MESSAGE to compid 100), or None."""
        return self._need_system().camera.information()

    def _need_system(self):
        if self.system is None:
            raise FlightError(f"not connected to a vehicle on {self.link_text} (connect() first)")
        return self.system

    # ------------------------------------------------------------------ the mission's life cycle
    def _wait_heartbeat(self):
        """The System to fly, once its autopilot heartbeats; FlightError after connect_timeout_s."""
        st, c = self.settings, self.connection
        wall0 = time.monotonic()
        next_note = wall0 + PROGRESS_FIRST_S
        who = "" if self.system_id is None else f" from system {self.system_id}"
        while True:
            if self.watchdog is not None:
                self.watchdog()
            s = c.wait_system(self.system_id, timeout_s=0.0)
            if s is not None:
                return s
            now = time.monotonic()
            if now >= next_note:
                next_note = now + PROGRESS_EVERY_S
                self._say(f"connecting  no heartbeat{who} yet on {self.link_text}  "
                          f"{now - wall0:.0f} s of {st.connect_timeout_s:.0f} s")
            if now > wall0 + st.connect_timeout_s:
                raise FlightError(f"no heartbeat{who} on {self.link_text}: no answer from the vehicle within "
                                  f"{st.connect_timeout_s:.0f} s (wall clock)")
            c.pump()

    def connect(self) -> None:
        """Wait for the autopilot's heartbeat and health (gyro, accel, mag, GPS) and a position."""
        st = self.settings
        self._say(f"connecting to {self.link_text} ...")
        self.system = s = self._wait_heartbeat()
        s.watchdog = self.watchdog
        s.telemetry.on_position(self._on_position)
        self.connection.send_heartbeat(force=True)
        if st.lockstep and not s.lockstep.start(st.lockstep_tick_s):
            self._say("the vehicle does not run in lockstep: this flight will not be reproducible from its seed")
        s.telemetry.set_rates()
        wall0 = time.monotonic()
        self._wait(s.telemetry.healthy, st.connect_timeout_s, "vehicle not healthy (SYS_STATUS sensors, position)",
                   status=lambda _: f"connecting  waiting for the vehicle's health ({s.telemetry.missing_health()})  "
                                    f"{time.monotonic() - wall0:.0f} s of {st.connect_timeout_s:.0f} s")
        self.connected_sim_s = self.sim_time_s

    def arm(self, timeout_s: float | None = None) -> None:
        """Arm, retrying while the estimator converges, until the heartbeat says armed."""
        st, s = self.settings, self.system
        timeout_s = st.connect_timeout_s if timeout_s is None else timeout_s
        end = time.monotonic() + timeout_s
        while True:
            r = s.commands.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            if r == M.MAV_RESULT_ACCEPTED:
                break
            if time.monotonic() > end:
                raise CommandError(f"arming refused ({s.last_texts(2) or f'MAV_RESULT {r}'})",
                                   M.MAV_CMD_COMPONENT_ARM_DISARM, r)
            s.advance(0.2)
        self._wait(lambda: self.armed, timeout_s, "arming")

    def take_off(self) -> None:
        """Arm (retrying while the estimator converges), take off to the mission altitude, go to the centre."""
        st = self.settings
        self.begin_take_off()
        self._wait(self.took_off, st.wall_timeout_s, "takeoff", sim_timeout_s=st.takeoff_timeout_s,
                   tick_s=lambda: climb_grant([self]),
                   status=lambda el: f"take-off  {self._where(el)}  (to {self.config.altitude_m:.0f} m)")

    def _takeoff_alt_amsl(self) -> float:
        return self.origin.alt_m + self.config.altitude_m

    def begin_take_off(self) -> None:
        """Arm and command the take-off to the mission altitude; `took_off()` says when it is there (a team
        takes off together: every vehicle begins, then one wait for all)."""
        st, s = self.settings, self.system
        alt_amsl = self._takeoff_alt_amsl()
        if not self.armed:  # fly arms its own vehicle while the models load (mission_controller.fly_search)
            self.arm()
        r = s.commands.long(M.MAV_CMD_NAV_TAKEOFF, math.nan, 0, 0, math.nan, math.nan, math.nan, alt_amsl)
        if r != M.MAV_RESULT_ACCEPTED:
            raise CommandError(f"takeoff refused ({s.last_texts(2) or f'MAV_RESULT {r}'})", M.MAV_CMD_NAV_TAKEOFF, r)
        self.in_air = True
        self._say(f"taking off to {self.config.altitude_m:.0f} m")
        self._wait(lambda: self.mode() == MODE_TAKEOFF or self._at_alt(alt_amsl), st.wall_timeout_s, "takeoff start")

    def took_off(self) -> bool:
        return self.mode() == MODE_HOLD and self._at_alt(self._takeoff_alt_amsl())

    def goto(self, position_enu) -> float:
        """DO_REPOSITION to the waypoint; returns the simulation time it took to arrive and settle."""
        try:
            self.begin_goto(position_enu)
            return self.wait_arrived()
        finally:
            self._settle = None

    def begin_goto(self, position_enu) -> None:
        """DO_REPOSITION to the waypoint, not waiting for the flight (`arrived()`, `wait_arrived()`): a team's
        vehicles fly at once."""
        st, s = self.settings, self.system
        target = np.asarray(position_enu, dtype=float)
        lat, lon, alt = self.origin.enu_to_geodetic(target)
        # Track every position report from before the command on, so no report is judged late or skipped.
        self._settle = _Settle(target, st.arrive_radius_m, st.settle_speed_m_s, st.settle_time_s)
        r = s.commands.int(M.MAV_CMD_DO_REPOSITION, M.MAV_FRAME_GLOBAL_INT, -1,
                           M.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.radians(st.yaw_deg),
                           wire.deg_to_e7(lat), wire.deg_to_e7(lon), float(alt))
        if r != M.MAV_RESULT_ACCEPTED:
            self._settle = None
            raise StepFailed(f"goto {np.round(target, 1).tolist()} refused "
                             f"({s.last_texts(1) or f'MAV_RESULT {r}'})")
        self._goto_t0 = getattr(s.commands.last_ack, "sim_s", None) or self.sim_time_s or 0.0
        self._settle.reset_before(self._goto_t0)

    @property
    def goal_enu(self) -> np.ndarray | None:
        """Where the last begin_goto sends it, until it has arrived there (wait_arrived)."""
        return None if self._settle is None else self._settle.target

    def arrived(self) -> bool:
        return self._settle is not None and self._settle.done_at is not None

    def _approach_tick(self) -> float:
        """The next lockstep grant while a goto flies: the ticks that end before the goto could have settled.

        From its last report the vehicle needs the distance beyond the radius at no more than
        APPROACH_SPEED_BOUND_M_S, then settle_s of reports, to settle: no tick before then can see it arrived,
        so granting them at once judges the arrival at the same tick, and flies the same flight, with fewer
        round trips (a wide mission, take-off included: 564 grants instead of 2,682)."""
        return ticks_until(self.system, self.settings.lockstep_tick_s, self._settled_earliest_s())

    def _settled_earliest_s(self) -> float | None:
        """The earliest vehicle time the goto could report itself settled (None: any moment now)."""
        s, p, t = self._settle, self.position_enu(), self.sim_time_s
        if s is None or p is None or t is None:
            return None
        gap_m = float(np.linalg.norm(p - s.target)) - s.radius_m
        if gap_m <= 0:  # inside: its settling may have begun with an earlier report
            return None
        return t + gap_m / APPROACH_SPEED_BOUND_M_S + s.settle_s

    def _at_takeoff_alt_earliest_s(self) -> float | None:
        """The earliest vehicle time its reports could put it at the take-off altitude (None: any moment now)."""
        t, alt = self.sim_time_s, self.system.telemetry.altitude_amsl_m()
        if t is None or not math.isfinite(alt):
            return None
        gap_m = abs(alt - self._takeoff_alt_amsl()) - TAKEOFF_ALT_TOL_M
        return None if gap_m <= 0 else t + gap_m / APPROACH_SPEED_BOUND_M_S

    def wait_arrived(self) -> float:
        """Until the goto of begin_goto has arrived and settled; the simulation seconds it took."""
        st, target = self.settings, self._settle.target
        self._wait(lambda: self.arrived() or self.trouble(), st.wall_timeout_s, f"goto {np.round(target, 1).tolist()}",
                   sim_timeout_s=st.step_timeout_s, tick_s=self._approach_tick,
                   status=lambda el: f"flying    {self._where(el)}  (to E {target[0]:.1f} N {target[1]:.1f}, "
                                     f"{self._distance_to(target):.1f} m to go)")
        if not self.arrived():
            self._settle = None
            raise self.leave(self.trouble())
        took = self._settle.done_at - self._goto_t0
        self._settle = None
        return took

    def take_picture(self):
        """IMAGE_START_CAPTURE -> CAMERA_IMAGE_CAPTURED; returns the message."""
        msg = self.system.camera.take_photo(self.captures_done + 1, self.settings.capture_timeout_s)
        self.captures_done += 1
        return msg

    @staticmethod
    def image_path(msg) -> Path:
        """The file CAMERA_IMAGE_CAPTURED's file:// URL names."""
        return image_path(msg)

    def view_from_capture(self, msg) -> tuple[View, Path, np.ndarray, tuple]:
        """The image named by CAMERA_IMAGE_CAPTURED and the View at the pose it reports."""
        import cv2

        path = self.image_path(msg)
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise StepFailed(f"cannot read the captured image {path}")
        if self.image_dir is not None and path.parent.resolve() != self.image_dir.resolve():
            self.image_dir.mkdir(parents=True, exist_ok=True)
            copy = self.image_dir / path.name
            if not cv2.imwrite(str(copy), bgr):
                raise StepFailed(f"cannot write the image copy {copy}")
            path = copy
        rgb = np.ascontiguousarray(bgr[..., ::-1])
        pos = wire.position_enu(msg, self.origin)
        rpy = wire.rpy_rad(msg.q)
        pose = camera_pose_from_vehicle(pos, *rpy, gimbal_stabilised=True)
        cfg = self.config
        view = make_view(rgb, pose, cfg.grid, cfg.intrinsics, None, cfg.min_cell_area_px)
        return view, path, pos, rpy

    def capture(self, position_enu) -> View:
        """Fly to `position_enu`, settle, take a picture: the View at the REPORTED pose."""
        wall0 = time.monotonic()
        if not self.in_air:
            self.connect()
            self.take_off()
        flight = self.goto(position_enu)
        return self.capture_here(position_enu, flight, wall0)

    def capture_here(self, position_enu, flight_s: float, wall0: float) -> View:
        """Take a picture where it stands (arrived at `position_enu` after `flight_s` of flight); the View."""
        msg = self.take_picture()
        view, path, pos, rpy = self.view_from_capture(msg)
        self.last_capture = CaptureInfo(
            index=int(msg.image_index), waypoint_enu=[float(x) for x in position_enu],
            reported_position_enu=[float(x) for x in pos], reported_rpy_rad=[float(x) for x in rpy],
            image_path=str(path), camera_dir=str(self.image_path(msg).parent.parent),
            time_boot_s=wire.seconds(msg.time_boot_ms), flight_time_s=float(flight_s),
            wall_s=time.monotonic() - wall0)
        return view

    def finish(self) -> str:
        """The mission's end action (land / RTL / none); waits until landed and disarmed. Returns what happened."""
        st = self.settings
        done = self.begin_finish()
        if done is not None:
            return done
        what = "landing" if st.end_action == "land" else "returning"
        self._wait(lambda: not self.armed, st.wall_timeout_s, f"{st.end_action} until disarmed",
                   sim_timeout_s=300.0, tick_s=st.land_tick_s,
                   status=lambda el: f"{what:<9} {self._where(el)}  (until landed and disarmed)")
        return self.end_text()

    def begin_finish(self) -> str | None:
        """Command the end action without waiting for it; what happened when there is nothing to wait for."""
        st = self.settings
        if self.down is not None and (self.link_lost or not self.armed):  # nothing to command: what it did
            self.in_air = False
            return self.down
        if self.down is not None and self.mode() in (MODE_LAND, MODE_RTL):  # its failsafe lands it
            return None
        if not self.in_air or st.end_action == "none":
            return "left in the air" if self.in_air else "not flown"
        cmd = M.MAV_CMD_NAV_LAND if st.end_action == "land" else M.MAV_CMD_NAV_RETURN_TO_LAUNCH
        r = self.system.commands.long(cmd, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        if r != M.MAV_RESULT_ACCEPTED:
            raise CommandError(f"{st.end_action} refused (MAV_RESULT {r})", cmd, r)
        self._say("landing" if st.end_action == "land" else "returning to launch")
        return None

    def end_text(self) -> str:
        """Once disarmed after begin_finish: what the end action did (a vehicle that left the search: what it did)."""
        self.in_air = False
        if self.down is not None and self.down.startswith("failsafe"):
            return f"{self.down}; {'on the ground, still armed' if self.armed else 'landed'}"
        return "landed" if self.settings.end_action == "land" else "returned and landed"

    def done_flying(self) -> bool:
        """After the end action: disarmed, or (a vehicle that left the search, which its failsafe lands) on the
        ground, not climbing nor sinking (an autopilot without a position may never detect its landing)."""
        if not self.armed:
            return True
        p, v = self.position_enu(), self.velocity_enu()
        return self.down is not None and p is not None and v is not None and p[2] < IN_AIR_M \
            and abs(float(v[2])) < self.settings.settle_speed_m_s  # vertical: a drifting estimate moves sideways

    def leave(self, reason: str) -> VehicleDown:
        """It leaves the search for `reason` (kept for its end state); the error that says so."""
        self.down = reason
        return VehicleDown(reason)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            if self.owns_connection:
                self.connection.close()
        finally:
            if self.tlog is not None:
                self.tlog.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["AUTOPILOT_COMPID", "CAMERA_COMPID", "HEALTH_BITS", "MODE_HOLD", "MODE_LAND", "MODE_RTL", "MODE_TAKEOFF",
           "STREAM_RATES_HZ", "CaptureInfo", "CommandError", "FlightError", "FlightSettings", "MavlinkVehicle",
           "StepFailed", "VehicleLost"]

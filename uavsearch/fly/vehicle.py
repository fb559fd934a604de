"""The second vehicle of "one search loop, two vehicles": a real MAVLink client that flies to each view.

`MavlinkVehicle.capture(position_enu)` does what a ground station would do on a real drone, using only
what any MAVLink client can see and send (pymavlink, no back door into the simulator):

1. DO_REPOSITION (COMMAND_INT, GLOBAL_INT, AMSL) to the waypoint, heading north;
2. wait, on the vehicle's telemetry (GLOBAL_POSITION_INT, i.e. its ESTIMATE), until it is within
   `arrive_radius_m` of the waypoint and slower than `settle_speed_m_s` for `settle_time_s` of
   simulation time (telemetry's time_boot_ms), or fail the step after `step_timeout_s`;
3. IMAGE_START_CAPTURE to the camera (compid 100), wait for CAMERA_IMAGE_CAPTURED, load the PNG its
   file:// URL names, and build the View with the pose the camera REPORTED (lat/lon/alt + attitude
   quaternion), so the estimator's error becomes projection error as on a real drone.

The scene frame's origin is the mission's home (the centre of the search area), not wherever the vehicle
was armed. Timeouts are in simulation time (so they mean the same at --speed 1 and max) with a wall-clock
backstop for a vehicle that stopped talking. Every packet both ways goes to the tlog when one is given.

With `lockstep` (and a vehicle started with `uavsearch sitl --lockstep`) the client is the clock master:
every wait that needs the vehicle to move grants it `lockstep_tick_s` of simulation time at a time and
judges its condition only at the end of a grant, and every command is sent while the simulation stands
still. Perception and policy then take no simulation time, and the same seeds fly the same flight.
A vehicle without lockstep answers UNSUPPORTED and the client falls back to free-running.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import time
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pymavlink import mavutil

from ..errors import UavsearchError
from ..flight.lockstep import MAV_CMD_SIM_ADVANCE
from ..flight.mavlink import wire_units as wire
from ..geometry import GeodeticOrigin, camera_pose_from_vehicle
from ..search.config import SearchConfig
from ..search.views import View, make_view

M = mavutil.mavlink
AUTOPILOT_COMPID = 1
CAMERA_COMPID = 100
# PX4 custom modes (main, sub) as HEARTBEAT.custom_mode = sub << 24 | main << 16.
MODE_HOLD = (4, 3)
MODE_TAKEOFF = (4, 2)
MODE_LAND = (4, 6)
MODE_RTL = (4, 5)
# SYS_STATUS sensor bits the autopilot must report present and healthy before we arm.
HEALTH_BITS = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL | M.MAV_SYS_STATUS_SENSOR_3D_MAG
               | M.MAV_SYS_STATUS_SENSOR_GPS)
# A wait that lasts longer than PROGRESS_FIRST_S (wall clock) says what it waits for and how far it is, then
# again every PROGRESS_EVERY_S, so a real-time take-off or landing or a silent link never looks like a hang.
PROGRESS_FIRST_S = 2.0
PROGRESS_EVERY_S = 5.0


# Telemetry this client reads, at the rates it needs (Hz); everything else the autopilot streams on our link
# is turned off with SET_MESSAGE_INTERVAL, as MAVSDK does. At --speed max the vehicle streams at N x real
# time and a Python client must not fall behind its own socket (a late COMMAND_ACK looks like a lost one).
STREAM_RATES_HZ = {
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0,
    M.MAVLINK_MSG_ID_ATTITUDE: 2.0,
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 0.0,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0.0,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    M.MAVLINK_MSG_ID_VFR_HUD: 0.0,
    M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 0.0,
    M.MAVLINK_MSG_ID_SIM_STATE: 5.0,  # the simulator's truth, only for the log (flight review); others say UNSUPPORTED
}


class FlightError(UavsearchError):
    """The vehicle could not do what the mission asked (no link, arming refused, a step timed out)."""


class StepFailed(FlightError):
    """One capture step failed cleanly (not arrived in time, camera did not answer); the vehicle is still flying."""


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


def _url_to_path(url: str) -> Path:
    p = urllib.parse.urlparse(url)
    if p.scheme not in ("file", ""):
        raise StepFailed(f"camera image URL {url!r} is not a file:// URL this client can read")
    return Path(urllib.request.url2pathname(p.path))


class MavlinkVehicle:
    """A pymavlink client implementing views.Vehicle: connect, arm, take off, fly to views, land."""

    def __init__(self, url: str, config: SearchConfig | None = None, origin: GeodeticOrigin | None = None,
                 settings: FlightSettings | None = None, tlog=None, source_system: int = 245,
                 source_component: int = 190, image_dir: Path | None = None, progress=None):
        self.config = config or SearchConfig()
        self.origin = origin or GeodeticOrigin()
        self.settings = settings or FlightSettings()
        self.url = url
        self.tlog = tlog
        self.image_dir = Path(image_dir) if image_dir else None
        self.progress = progress  # callable(str) for status lines, or None
        os.environ["MAVLINK20"] = "1"  # speak MAVLink 2 from the first packet (pymavlink switches to it anyway)
        try:
            # pymavlink prints its own retries ("... sleeping") to stdout; the error below says it once
            with contextlib.redirect_stdout(io.StringIO()):
                self.conn = mavutil.mavlink_connection(url, source_system=source_system,
                                                       source_component=source_component, dialect="common")
        except Exception as e:  # noqa: BLE001 - any bad URL / port is one line
            raise FlightError(f"cannot open MAVLink connection {url!r}: {e}") from None
        if tlog is not None:
            tlog.attach(self.conn)
        self.target_system = 1
        self._hb: dict = {}
        self._gpos = None  # last GLOBAL_POSITION_INT
        self._sys_status = None
        self._ext_state = None
        self._acks: list = []
        self._captures: list = []
        self._texts: list[str] = []
        self._replies: list = []  # PARAM_VALUE / CAMERA_INFORMATION answers
        self._last_hb_sent = 0.0
        self.last_capture: CaptureInfo | None = None
        self.captures_done = 0
        self.in_air = False
        self.closed = False
        self.connected_sim_s: float | None = None  # vehicle clock when the link came up healthy
        self._settle: _Settle | None = None
        self._last_ack = None
        self.lockstep = False  # on once the vehicle accepted a grant
        self._clock_ms = 0  # lockstep: where the vehicle's clock stands (its answer to the last grant)

    # ------------------------------------------------------------------ message pump
    def _on_message(self, m) -> None:
        t = m.get_type()
        if t == "BAD_DATA":
            return
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src[0] != self.target_system and t != "HEARTBEAT":
            return
        if t == "HEARTBEAT":
            if src[1] == AUTOPILOT_COMPID and m.type != M.MAV_TYPE_GCS:
                self.target_system = src[0]
                self._hb = {"main": (m.custom_mode >> 16) & 0xFF, "sub": (m.custom_mode >> 24) & 0xFF,
                            "armed": bool(m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED), "t": time.monotonic()}
        elif t == "GLOBAL_POSITION_INT":
            self._gpos = m
            if self._settle is not None:
                self._settle.update(self.position_enu(), self.velocity_enu(), wire.seconds(m.time_boot_ms))
        elif t == "SYS_STATUS":
            self._sys_status = m
        elif t == "EXTENDED_SYS_STATE":
            self._ext_state = m
        elif t == "COMMAND_ACK":
            m._sim_s = self.sim_time_s  # the vehicle clock when it answered (last position report before it)
            self._acks.append(m)
        elif t == "CAMERA_IMAGE_CAPTURED":
            self._captures.append(m)
        elif t == "STATUSTEXT":
            self._texts.append(m.text)
            self._texts = self._texts[-20:]
        elif t in ("PARAM_VALUE", "CAMERA_INFORMATION"):
            self._replies.append(m)

    def _heartbeat(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_hb_sent >= 1.0:
            self._last_hb_sent = now
            self.conn.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE)

    def pump(self, timeout_s: float = 0.05) -> None:
        """Read every packet that is waiting (block up to timeout_s for the first one)."""
        self._heartbeat()
        m = self.conn.recv_match(blocking=True, timeout=timeout_s)
        while m is not None:
            self._on_message(m)
            m = self.conn.recv_match(blocking=False)

    def _advance(self, sim_s: float | None = None) -> None:
        """Let the vehicle fly on: grant it sim_s (lockstep) or read its telemetry for up to that long."""
        if self.lockstep:
            self._grant(self._clock_ms + int(round(1000 * (sim_s or self.settings.lockstep_tick_s))))
        else:
            self.pump(0.05 if sim_s is None else sim_s)

    def _grant(self, until_ms: int) -> int:
        """MAV_CMD_SIM_ADVANCE to until_ms; returns the MAV_RESULT (UNSUPPORTED: a free-running vehicle)."""
        r = self.command_int(MAV_CMD_SIM_ADVANCE, M.MAV_FRAME_MISSION, 0, 0, 0, 0, int(until_ms), 0, 0.0)
        if r == M.MAV_RESULT_ACCEPTED:
            self._clock_ms = int(self._last_ack.result_param2)
        return r

    def _wait(self, cond, wall_timeout_s: float, what: str, sim_timeout_s: float | None = None, moving: bool = True,
              tick_s: float | None = None, status=None):
        """Until cond() is truthy; FlightError (StepFailed for sim-time outs) naming `what` otherwise.

        `moving`: the condition needs simulation time (lockstep grants it, `tick_s` at a time, default
        lockstep_tick_s); otherwise it is an answer the vehicle sends at once, and in lockstep no time may
        pass while waiting for it. `status(elapsed)` (elapsed: simulation seconds when moving, else wall
        seconds) is a progress line said while the wait lasts (PROGRESS_FIRST_S, then every
        PROGRESS_EVERY_S of wall clock)."""
        wall0 = time.monotonic()
        wall_end = wall0 + wall_timeout_s
        next_note = wall0 + PROGRESS_FIRST_S
        if self.lockstep and moving:
            self._grant(self._clock_ms)  # a barrier: what the vehicle sent so far has arrived
        sim0 = self.sim_time_s
        while True:
            r = cond()
            if r:
                return r
            now = time.monotonic()
            if status is not None and now >= next_note:
                next_note = now + PROGRESS_EVERY_S
                sim_now = self.sim_time_s
                elapsed = sim_now - sim0 if moving and sim0 is not None and sim_now is not None else now - wall0
                self._say(status(elapsed))
            if time.monotonic() > wall_end:
                raise FlightError(f"{what}: no answer from the vehicle within {wall_timeout_s:.0f} s (wall clock)")
            if sim_timeout_s is not None and sim0 is not None and self.sim_time_s is not None \
                    and self.sim_time_s - sim0 > sim_timeout_s:
                raise StepFailed(f"{what}: not done after {sim_timeout_s:g} s of flight")
            if moving:
                self._advance(tick_s if self.lockstep else None)
            else:
                self.pump()

    @property
    def sim_time_s(self) -> float | None:
        """The vehicle's clock (time since boot) from its last position report."""
        return None if self._gpos is None else wire.seconds(self._gpos.time_boot_ms)

    # ------------------------------------------------------------------ commands
    def command_long(self, command: int, *params: float, compid: int = AUTOPILOT_COMPID,
                     timeout_s: float = 3.0, retries: int = 3) -> int:
        """COMMAND_LONG with retries (as MAVSDK does); the MAV_RESULT of its COMMAND_ACK."""
        p = list(params) + [0.0] * (7 - len(params))
        for attempt in range(retries):
            self._acks.clear()
            self.conn.mav.command_long_send(self.target_system, compid, command, attempt, *p)
            result = self._await_ack(command, timeout_s)
            if result is not None:
                return result
        raise FlightError(f"command {command} not acknowledged by the vehicle")

    def command_int(self, command: int, frame: int, p1, p2, p3, p4, x: int, y: int, z: float,
                    timeout_s: float = 3.0, retries: int = 3) -> int:
        for _ in range(retries):
            self._acks.clear()
            self.conn.mav.command_int_send(self.target_system, AUTOPILOT_COMPID, frame, command, 0, 0,
                                           p1, p2, p3, p4, x, y, z)
            result = self._await_ack(command, timeout_s)
            if result is not None:
                return result
        raise FlightError(f"command {command} not acknowledged by the vehicle")

    def _await_ack(self, command: int, timeout_s: float) -> int | None:
        """The MAV_RESULT of the first COMMAND_ACK for `command` within the timeout, else None (resend)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for a in self._acks:
                if a.command == command:
                    self._last_ack = a
                    return int(a.result)
            self.pump(0.02)
        return None

    def _reply(self, cond, timeout_s: float = 2.0, retries: int = 3, send=None):
        for _ in range(retries):
            self._replies.clear()
            send()
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                for m in self._replies:
                    if cond(m):
                        return m
                self.pump(0.02)
        return None

    def read_param(self, name: str) -> float | None:
        """A parameter's value (int32 parameters decoded bytewise, as PX4 sends them), None if the vehicle has none."""
        m = self._reply(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name,
                        send=lambda: self.conn.mav.param_request_read_send(self.target_system, AUTOPILOT_COMPID,
                                                                           name.encode(), -1))
        if m is None:
            return None
        if m.param_type == M.MAV_PARAM_TYPE_INT32:
            import struct

            return float(struct.unpack("<i", struct.pack("<f", m.param_value))[0])
        return float(m.param_value)

    def camera_information(self):
        """The camera's CAMERA_INFORMATION (REQUEST_MESSAGE to compid 100), or None."""
        return self._reply(lambda m: m.get_type() == "CAMERA_INFORMATION", send=lambda: self.conn.mav.command_long_send(
            self.target_system, CAMERA_COMPID, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_CAMERA_INFORMATION,
            0, 0, 0, 0, 0, 0))

    def _say(self, text: str) -> None:
        if self.progress:
            self.progress(text)

    @property
    def link_text(self) -> str:
        """The URL with the port this client really listens on (`udpin:HOST:0` binds a free one)."""
        scheme, _, rest = self.url.partition(":")
        if scheme != "udpin":
            return self.url
        try:
            port = self.conn.port.getsockname()[1]
        except (AttributeError, OSError):
            return self.url
        return f"udpin:{rest.rpartition(':')[0]}:{port}"

    def _where(self, elapsed_s: float) -> str:
        """'at E .. N .. U .. m  flew .. s', the per-step lines' style, for progress lines."""
        p = self.position_enu()
        at = "no position yet" if p is None else f"at E {p[0]:6.1f} N {p[1]:6.1f} U {p[2]:5.1f} m"
        return f"{at}  flew {elapsed_s:5.1f} s"

    def _missing_health(self) -> str:
        """What the health check still waits for, e.g. 'GPS, position'."""
        s, missing = self._sys_status, []
        if s is None:
            missing.append("SYS_STATUS")
        else:
            ok = s.onboard_control_sensors_present & s.onboard_control_sensors_health
            missing += [name for bit, name in ((M.MAV_SYS_STATUS_SENSOR_3D_GYRO, "gyro"),
                                               (M.MAV_SYS_STATUS_SENSOR_3D_ACCEL, "accel"),
                                               (M.MAV_SYS_STATUS_SENSOR_3D_MAG, "mag"),
                                               (M.MAV_SYS_STATUS_SENSOR_GPS, "GPS")) if not ok & bit]
        if self._gpos is None:
            missing.append("position")
        if self._ext_state is None:
            missing.append("landed state")
        return ", ".join(missing) or "nothing"

    # ------------------------------------------------------------------ state
    def position_enu(self) -> np.ndarray | None:
        """The vehicle's reported position in the scene frame (its estimate)."""
        g = self._gpos
        if g is None:
            return None
        return wire.position_enu(g, self.origin)

    def _distance_to(self, target) -> float:
        p = self.position_enu()
        return math.nan if p is None else float(np.linalg.norm(p - target))

    def velocity_enu(self) -> np.ndarray | None:
        g = self._gpos
        return None if g is None else wire.velocity_enu_m_s(g)

    def mode(self) -> tuple[int, int] | None:
        return (self._hb["main"], self._hb["sub"]) if self._hb else None

    @property
    def armed(self) -> bool:
        return bool(self._hb.get("armed"))

    def _healthy(self) -> bool:
        s = self._sys_status
        return (s is not None and self._gpos is not None and self._ext_state is not None
                and (s.onboard_control_sensors_present & HEALTH_BITS) == HEALTH_BITS
                and (s.onboard_control_sensors_health & HEALTH_BITS) == HEALTH_BITS)

    # ------------------------------------------------------------------ the mission's life cycle
    def connect(self) -> None:
        """Wait for the autopilot's heartbeat and health (gyro, accel, mag, GPS) and a position."""
        st = self.settings
        self._say(f"connecting to {self.link_text} ...")
        self._wait(lambda: self._hb, st.connect_timeout_s, f"no heartbeat on {self.link_text}", moving=False,
                   status=lambda el: f"connecting  no heartbeat yet on {self.link_text}  "
                                     f"{el:.0f} s of {st.connect_timeout_s:.0f} s")
        self._heartbeat(force=True)
        if st.lockstep:
            self.lockstep = self._grant(0) == M.MAV_RESULT_ACCEPTED
            if not self.lockstep:
                self._say("the vehicle does not run in lockstep: this flight will not be reproducible from its seed")
        for mid, hz in STREAM_RATES_HZ.items():
            self.command_long(M.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 1e6 / hz if hz > 0 else -1)
        wall0 = time.monotonic()
        self._wait(self._healthy, st.connect_timeout_s, "vehicle not healthy (SYS_STATUS sensors, position)",
                   status=lambda _: f"connecting  waiting for the vehicle's health ({self._missing_health()})  "
                                    f"{time.monotonic() - wall0:.0f} s of {st.connect_timeout_s:.0f} s")
        self.connected_sim_s = self.sim_time_s

    def take_off(self) -> None:
        """Arm (retrying while the estimator converges), take off to the mission altitude, go to the centre."""
        st = self.settings
        alt_amsl = self.origin.alt_m + self.config.altitude_m
        end = time.monotonic() + st.connect_timeout_s
        while True:
            r = self.command_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            if r == M.MAV_RESULT_ACCEPTED:
                break
            if time.monotonic() > end:
                raise FlightError(f"arming refused ({'; '.join(self._texts[-2:]) or f'MAV_RESULT {r}'})")
            self._advance(0.2)
        self._wait(lambda: self.armed, st.connect_timeout_s, "arming")
        r = self.command_long(M.MAV_CMD_NAV_TAKEOFF, math.nan, 0, 0, math.nan, math.nan, math.nan, alt_amsl)
        if r != M.MAV_RESULT_ACCEPTED:
            raise FlightError(f"takeoff refused ({'; '.join(self._texts[-2:]) or f'MAV_RESULT {r}'})")
        self.in_air = True
        self._say(f"taking off to {self.config.altitude_m:.0f} m")
        self._wait(lambda: self.mode() == MODE_TAKEOFF or self._at_alt(alt_amsl), st.wall_timeout_s, "takeoff start")
        self._wait(lambda: self.mode() == MODE_HOLD and self._at_alt(alt_amsl), st.wall_timeout_s, "takeoff",
                   sim_timeout_s=st.takeoff_timeout_s,
                   status=lambda el: f"take-off  {self._where(el)}  (to {self.config.altitude_m:.0f} m)")

    def _at_alt(self, alt_amsl: float, tol_m: float = 1.0) -> bool:
        return self._gpos is not None and abs(wire.lla(self._gpos)[2] - alt_amsl) < tol_m

    def goto(self, position_enu) -> float:
        """DO_REPOSITION to the waypoint; returns the simulation time it took to arrive and settle."""
        st = self.settings
        target = np.asarray(position_enu, dtype=float)
        lat, lon, alt = self.origin.enu_to_geodetic(target)
        # Track every position report from before the command on, so no report is judged late or skipped.
        self._settle = _Settle(target, st.arrive_radius_m, st.settle_speed_m_s, st.settle_time_s)
        try:
            r = self.command_int(M.MAV_CMD_DO_REPOSITION, M.MAV_FRAME_GLOBAL_INT, -1,
                                 M.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.radians(st.yaw_deg),
                                 wire.deg_to_e7(lat), wire.deg_to_e7(lon), float(alt))
            if r != M.MAV_RESULT_ACCEPTED:
                raise StepFailed(f"goto {np.round(target, 1).tolist()} refused "
                                 f"({'; '.join(self._texts[-1:]) or f'MAV_RESULT {r}'})")
            t0 = getattr(self._last_ack, "_sim_s", None) or self.sim_time_s or 0.0
            self._settle.reset_before(t0)
            self._wait(lambda: self._settle.done_at, st.wall_timeout_s, f"goto {np.round(target, 1).tolist()}",
                       sim_timeout_s=st.step_timeout_s,
                       status=lambda el: f"flying    {self._where(el)}  (to E {target[0]:.1f} N {target[1]:.1f}, "
                                         f"{self._distance_to(target):.1f} m to go)")
            return self._settle.done_at - t0
        finally:
            self._settle = None

    def take_picture(self):
        """IMAGE_START_CAPTURE -> CAMERA_IMAGE_CAPTURED; returns the message."""
        st = self.settings
        self._captures.clear()
        seq = self.captures_done + 1
        r = self.command_long(M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, seq, compid=CAMERA_COMPID)
        if r != M.MAV_RESULT_ACCEPTED:
            raise StepFailed(f"camera refused IMAGE_START_CAPTURE (MAV_RESULT {r})")
        msg = self._wait(lambda: self._captures[-1] if self._captures else None, st.capture_timeout_s,
                         "CAMERA_IMAGE_CAPTURED", moving=False)
        if msg.capture_result != 1:
            raise StepFailed("the camera reported a failed capture")
        self.captures_done += 1
        return msg

    @staticmethod
    def image_path(msg) -> Path:
        """The file CAMERA_IMAGE_CAPTURED's file:// URL names."""
        url = msg.file_url if isinstance(msg.file_url, str) else bytes(msg.file_url).decode(errors="replace")
        return _url_to_path(url.rstrip("\x00"))

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
            cv2.imwrite(str(copy), bgr)
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
        msg = self.take_picture()
        view, path, pos, rpy = self.view_from_capture(msg)
        self.last_capture = CaptureInfo(
            index=int(msg.image_index), waypoint_enu=[float(x) for x in position_enu],
            reported_position_enu=[float(x) for x in pos], reported_rpy_rad=[float(x) for x in rpy],
            image_path=str(path), camera_dir=str(self.image_path(msg).parent.parent),
            time_boot_s=wire.seconds(msg.time_boot_ms), flight_time_s=float(flight),
            wall_s=time.monotonic() - wall0)
        return view

    def finish(self) -> str:
        """The mission's end action (land / RTL / none); waits until landed and disarmed. Returns what happened."""
        st = self.settings
        if not self.in_air or st.end_action == "none":
            return "left in the air" if self.in_air else "not flown"
        cmd = M.MAV_CMD_NAV_LAND if st.end_action == "land" else M.MAV_CMD_NAV_RETURN_TO_LAUNCH
        r = self.command_long(cmd, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        if r != M.MAV_RESULT_ACCEPTED:
            raise FlightError(f"{st.end_action} refused (MAV_RESULT {r})")
        self._say("landing" if st.end_action == "land" else "returning to launch")
        what = "landing" if st.end_action == "land" else "returning"
        self._wait(lambda: not self.armed, st.wall_timeout_s, f"{st.end_action} until disarmed",
                   sim_timeout_s=300.0, tick_s=st.land_tick_s,
                   status=lambda el: f"{what:<9} {self._where(el)}  (until landed and disarmed)")
        self.in_air = False
        return "landed" if st.end_action == "land" else "returned and landed"

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.conn.close()
        finally:
            if self.tlog is not None:
                self.tlog.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["CaptureInfo", "FlightError", "FlightSettings", "MavlinkVehicle", "StepFailed"]

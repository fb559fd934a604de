"""The one place MAVLink is translated: UDP links, telemetry streams, commands, params, missions, camera.

Each link is a non-blocking UDP socket that sends to a fixed remote port (14540 for APIs such as
MAVSDK, 14550 for ground stations, like PX4 SITL) and answers whoever last talked to it. The runner
calls `poll()` and `send_streams()` at a fixed simulation-time rate, never per physics step: the
endpoint never blocks and never advances time itself. Telemetry timestamps are simulation time.

Protocols: HEARTBEAT (autopilot compid 1 and camera compid 100), message streams with
SET_MESSAGE_INTERVAL / REQUEST_MESSAGE, COMMAND_LONG / COMMAND_INT with COMMAND_ACK to the sender,
PARAM_* with PX4's bytewise integer encoding, the mission protocol (upload, download, clear,
set-current, MISSION_CURRENT, MISSION_ITEM_REACHED), SET_POSITION_TARGET_LOCAL_NED for offboard,
TIMESYNC, and MAVLink 2 signing per link. Malformed or badly signed packets are dropped and counted
(SYS_STATUS.errors_comm), never raised.
"""

from __future__ import annotations

import logging
import math
import select
import socket
import struct
import time
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from .camera import CAMERA_COMPID, Camera, CaptureRecord
from .commander import Commander, Result, VehicleCommand
from .lockstep import HOLD_HEARTBEAT_WALL_S, MAV_CMD_SIM_ADVANCE, LockstepGate
from .mission import MissionItem
from .params import ParamError, ParamStore

AUTOPILOT_COMPID = 1
log = logging.getLogger(__name__)
M = mavlink

# Default stream rates (Hz) per link; SET_MESSAGE_INTERVAL changes them per link.
DEFAULT_RATES_HZ = {
    M.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0,
    M.MAVLINK_MSG_ID_ATTITUDE: 10.0,
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 10.0,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0,
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    M.MAVLINK_MSG_ID_VFR_HUD: 4.0,
    M.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    M.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    M.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 2.0,
}
# Ground stations get PX4's lighter "normal" profile: half the position/attitude rates.
GCS_RATES_HZ = {
    **DEFAULT_RATES_HZ,
    M.MAVLINK_MSG_ID_ATTITUDE: 5.0,
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 0.0,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 5.0,
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: 2.0,
    M.MAVLINK_MSG_ID_VFR_HUD: 2.0,
    M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 0.0,
}

CAMERA_COMMANDS = {
    M.MAV_CMD_IMAGE_START_CAPTURE,
    M.MAV_CMD_IMAGE_STOP_CAPTURE,
    M.MAV_CMD_REQUEST_CAMERA_INFORMATION,
    M.MAV_CMD_REQUEST_CAMERA_SETTINGS,
    M.MAV_CMD_REQUEST_STORAGE_INFORMATION,
    M.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS,
    M.MAV_CMD_SET_CAMERA_MODE,
}
CAMERA_MESSAGES = {
    M.MAVLINK_MSG_ID_CAMERA_INFORMATION,
    M.MAVLINK_MSG_ID_CAMERA_SETTINGS,
    M.MAVLINK_MSG_ID_STORAGE_INFORMATION,
    M.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS,
    M.MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED,
}

HEALTH_BITS = {
    "gyro": M.MAV_SYS_STATUS_SENSOR_3D_GYRO,
    "accel": M.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
    "mag": M.MAV_SYS_STATUS_SENSOR_3D_MAG,
    "baro": M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE,
    "gps": M.MAV_SYS_STATUS_SENSOR_GPS,
}
ALWAYS_OK_BITS = (
    M.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | M.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | M.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | M.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | M.MAV_SYS_STATUS_GEOFENCE
    | M.MAV_SYS_STATUS_AHRS
    | M.MAV_SYS_STATUS_SENSOR_BATTERY
)

MISSION_RETRY_WALL_S = 0.25
DATAGRAM_BYTES = 1400  # below a typical MTU; frames are never split across datagrams
SIGNING_EPOCH = 1420070400  # 2015-01-01 UTC
MISSION_MAX_RETRIES = 8
PX4_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255  # reported as PX4 v1.15.0 (official release)


def encode_param(value: float, is_int: bool) -> tuple[float, int]:
    """PX4 bytewise encoding: an int32 parameter travels as the float with the same four bytes."""
    if is_int:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0], M.MAV_PARAM_TYPE_INT32
    return float(value), M.MAV_PARAM_TYPE_REAL32


def decode_param(value: float, param_type: int, is_int: bool) -> float:
    if is_int and param_type in (M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_UINT32, M.MAV_PARAM_TYPE_INT8,
                                 M.MAV_PARAM_TYPE_UINT8, M.MAV_PARAM_TYPE_INT16, M.MAV_PARAM_TYPE_UINT16):
        return float(struct.unpack("<i", struct.pack("<f", value))[0])
    return float(value)


def parse_signing_key(text: str) -> bytes:
    """32-byte key as 64 hex digits (what `--signing-key` takes)."""
    from ..errors import UavsearchError

    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise UavsearchError("--signing-key must be 64 hexadecimal digits (a 32-byte key)") from None
    if len(key) != 32:
        raise UavsearchError(f"--signing-key must be 32 bytes (64 hex digits), got {len(key)} bytes")
    return key


@dataclass
class LinkConfig:
    """One UDP link: where to send, where to listen, and how to sign."""

    name: str
    remote_port: int
    remote_host: str = "127.0.0.1"
    local_port: int = 0  # 0: any free port; replies come from it
    signing_key: bytes | None = None
    require_signed: bool = True  # False: sign output but accept unsigned input (MAVSDK cannot sign)
    rates_hz: dict | None = None  # default stream rates; None = DEFAULT_RATES_HZ


class _Writer:
    def __init__(self, link: "Link"):
        self.link = link

    def write(self, buf: bytes) -> None:
        self.link.send_raw(bytes(buf))


@dataclass
class _Upload:
    partner: tuple[int, int]
    count: int
    items: list = field(default_factory=list)
    last_request_wall: float = 0.0
    retries: int = 0
    mission_type: int = 0


class Link:
    def __init__(self, cfg: LinkConfig, sysid: int):
        self.cfg = cfg
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.sock.bind(("127.0.0.1" if cfg.remote_host in ("127.0.0.1", "localhost") else "0.0.0.0", cfg.local_port))
        self.remote = (cfg.remote_host, cfg.remote_port)
        self.mav = mavlink.MAVLink(_Writer(self), srcSystem=sysid, srcComponent=AUTOPILOT_COMPID)
        self.mav.robust_parsing = True
        self._frame_signed = False
        if cfg.signing_key is not None:
            self.mav.signing.secret_key = cfg.signing_key
            self.mav.signing.link_id = 0
            self.mav.signing.sign_outgoing = True
            # MAVLink 2 signing timestamps count 10 us since 2015-01-01 on the wall clock: receivers drop
            # a new stream that starts more than a minute behind their own clock.
            self.mav.signing.timestamp = int((max(time.time(), SIGNING_EPOCH) - SIGNING_EPOCH) * 1e5)
            if not cfg.require_signed:
                # Accept unsigned frames, but a signed frame must carry the right signature.
                self.mav.signing.allow_unsigned_callback = lambda mav, msgid: not self._frame_signed
        self.default_rates_hz = cfg.rates_hz or DEFAULT_RATES_HZ
        self.intervals_us = {mid: int(1e6 / hz) if hz > 0 else 0 for mid, hz in self.default_rates_hz.items()}
        self.next_due_us = {mid: 0 for mid in self.intervals_us}
        self.rx_packets = 0
        self.rx_dropped = 0
        self.tx_packets = 0
        self._out = bytearray()
        self.upload: _Upload | None = None

    @property
    def local_port(self) -> int:
        return self.sock.getsockname()[1]

    def send_raw(self, buf: bytes) -> None:
        """Queue one frame; flush() packs queued frames into datagrams of at most DATAGRAM_BYTES (as PX4 does)."""
        if self._out and len(self._out) + len(buf) > DATAGRAM_BYTES:
            self.flush()
        self._out += buf
        self.tx_packets += 1

    def flush(self) -> None:
        if not self._out:
            return
        try:
            self.sock.sendto(bytes(self._out), self.remote)
        except OSError:
            pass  # nobody listening (ICMP port unreachable) or a full buffer: telemetry is best effort
        self._out.clear()

    def send(self, msg, compid: int = AUTOPILOT_COMPID) -> None:
        self.mav.srcComponent = compid
        self.mav.send(msg)

    def receive(self) -> list:
        """Every message waiting on the socket; bad frames are counted and dropped."""
        out = []
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                return out  # ICMP errors surface on the next recv on some platforms
            self._frame_signed = len(data) > 2 and data[0] == 0xFD and bool(data[2] & 0x01)
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:  # pymavlink raises a few plain errors on garbage even when robust
                self.rx_dropped += 1
                self.mav.buf = bytearray()
                self.mav.buf_index = 0
                continue
            good = 0
            for m in msgs:
                if m.get_type() in ("BAD_DATA", "UNKNOWN") or m.get_msgId() < 0:
                    self.rx_dropped += 1
                    continue
                good += 1
                out.append(m)
            if good:
                self.remote = addr
                self.rx_packets += good
            elif not msgs and len(data) > 0 and self.mav.bytes_needed() > 0 and len(self.mav.buf) - self.mav.buf_index > 0:
                # A truncated frame stays in the parser's buffer: drop it, datagrams never continue.
                self.rx_dropped += 1
                self.mav.buf = bytearray()
                self.mav.buf_index = 0

    def close(self) -> None:
        self.sock.close()


class MavlinkEndpoint:
    """Translates between MAVLink packets and the commander / camera / param store."""

    def __init__(self, commander: Commander, params: ParamStore, links: list[LinkConfig], camera: Camera | None = None,
                 sysid: int = 1, tlog_path=None):
        self.cmd = commander
        self.vehicle = commander.vehicle
        self.params = params
        self.camera = camera
        self.sysid = sysid
        self.links = [Link(c, sysid) for c in links]
        self.wall_s = 0.0
        self._sent_state = None
        self._tlog = open(tlog_path, "ab") if tlog_path else None
        self._snap: dict = {}
        self._fds = [link.sock.fileno() for link in self.links]
        self._next_due_any = 0  # the earliest stream deadline over every link
        self.lockstep: LockstepGate | None = None  # set by a runner in lockstep (see lockstep.py)
        self._hold_hb_wall = -math.inf

    # ------------------------------------------------------------------ plumbing
    def fileno_list(self) -> list[int]:
        return [l.sock.fileno() for l in self.links]

    def wait_readable(self, timeout_s: float) -> bool:
        if timeout_s <= 0:
            return False
        r, _, _ = select.select(self.fileno_list(), [], [], timeout_s)
        return bool(r)

    @property
    def rx_dropped(self) -> int:
        return sum(l.rx_dropped for l in self.links)

    def close(self) -> None:
        for l in self.links:
            l.flush()
            l.close()
        if self._tlog:
            self._tlog.close()

    def _time_boot_ms(self) -> int:
        return int(self.vehicle.time_us // 1000) & 0xFFFFFFFF

    def _broadcast(self, msg, compid: int = AUTOPILOT_COMPID) -> None:
        for l in self.links:
            l.send(msg, compid)

    def _ack(self, link: Link, m, command: int, result: int, compid: int = AUTOPILOT_COMPID,
             result_param2: int = 0) -> None:
        link.send(link.mav.command_ack_encode(command, int(result), 0, result_param2, m.get_srcSystem(),
                                              m.get_srcComponent()), compid)

    # ------------------------------------------------------------------ the two calls the runner makes
    def poll(self, wall_s: float) -> int:
        """Handle every waiting packet on every link; returns how many were handled."""
        self.wall_s = wall_s
        self._snap.clear()
        n = 0
        try:  # one select() tells which sockets have data: idle links cost no recv call
            readable = set(select.select(self._fds, [], [], 0)[0])
        except (OSError, ValueError):
            readable = set(self._fds)
        for link in self.links:
            if link.upload is not None:
                self._mission_retry(link)
            if link.sock.fileno() not in readable:
                continue
            for m in link.receive():
                n += 1
                try:
                    self._handle(link, m)
                except Exception as e:  # a packet must never take the vehicle down
                    link.rx_dropped += 1
                    log.debug("dropped %s", m, exc_info=True)
                    self.cmd.text(3, f"dropped {m.get_type()}: {type(e).__name__}")
        if self.cmd.texts or self.cmd.mission_events or self.cmd.captures:
            self._flush_events()
        self._flush_links()
        return n

    def _flush_links(self) -> None:
        for link in self.links:
            link.flush()

    def send_streams(self) -> None:
        now = int(self.vehicle.time_us)
        self._snap.clear()  # vehicle outputs are built once per call, shared by every message and link
        self._send_state_if_changed()
        if self.camera is not None and self.camera.capturing_interval:
            for rec in self.camera.update():
                self._broadcast_capture(rec)
        if now < self._next_due_any:
            return self._flush_links()
        built: dict = {}  # one message object per id and tick, packed per link (own sequence, signing)
        for link in self.links:
            if self.camera is not None and now >= link.next_due_us.get("camera_hb", 0):
                link.next_due_us["camera_hb"] = now + 1_000_000
                self._camera_heartbeat(link, now)
            for mid, interval in link.intervals_us.items():
                if interval <= 0 or now < link.next_due_us.get(mid, 0):
                    continue
                link.next_due_us[mid] = now + interval
                msg = built[mid] if mid in built else built.setdefault(mid, self._build_safe(mid))
                if msg is not None:
                    try:
                        link.send(msg)
                    except (struct.error, OverflowError, ValueError):  # a field out of its wire range
                        log.warning("cannot pack %s", msg.get_type(), exc_info=True)
                        built[mid] = None
        due = [t for link in self.links for mid, t in link.next_due_us.items()
               if mid == "camera_hb" or link.intervals_us.get(mid, 0) > 0]
        self._next_due_any = min(due) if due else now + 1_000_000
        self._flush_links()

    def _camera_heartbeat(self, link, now: int) -> None:
        """The camera's heartbeat, always followed by the autopilot's in the same datagram.

        pymavlink (so MAVProxy) takes a system's autopilot type from the LAST heartbeat of that system,
        whichever component sent it; after the camera's (MAV_AUTOPILOT_INVALID) it falls back to ArduPilot
        mode handling ("required argument is not a float"). Clients parse a datagram at once, so they never
        act between the two."""
        link.flush()
        link.send(link.mav.heartbeat_encode(M.MAV_TYPE_CAMERA, M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE),
                  CAMERA_COMPID)
        link.send(self._heartbeat())
        hb = M.MAVLINK_MSG_ID_HEARTBEAT
        if link.intervals_us.get(hb, 0) > 0:
            link.next_due_us[hb] = now + link.intervals_us[hb]

    def _send_state_if_changed(self) -> None:
        """HEARTBEAT + EXTENDED_SYS_STATE at once when arming, mode or landed state changed."""
        state = (self.cmd.armed, self.cmd.custom_mode)
        if self.cmd.state_changed or state != self._sent_state:
            self.cmd.state_changed = False
            self._sent_state = state
            self._broadcast(self._heartbeat())
            self._broadcast(self._extended_sys_state())

    def hold(self, wall_s: float) -> None:
        """Lockstep: the clock reached its grant. Publish the state it stopped in, answer the grant, and
        keep a heartbeat going on the wall clock while nothing runs."""
        self._send_state_if_changed()  # the client must not learn of a change later than the ACK
        self.lockstep.arrived(int(self.vehicle.time_us))
        if wall_s - self._hold_hb_wall >= HOLD_HEARTBEAT_WALL_S:
            self._hold_hb_wall = wall_s
            self._broadcast(self._heartbeat())
        self._flush_links()

    def _flush_events(self) -> None:
        for t in self.cmd.texts:
            self._broadcast(M.MAVLink_statustext_message(t.severity, t.text.encode()[:50], 0, 0))
        self.cmd.texts.clear()
        for kind, seq in self.cmd.mission_events:
            if kind == "reached":
                self._broadcast(M.MAVLink_mission_item_reached_message(seq))
            else:
                self._broadcast(self._mission_current())
        self.cmd.mission_events.clear()
        for _item in self.cmd.captures:
            if self.camera is not None:
                self._broadcast_capture(self.camera.capture())
        self.cmd.captures.clear()

    # ------------------------------------------------------------------ telemetry builders
    def _heartbeat(self):
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.cmd.armed:
            base |= M.MAV_MODE_FLAG_SAFETY_ARMED
        if self.cmd.mode in ("TAKEOFF", "HOLD", "MISSION", "RTL", "LAND", "OFFBOARD"):
            base |= M.MAV_MODE_FLAG_AUTO_ENABLED | M.MAV_MODE_FLAG_GUIDED_ENABLED | M.MAV_MODE_FLAG_STABILIZE_ENABLED
        status = M.MAV_STATE_ACTIVE if self.cmd.armed else M.MAV_STATE_STANDBY
        return M.MAVLink_heartbeat_message(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, base, self.cmd.custom_mode, status, 3)

    def _extended_sys_state(self):
        return M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_UNDEFINED, self.cmd.landed_state)

    def _sys_status(self):
        h = self._v("sensor_health")
        present = ALWAYS_OK_BITS | M.MAV_SYS_STATUS_PREARM_CHECK
        health = ALWAYS_OK_BITS
        for name, bit in HEALTH_BITS.items():
            present |= bit
            if getattr(h, name):
                health |= bit
        if not self.cmd.arming_failures() or self.cmd.armed:
            health |= M.MAV_SYS_STATUS_PREARM_CHECK
        b = self._v("battery")
        return M.MAVLink_sys_status_message(
            present, present, health, 0, int(b.voltage_v * 1000), int(b.current_a * 100), int(round(b.remaining * 100)),
            0, min(self.rx_dropped, 65535), 0, 0, 0, 0, 0, 0, 0,
        )

    def _v(self, name: str):
        """A vehicle output, read once per send_streams() call."""
        try:
            return self._snap[name]
        except KeyError:
            value = None
            if name == "local_position":  # the commander read it at this very instant: reuse it
                lp = self.cmd.local_position
                if lp is not None and lp.timestamp_us == self.vehicle.time_us:
                    value = lp
            if value is None:
                value = getattr(self.vehicle, name)
            self._snap[name] = value
            return value

    def _attitude(self):
        a = self._v("attitude")
        w0, x, y_, z = (float(q) for q in a.q_wxyz)
        r = math.atan2(2.0 * (w0 * x + y_ * z), 1.0 - 2.0 * (x * x + y_ * y_))
        p = math.asin(max(-1.0, min(1.0, 2.0 * (w0 * y_ - z * x))))
        y = math.atan2(2.0 * (w0 * z + x * y_), 1.0 - 2.0 * (y_ * y_ + z * z))
        w = a.angular_velocity_frd_rad_s
        return M.MAVLink_attitude_message(self._time_boot_ms(), r, p, y, float(w[0]), float(w[1]), float(w[2]))

    def _attitude_quaternion(self):
        a = self._v("attitude")
        q = [float(x) for x in a.q_wxyz]
        w = a.angular_velocity_frd_rad_s
        return M.MAVLink_attitude_quaternion_message(self._time_boot_ms(), *q, float(w[0]), float(w[1]), float(w[2]), [0.0] * 4)

    def _local_position(self):
        lp = self._v("local_position")
        p, v = lp.position_ned_m, lp.velocity_ned_m_s
        return M.MAVLink_local_position_ned_message(self._time_boot_ms(), *(float(x) for x in p), *(float(x) for x in v))

    def _global_position(self):
        gp = self._v("global_position")
        lp = self._v("local_position")
        v = lp.velocity_ned_m_s
        hdg = int(round(math.degrees(lp.heading_rad) % 360.0 * 100)) % 36000
        return M.MAVLink_global_position_int_message(
            self._time_boot_ms(), int(round(gp.lat_deg * 1e7)), int(round(gp.lon_deg * 1e7)), int(round(gp.alt_amsl_m * 1000)),
            int(round((gp.alt_amsl_m - self.cmd.home_alt_amsl_m) * 1000)), int(round(v[0] * 100)), int(round(v[1] * 100)), int(round(v[2] * 100)), hdg,
        )

    def _gps_raw(self):
        """The raw GPS solution (not the estimate), as a GPS receiver reports it."""
        fix = self._v("gps_fix")
        if fix is None or not hasattr(fix, "lat_deg"):
            return None
        v = fix.velocity_ned_m_s
        speed = math.hypot(v[0], v[1])
        cog = int(round(math.degrees(math.atan2(v[1], v[0])) % 360.0 * 100)) % 36000 if speed > 0.2 else 65535
        return M.MAVLink_gps_raw_int_message(
            int(fix.time_us), int(fix.fix_type), int(round(fix.lat_deg * 1e7)), int(round(fix.lon_deg * 1e7)),
            int(round(fix.alt_amsl_m * 1000)), int(min(fix.eph_m * 100, 65534)), int(min(fix.epv_m * 100, 65534)),
            int(speed * 100), cog, int(fix.satellites_visible),
        )

    def _vfr_hud(self):
        lp = self._v("local_position")
        v = lp.velocity_ned_m_s
        gs = float(np.hypot(v[0], v[1]))
        hdg = int(round(math.degrees(lp.heading_rad))) % 360
        thr = int(np.clip(getattr(self.vehicle, "thrust_setpoint", 0.0) * 100, 0, 100))
        return M.MAVLink_vfr_hud_message(gs, gs, hdg, thr, float(self._v("global_position").alt_amsl_m), float(-v[2]))

    def _battery_status(self):
        b = self._v("battery")
        volts = [min(int(b.voltage_v * 1000), 65534)] + [65535] * 9
        return M.MAVLink_battery_status_message(
            0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, volts, int(b.current_a * 100),
            int(b.discharged_mah), -1, int(round(b.remaining * 100)),
        )

    def _home_position(self):
        if not self.cmd.home_set:
            return None
        lla = self.cmd.home_lla()
        h = self.cmd.home_ned
        return M.MAVLink_home_position_message(
            int(round(lla[0] * 1e7)), int(round(lla[1] * 1e7)), int(round(lla[2] * 1000)), float(h[0]), float(h[1]), float(h[2]),
            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(self.vehicle.time_us),
        )

    def _mission_current(self):
        m = self.cmd.mission
        if not m.items:
            state = M.MISSION_STATE_NO_MISSION
        elif m.finished:
            state = M.MISSION_STATE_COMPLETE
        elif self.cmd.mode == "MISSION":
            state = M.MISSION_STATE_ACTIVE
        elif m.reached_seq >= 0:
            state = M.MISSION_STATE_PAUSED
        else:
            state = M.MISSION_STATE_NOT_STARTED
        return M.MAVLink_mission_current_message(m.current_seq, len(m.items), state, 1 if self.cmd.mode == "MISSION" else 0)

    def _position_target(self):
        sp = self.cmd._last_sp
        if sp is None:
            return None
        p, v = sp.position_ned_m, sp.velocity_ned_m_s
        mask = 0
        for i, bit in enumerate((1, 2, 4)):
            if not math.isfinite(p[i]):
                mask |= bit
        for i, bit in enumerate((8, 16, 32)):
            if not math.isfinite(v[i]):
                mask |= bit
        mask |= 64 | 128 | 256 | 2048
        clean = [0.0 if not math.isfinite(x) else float(x) for x in (*p, *v)]
        yaw = sp.yaw_rad if math.isfinite(sp.yaw_rad) else 0.0
        return M.MAVLink_position_target_local_ned_message(self._time_boot_ms(), M.MAV_FRAME_LOCAL_NED, mask, *clean, 0.0, 0.0, 0.0, yaw, 0.0)

    def _autopilot_version(self):
        caps = (
            M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
        )
        return M.MAVLink_autopilot_version_message(
            caps, PX4_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x5541565345415243, [0] * 18
        )

    def _build_safe(self, mid: int):
        """A telemetry message, or None when the state cannot be encoded (e.g. a NaN estimate)."""
        try:
            return self._build(mid)
        except (ValueError, OverflowError):
            log.warning("cannot build message %d", mid, exc_info=True)
            return None

    def _build(self, mid: int):
        f = {
            M.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            M.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            M.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self._attitude_quaternion,
            M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position,
            M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position,
            M.MAVLINK_MSG_ID_GPS_RAW_INT: self._gps_raw,
            M.MAVLINK_MSG_ID_VFR_HUD: self._vfr_hud,
            M.MAVLINK_MSG_ID_BATTERY_STATUS: self._battery_status,
            M.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            M.MAVLINK_MSG_ID_MISSION_CURRENT: self._mission_current,
            M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: self._position_target,
            M.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
        }.get(mid)
        return f() if f else None

    # ------------------------------------------------------------------ camera messages
    def _camera_message(self, mid: int):
        c = self.camera
        t = self._time_boot_ms()
        if mid == M.MAVLINK_MSG_ID_CAMERA_INFORMATION:
            vendor = list(b"uavsearch".ljust(32, b"\0"))
            model = list(f"nadir {c.intrinsics.width_px}x{c.intrinsics.height_px}".encode().ljust(32, b"\0"))[:32]
            sw, sh = c.sensor_size_mm
            return M.MAVLink_camera_information_message(
                t, vendor, model, 1, c.focal_length_mm, sw, sh, c.intrinsics.width_px, c.intrinsics.height_px, 0,
                M.CAMERA_CAP_FLAGS_CAPTURE_IMAGE, 0, b"", 0, 0,
            )
        if mid == M.MAVLINK_MSG_ID_CAMERA_SETTINGS:
            return M.MAVLink_camera_settings_message(t, M.CAMERA_MODE_IMAGE, math.nan, math.nan, 0)
        if mid == M.MAVLINK_MSG_ID_STORAGE_INFORMATION:
            return M.MAVLink_storage_information_message(t, 1, 1, M.STORAGE_STATUS_READY, 100000.0, 0.0, 100000.0, 100.0, 100.0, 0, b"run", 0)
        if mid == M.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS:
            return M.MAVLink_camera_capture_status_message(
                t, 3 if c.capturing_interval else 0, 0, float(c.interval_s), 0, 100000.0, c.image_count, 0
            )
        return None

    def _capture_message(self, rec: CaptureRecord):
        url = rec.file_url.encode()[:205] if rec.ok else b""
        return M.MAVLink_camera_image_captured_message(
            self._time_boot_ms(), int(rec.time_us), 0, int(round(rec.lat_deg * 1e7)), int(round(rec.lon_deg * 1e7)),
            int(round(rec.alt_amsl_m * 1000)), int(round(rec.alt_rel_home_m * 1000)), list(rec.q_wxyz), rec.index,
            1 if rec.ok else 0, url,
        )

    def _broadcast_capture(self, rec: CaptureRecord) -> None:
        self._broadcast(self._capture_message(rec), CAMERA_COMPID)

    # ------------------------------------------------------------------ incoming
    def _for_me(self, target_system: int) -> bool:
        return target_system in (0, self.sysid)

    def _handle(self, link: Link, m) -> None:
        t = m.get_type()
        if m.get_srcSystem() == self.sysid and m.get_srcComponent() in (AUTOPILOT_COMPID, CAMERA_COMPID):
            return  # our own echo
        h = getattr(self, "_on_" + t.lower(), None)
        if h is not None:
            h(link, m)

    def _on_heartbeat(self, link, m):
        if m.type not in (M.MAV_TYPE_CAMERA, M.MAV_TYPE_GIMBAL) and m.get_srcSystem() != self.sysid:
            self.cmd.on_gcs_heartbeat()

    def _on_timesync(self, link, m):
        if m.tc1 == 0:
            link.send(M.MAVLink_timesync_message(int(self.vehicle.time_us) * 1000, m.ts1))

    # ---- commands
    def _on_command_long(self, link, m):
        if not self._for_me(m.target_system):
            return
        p = [m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7]
        self._command(link, m, m.command, p, M.MAV_FRAME_GLOBAL, m.target_component)

    def _on_command_int(self, link, m):
        if not self._for_me(m.target_system):
            return
        p = [m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z]
        if m.frame in (M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                       M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
            p[4] = m.x * 1e-7 if m.x != 0 or m.y != 0 else math.nan
            p[5] = m.y * 1e-7 if m.x != 0 or m.y != 0 else math.nan
        frame = {M.MAV_FRAME_GLOBAL_INT: M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: M.MAV_FRAME_GLOBAL_RELATIVE_ALT}.get(m.frame, m.frame)
        self._command(link, m, m.command, p, frame, m.target_component)

    def _command(self, link, m, command: int, p: list, frame: int, target_comp: int) -> None:
        try:
            self._dispatch_command(link, m, command, p, frame, target_comp)
        except (ValueError, OverflowError):  # e.g. a message id or count of NaN / inf
            self._ack(link, m, command, Result.DENIED, CAMERA_COMPID if target_comp == CAMERA_COMPID else AUTOPILOT_COMPID)

    def _dispatch_command(self, link, m, command: int, p: list, frame: int, target_comp: int) -> None:
        to_camera = target_comp == CAMERA_COMPID or (target_comp == 0 and command in CAMERA_COMMANDS)
        if to_camera:
            if self.camera is None:
                return
            result = self._camera_command(link, m, command, p)
            if result is not None:
                self._ack(link, m, command, result, CAMERA_COMPID)
            return
        if target_comp not in (0, AUTOPILOT_COMPID):
            return  # addressed to a component that does not exist here
        if command == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._ack(link, m, command, self._set_interval(link, p))
        if command == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            mid = int(p[0])
            iv = link.intervals_us.get(mid, 0)
            link.send(M.MAVLink_message_interval_message(mid, iv if iv > 0 else -1))
            return self._ack(link, m, command, Result.ACCEPTED)
        if command == M.MAV_CMD_REQUEST_MESSAGE:
            mid = int(p[0]) if math.isfinite(p[0]) else -1
            msg = self._build(mid) if mid != M.MAVLINK_MSG_ID_HOME_POSITION or self.cmd.home_set else None
            if msg is None:
                result = Result.TEMPORARILY_REJECTED if mid == M.MAVLINK_MSG_ID_HOME_POSITION else Result.UNSUPPORTED
                return self._ack(link, m, command, result)
            self._ack(link, m, command, Result.ACCEPTED)  # the ACK first, then the message (as PX4)
            return link.send(msg)
        if command == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._ack(link, m, command, Result.ACCEPTED)
            return link.send(self._autopilot_version())
        if command == MAV_CMD_SIM_ADVANCE:
            return self._sim_advance(link, m, command, p[4])
        vc = VehicleCommand(command, *(float(x) for x in p), frame=frame, source_system=m.get_srcSystem(),
                            source_component=m.get_srcComponent())
        result = self.cmd.handle_command(vc)
        self._ack(link, m, command, result)
        self._flush_events()
        self._send_state_if_changed()

    def _sim_advance(self, link: Link, m, command: int, until_ms: float) -> None:
        if self.lockstep is None:
            return self._ack(link, m, command, Result.UNSUPPORTED)
        if not (math.isfinite(until_ms) and 0 <= until_ms < 2**31):
            return self._ack(link, m, command, Result.DENIED)
        self.lockstep.grant(int(until_ms) * 1000,
                            lambda now_ms: self._ack(link, m, command, Result.ACCEPTED, result_param2=now_ms))

    def _set_interval(self, link: Link, p) -> Result:
        mid, iv = int(p[0]), p[1]
        if mid not in DEFAULT_RATES_HZ:
            return Result.UNSUPPORTED
        if iv == 0:
            hz = link.default_rates_hz.get(mid, 0.0)
            link.intervals_us[mid] = int(1e6 / hz) if hz > 0 else 0
        elif iv < 0:
            link.intervals_us[mid] = 0
        else:
            link.intervals_us[mid] = max(int(iv), 1000)  # at most 1 kHz of simulation time
        link.next_due_us[mid] = 0
        self._next_due_any = 0
        return Result.ACCEPTED

    def _camera_command(self, link, m, command: int, p) -> Result | None:
        """None when the command was already acknowledged."""
        c = self.camera
        if command == M.MAV_CMD_REQUEST_MESSAGE:
            msg = self._camera_message(int(p[0]) if math.isfinite(p[0]) else -1)
            if msg is None:
                return Result.UNSUPPORTED
            self._ack(link, m, command, Result.ACCEPTED, CAMERA_COMPID)
            link.send(msg, CAMERA_COMPID)
            return None
        if command == M.MAV_CMD_IMAGE_START_CAPTURE:
            if not c.available:
                return Result.FAILED
            interval = p[1] if math.isfinite(p[1]) else 0.0
            count = int(p[2]) if math.isfinite(p[2]) else 1
            if interval < 0 or count < 0:
                return Result.DENIED
            # ACK first, then the capture(s): clients wait for the ACK before listening for images.
            self._ack(link, m, command, Result.ACCEPTED, CAMERA_COMPID)
            link.flush()  # the ACK leaves before the render
            for rec in c.start(interval, count):
                self._broadcast_capture(rec)
            return None
        if command == M.MAV_CMD_IMAGE_STOP_CAPTURE:
            c.stop()
            return Result.ACCEPTED
        if command == M.MAV_CMD_SET_CAMERA_MODE:
            return Result.ACCEPTED if int(p[1]) == M.CAMERA_MODE_IMAGE else Result.DENIED
        req = {
            M.MAV_CMD_REQUEST_CAMERA_INFORMATION: M.MAVLINK_MSG_ID_CAMERA_INFORMATION,
            M.MAV_CMD_REQUEST_CAMERA_SETTINGS: M.MAVLINK_MSG_ID_CAMERA_SETTINGS,
            M.MAV_CMD_REQUEST_STORAGE_INFORMATION: M.MAVLINK_MSG_ID_STORAGE_INFORMATION,
            M.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS: M.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS,
        }.get(command)
        if req is not None:
            self._ack(link, m, command, Result.ACCEPTED, CAMERA_COMPID)
            link.send(self._camera_message(req), CAMERA_COMPID)
            return None
        return Result.UNSUPPORTED

    # ---- params
    def _param_value(self, name: str):
        d = self.params.definition(name)
        val, ptype = encode_param(self.params[name], d.type == "int")
        return M.MAVLink_param_value_message(name.encode(), val, ptype, len(self.params), self.params.index(name))

    def _on_param_request_list(self, link, m):
        if not self._for_me(m.target_system) or m.target_component not in (0, AUTOPILOT_COMPID):
            return
        for name in self.params.names():
            link.send(self._param_value(name))

    def _on_param_request_read(self, link, m):
        if not self._for_me(m.target_system) or m.target_component not in (0, AUTOPILOT_COMPID):
            return
        names = self.params.names()
        if m.param_index >= 0:
            if m.param_index < len(names):
                link.send(self._param_value(names[m.param_index]))
            return
        name = _param_name(m.param_id)
        if name in self.params:
            link.send(self._param_value(name))
        else:
            self.cmd.text(4, f"unknown parameter {name}")
            self._flush_events()

    def _on_param_set(self, link, m):
        if not self._for_me(m.target_system) or m.target_component not in (0, AUTOPILOT_COMPID):
            return
        name = _param_name(m.param_id)
        if name not in self.params:
            self.cmd.text(4, f"unknown parameter {name}")
            return
        d = self.params.definition(name)
        try:
            self.params.set(name, decode_param(m.param_value, m.param_type, d.type == "int"))
        except ParamError as e:
            self.cmd.text(4, str(e))
        # PX4 answers with the (possibly unchanged) value, so the client sees what is stored.
        self._broadcast(self._param_value(name))

    # ---- mission protocol
    def _mission_ack(self, link, partner, result: int, mission_type: int = 0):
        link.send(M.MAVLink_mission_ack_message(partner[0], partner[1], result, mission_type))

    def _item_message(self, it: MissionItem, partner, as_int: bool):
        if as_int:
            return M.MAVLink_mission_item_int_message(partner[0], partner[1], it.seq, it.frame, it.command,
                                                      int(it.seq == self.cmd.mission.current_seq), it.autocontinue,
                                                      it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z, 0)
        return M.MAVLink_mission_item_message(partner[0], partner[1], it.seq, it.frame, it.command,
                                              int(it.seq == self.cmd.mission.current_seq), it.autocontinue,
                                              it.param1, it.param2, it.param3, it.param4, it.x * 1e-7, it.y * 1e-7, it.z, 0)

    def _mission_addressed(self, m) -> bool:
        return self._for_me(m.target_system) and m.target_component in (0, AUTOPILOT_COMPID)

    def _on_mission_request_list(self, link, m):
        if not self._mission_addressed(m):
            return
        mt = getattr(m, "mission_type", 0)
        n = len(self.cmd.mission.items) if mt == M.MAV_MISSION_TYPE_MISSION else 0
        link.send(M.MAVLink_mission_count_message(m.get_srcSystem(), m.get_srcComponent(), n, mt))

    def _send_item(self, link, m, as_int: bool):
        if not self._mission_addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        items = self.cmd.mission.items
        if getattr(m, "mission_type", 0) != M.MAV_MISSION_TYPE_MISSION or not 0 <= m.seq < len(items):
            return self._mission_ack(link, partner, M.MAV_MISSION_INVALID_SEQUENCE, getattr(m, "mission_type", 0))
        link.send(self._item_message(items[m.seq], partner, as_int))

    def _on_mission_request_int(self, link, m):
        self._send_item(link, m, True)

    def _on_mission_request(self, link, m):
        self._send_item(link, m, False)

    def _on_mission_count(self, link, m):
        if not self._mission_addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        mt = getattr(m, "mission_type", 0)
        if mt != M.MAV_MISSION_TYPE_MISSION:
            return self._mission_ack(link, partner, M.MAV_MISSION_UNSUPPORTED, mt)
        if m.count > 500:
            return self._mission_ack(link, partner, M.MAV_MISSION_NO_SPACE)
        if m.count == 0:
            self.cmd.clear_mission()
            self._mission_ack(link, partner, M.MAV_MISSION_ACCEPTED)
            return self._flush_events()
        link.upload = _Upload(partner, m.count, [], self.wall_s, 0, mt)
        link.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], 0, mt))

    def _on_mission_item_int(self, link, m):
        self._receive_item(link, m, m.x, m.y)

    def _on_mission_item(self, link, m):
        self._receive_item(link, m, int(round(m.x * 1e7)), int(round(m.y * 1e7)))

    def _receive_item(self, link, m, x: int, y: int):
        up = link.upload
        if up is None or not self._mission_addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        if partner != up.partner:
            return self._mission_ack(link, partner, M.MAV_MISSION_DENIED)
        expected = len(up.items)
        if m.seq != expected:
            if m.seq > expected:
                link.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], expected, up.mission_type))
            return
        up.items.append(MissionItem(m.seq, m.frame, m.command, m.current, m.autocontinue, m.param1, m.param2, m.param3,
                                    m.param4, int(x), int(y), float(m.z)))
        up.retries = 0
        up.last_request_wall = self.wall_s
        if len(up.items) < up.count:
            link.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], len(up.items), up.mission_type))
            return
        link.upload = None
        result, _reason = self.cmd.upload_mission(up.items)
        self._mission_ack(link, partner, result)
        self._flush_events()

    def _mission_retry(self, link: Link) -> None:
        up = link.upload
        if up is None or self.wall_s - up.last_request_wall < MISSION_RETRY_WALL_S:
            return
        if up.retries >= MISSION_MAX_RETRIES:
            link.upload = None
            return self._mission_ack(link, up.partner, M.MAV_MISSION_OPERATION_CANCELLED)
        up.retries += 1
        up.last_request_wall = self.wall_s
        link.send(M.MAVLink_mission_request_int_message(up.partner[0], up.partner[1], len(up.items), up.mission_type))

    def _on_mission_clear_all(self, link, m):
        if not self._mission_addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        if getattr(m, "mission_type", 0) not in (M.MAV_MISSION_TYPE_MISSION, M.MAV_MISSION_TYPE_ALL):
            return self._mission_ack(link, partner, M.MAV_MISSION_ACCEPTED, m.mission_type)
        self.cmd.clear_mission()
        self._mission_ack(link, partner, M.MAV_MISSION_ACCEPTED)
        self._flush_events()

    def _on_mission_set_current(self, link, m):
        if not self._mission_addressed(m):
            return
        if not self.cmd.set_mission_current(m.seq):
            self.cmd.text(4, f"mission item {m.seq} does not exist")
        self._flush_events()

    def _on_mission_ack(self, link, m):
        pass  # end of a download: nothing to release

    # ---- offboard
    def _on_set_position_target_local_ned(self, link, m):
        if not self._mission_addressed(m):
            return
        from .messages import TrajectorySetpoint

        mask = m.type_mask
        nan = math.nan
        p = np.array([nan if mask & b else v for b, v in ((1, m.x), (2, m.y), (4, m.z))], dtype=float)
        v = np.array([nan if mask & b else x for b, x in ((8, m.vx), (16, m.vy), (32, m.vz))], dtype=float)
        a = np.array([nan if mask & b else x for b, x in ((64, m.afx), (128, m.afy), (256, m.afz))], dtype=float)
        yaw = nan if mask & 1024 else float(m.yaw)
        yawrate = nan if mask & 2048 else float(m.yaw_rate)
        if any(math.isinf(x) for x in (*p, *v, *a, yaw, yawrate)):
            link.rx_dropped += 1  # NaN means "not controlled"; infinity means nothing
            return
        frame = m.coordinate_frame
        if frame == M.MAV_FRAME_BODY_NED or frame == M.MAV_FRAME_BODY_OFFSET_NED:
            hdg = float(self._v("local_position").heading_rad)
            c, s = math.cos(hdg), math.sin(hdg)
            rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            v = rot @ v if np.all(np.isfinite(v[:2])) else v
            a = rot @ a if np.all(np.isfinite(a[:2])) else a
            if frame == M.MAV_FRAME_BODY_OFFSET_NED and np.all(np.isfinite(p)):
                p = self._v("local_position").position_ned_m + rot @ p
        elif frame == M.MAV_FRAME_LOCAL_OFFSET_NED and np.all(np.isfinite(p)):
            p = self._v("local_position").position_ned_m + p
        elif frame != M.MAV_FRAME_LOCAL_NED:
            self.cmd.text(4, f"offboard frame {frame} not supported")
            return
        self.cmd.set_offboard_setpoint(TrajectorySetpoint(int(self.vehicle.time_us), p, v, a, yaw, yawrate))


def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return raw.split("\0", 1)[0].strip()

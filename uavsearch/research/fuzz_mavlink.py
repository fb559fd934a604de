"""Seeded MAVLink fuzzer: hostile and malformed packets at a real `uavsearch sitl` flying a hold.

    python tools/fuzz_mavlink.py [--packets 10000] [--seeds 1 2 3] [--speed 1] [--rate 250] [--sources 1]
    python tools/fuzz_mavlink.py --signing [--count 1000]

Fuzz run (per seed): start `uavsearch sitl` (camera scene on) on free loopback ports, take off to a
hold at 10 m over the API link, then send --packets packets drawn from the categories below to the
API link while reading both links. Measured: the largest wall-clock gap between autopilot
HEARTBEATs on each link, the largest distance of LOCAL_POSITION_NED from the hold point, the
vehicle's RSS before and after, COMMAND_LONG/INT addressed to an existing component left without a
COMMAND_ACK, whether the vehicle still answers (PARAM_REQUEST_READ and REQUEST_MESSAGE) and whether
it still lands and disarms. With --sources N the packets leave from N sockets (N peers of the API link,
one chosen at random per packet): every COMMAND_ACK must come back to the socket that sent its command,
and the flying client (a peer too) must keep its heartbeats. Categories:

  random_bytes     random datagrams (some starting with a MAVLink magic byte)
  truncated        valid frames cut short
  bitflip          valid frames with 1-8 bits flipped
  random_message   any message of the common dialect with random field values, to every component
  hostile_command  COMMAND_LONG / COMMAND_INT, known and random ids, NaN / inf / huge / tiny params
  mission_abuse    MISSION_COUNT / ITEM(_INT) / REQUEST / SET_CURRENT / CLEAR / ACK out of order, NaN items
  param_abuse      PARAM_SET out of range / NaN / wrong type / unknown names; requests of bad indices
  nan_setpoint     SET_POSITION_TARGET_* and SET_ATTITUDE_TARGET with NaN / inf fields
  wrong_target     real flight commands (land, disarm, RTL, reposition, param set) to another system
  camera_abuse     IMAGE_START_CAPTURE with huge counts, NaN / inf / tiny intervals; camera requests

Commands that a real vehicle must obey with their values (land, RTL, force-disarm, mode changes,
mission start) are never sent to this vehicle with valid values: the fuzzer checks that the vehicle
survives what it must refuse, not that it refuses what it must do.

Signing run (--signing): a sitl with a signing key; per link (API, GCS), how many of --count unsigned,
wrong-key, replayed and far-future-timestamp (forged) REQUEST_MESSAGE commands were accepted
(answered with a COMMAND_ACK), wrong-key frames hidden behind junk or an unsigned frame in one
datagram, whether the legitimate signed sender is still accepted after the forgeries, and how many
of 100 copies of a signed frame accepted on one link are accepted again on the other.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from ..flight.sitl_process import SitlProcess

M = mavlink
CATEGORIES = ("random_bytes", "truncated", "bitflip", "random_message", "hostile_command", "mission_abuse",
              "param_abuse", "nan_setpoint", "wrong_target", "camera_abuse")
HOSTILE = (math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e20, -1e20, 2.0**31, -(2.0**31), 2.0**32 + 0.5,
           1e-45, -1e-45, 1e-7, 0.5, -0.5, -1.0, 65536.0, 1e6)
# Values that can only be refused, for commands whose valid values would legitimately move the vehicle.
REFUSE_ONLY = (math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e20, -1e20, 2.0**31, -(2.0**31))
VEHICLE_SYSID = 1
AUTOPILOT, CAMERA = 1, 100
FUZZ_SYSID, FUZZ_COMPID = 254, 191
# Handled by other categories (or would fly the vehicle with valid random values).
NOT_RANDOM = {"COMMAND_LONG", "COMMAND_INT", "SET_MODE", "SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT",
              "SET_ATTITUDE_TARGET", "PARAM_SET", "PARAM_EXT_SET", "MISSION_ITEM", "MISSION_ITEM_INT", "MISSION_COUNT",
              "MISSION_SET_CURRENT", "MANUAL_CONTROL", "SET_HOME_POSITION", "PARAM_REQUEST_LIST", "MISSION_CLEAR_ALL"}
# Commands a vehicle must obey when their values are valid: sent with values that can only be refused.
OBEYED = {M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_DO_REPOSITION, M.MAV_CMD_DO_CHANGE_SPEED,
          M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_DO_SET_HOME, M.MAV_CMD_DO_PAUSE_CONTINUE,
          M.MAV_CMD_DO_SET_MISSION_CURRENT, M.MAV_CMD_SET_MESSAGE_INTERVAL}
NEVER = {M.MAV_CMD_NAV_LAND, M.MAV_CMD_NAV_RETURN_TO_LAUNCH, M.MAV_CMD_MISSION_START, M.MAV_CMD_NAV_LOITER_UNLIM,
         M.MAV_CMD_DO_FLIGHTTERMINATION, M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, M.MAV_CMD_IMAGE_START_CAPTURE,
         M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_DO_MOTOR_TEST, M.MAV_CMD_DO_SET_SERVO, M.MAV_CMD_DO_SET_ACTUATOR}
KNOWN_COMMANDS = [M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_DO_REPOSITION, M.MAV_CMD_DO_CHANGE_SPEED,
                  M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_DO_SET_HOME, M.MAV_CMD_DO_PAUSE_CONTINUE,
                  M.MAV_CMD_DO_SET_MISSION_CURRENT, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAV_CMD_GET_MESSAGE_INTERVAL,
                  M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, M.MAV_CMD_REQUEST_CAMERA_INFORMATION,
                  M.MAV_CMD_REQUEST_CAMERA_SETTINGS, M.MAV_CMD_REQUEST_STORAGE_INFORMATION,
                  M.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS, M.MAV_CMD_SET_CAMERA_MODE, M.MAV_CMD_IMAGE_STOP_CAPTURE,
                  31000]  # the vendor SIM_ADVANCE (no lockstep here: UNSUPPORTED)
RANDOM_CLASSES = sorted((c for c in M.mavlink_map.values() if c.msgname not in NOT_RANDOM), key=lambda c: c.id)
SAFE_FRAMES = ("heartbeat", "param_request_read", "request_data_stream", "mission_request_list", "timesync")


class Packets:
    """Seeded packet generator: `next()` -> (category, datagram bytes, ACKs expected {command: n})."""

    def __init__(self, seed: int, categories=CATEGORIES, param_names=()):
        self.rng = np.random.default_rng(seed)
        self.mav = M.MAVLink(None, srcSystem=FUZZ_SYSID, srcComponent=FUZZ_COMPID)
        self.categories = tuple(categories)
        self.param_names = list(param_names) or ["MPC_XY_P", "MC_ROLLRATE_P", "MAV_SYS_ID", "NAV_DLL_ACT"]

    # -- helpers
    def _pick(self, seq):
        return seq[int(self.rng.integers(len(seq)))]

    def _frame(self, msg) -> bytes:
        buf = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def _target_comp(self) -> int:
        return self._pick((0, AUTOPILOT, CAMERA, AUTOPILOT, CAMERA, int(self.rng.integers(256))))

    def _hostile(self, pool=HOSTILE) -> float:
        return float(self._pick(pool)) if self.rng.random() < 0.8 else float(self.rng.normal() * 10 ** self.rng.integers(0, 8))

    def _random_value(self, ftype: str, n: int):
        r = self.rng
        if ftype == "char":
            return bytes(r.integers(0, 256, n if n else 1, dtype=np.uint8))
        if ftype in ("float", "double"):
            v = [self._hostile() if r.random() < 0.5 else float(r.normal() * 100) for _ in range(max(n, 1))]
            return v if n else v[0]
        bits = int("".join(ch for ch in ftype if ch.isdigit()) or 8)
        signed = not ftype.startswith("uint")
        lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
        vals = [lo + int(r.integers(0, 1 << 62)) * (hi - lo) // ((1 << 62) - 1) if r.random() < 0.7 else self._pick((lo, hi, 0))
                for _ in range(max(n, 1))]
        return vals if n else vals[0]

    def _random_message(self):
        cls = self._pick(RANDOM_CLASSES)
        args = []
        for name, ftype, n in zip(cls.fieldnames, cls.fieldtypes, _array_lengths(cls)):
            if name == "target_system":
                args.append(self._pick((0, VEHICLE_SYSID, VEHICLE_SYSID, int(self.rng.integers(256)))))
            elif name == "target_component":
                args.append(self._target_comp())
            else:
                args.append(self._random_value(ftype, n))
        return cls(*args)

    def _command(self, command: int, params, target_sys=VEHICLE_SYSID, target_comp=None, as_int=None):
        comp = self._target_comp() if target_comp is None else target_comp
        as_int = self.rng.random() < 0.4 if as_int is None else as_int
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        if as_int:
            xy = [int(np.clip(v, -2**31, 2**31 - 1)) if math.isfinite(v) else int(self.rng.integers(-2**31, 2**31))
                  for v in p[4:6]]
            msg = M.MAVLink_command_int_message(target_sys, comp, int(self._pick((0, 3, 5, 6, 1, 255))), command, 0, 0,
                                                *p[:4], *xy, p[6])
        else:
            msg = M.MAVLink_command_long_message(target_sys, comp, command, int(self.rng.integers(256)), *p)
        exists = target_sys in (0, VEHICLE_SYSID) and comp in (0, AUTOPILOT, CAMERA)
        return msg, ({command: 1} if exists else {})

    # -- categories
    def random_bytes(self):
        n = int(self.rng.integers(1, 300))
        data = bytearray(self.rng.integers(0, 256, n, dtype=np.uint8).tobytes())
        if self.rng.random() < 0.5:
            data[0] = self._pick((0xFD, 0xFE))
        return bytes(data), {}

    def _safe_frame(self) -> bytes:
        kind = self._pick(SAFE_FRAMES)
        msg = {
            "heartbeat": lambda: M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3),
            "param_request_read": lambda: M.MAVLink_param_request_read_message(VEHICLE_SYSID, AUTOPILOT, b"MPC_XY_P", -1),
            "request_data_stream": lambda: M.MAVLink_request_data_stream_message(VEHICLE_SYSID, AUTOPILOT, 0, 1, 1),
            "mission_request_list": lambda: M.MAVLink_mission_request_list_message(VEHICLE_SYSID, AUTOPILOT, 0),
            "timesync": lambda: M.MAVLink_timesync_message(0, int(self.rng.integers(1, 2**62))),
        }[kind]()
        return self._frame(msg)

    def truncated(self):
        frame = self._safe_frame() if self.rng.random() < 0.5 else self._frame(self._random_message())
        return frame[: int(self.rng.integers(1, len(frame)))], {}

    def bitflip(self):
        frame = bytearray(self._safe_frame())
        for _ in range(int(self.rng.integers(1, 9))):
            i = int(self.rng.integers(len(frame)))
            frame[i] ^= 1 << int(self.rng.integers(8))
        return bytes(frame), {}

    def random_message(self):
        return self._frame(self._random_message()), {}

    def hostile_command(self):
        r = self.rng.random()
        if r < 0.15:
            command = int(self.rng.integers(0, 65536))
            while command in NEVER or command in OBEYED:
                command = int(self.rng.integers(0, 65536))
            params = [self._hostile() for _ in range(7)]
        else:
            command = self._pick(KNOWN_COMMANDS)
            pool = REFUSE_ONLY if command in OBEYED else HOSTILE
            params = [self._hostile(pool) if command not in OBEYED else float(self._pick(pool)) for _ in range(7)]
            if command == M.MAV_CMD_SET_MESSAGE_INTERVAL and self.rng.random() < 0.5:
                # the message id itself hostile (fractions that truncate to HEARTBEAT's 0, negative, huge);
                # the interval valid-looking, including "off"
                params[0] = float(self._pick((0.5, 0.99, -0.5, 1e-9, 65536.0, 2.0**31, -1.0, math.nan)))
                params[1] = float(self._pick((-1.0, 0.0, 1e6, 1.0)))
        msg, acks = self._command(command, params)
        return self._frame(msg), acks

    def mission_abuse(self):
        r, rng = self.rng.random(), self.rng
        comp = self._pick((0, AUTOPILOT, AUTOPILOT, int(rng.integers(256))))
        mt = int(self._pick((0, 0, 0, 1, 2, 255)))
        seq = int(self._pick((0, 1, 2, 499, 65535, int(rng.integers(65536)))))
        if r < 0.15:
            msg = M.MAVLink_mission_count_message(VEHICLE_SYSID, comp, int(self._pick((1, 2, 3, 501, 65535))), mt)
        elif r < 0.45:
            xy = [self._pick((math.nan, math.inf, -math.inf, 1e20, 91.0, -181.0, 47.39, 8.54)) for _ in range(2)]
            z = self._pick((math.nan, math.inf, -1e20, 10.0, 3.4e38))
            cmd = int(self._pick((16, 22, 21, 20, 17, 2000, int(rng.integers(65536)))))
            msg = M.MAVLink_mission_item_message(VEHICLE_SYSID, comp, int(self._pick((0, 1, 2, seq))), int(self._pick((0, 3, 6, 1, 255))),
                                                 cmd, 0, 1, *[self._hostile() for _ in range(4)], *xy, z, mt)
        elif r < 0.65:
            x, y = (int(rng.integers(-2**31, 2**31)) for _ in range(2))
            z = self._pick((math.nan, math.inf, -1e20, 10.0))
            cmd = int(self._pick((16, 22, 21, 20, 2000, int(rng.integers(65536)))))
            msg = M.MAVLink_mission_item_int_message(VEHICLE_SYSID, comp, int(self._pick((0, 1, 2, seq))), int(self._pick((0, 3, 6, 5, 255))),
                                                     cmd, 0, 1, *[self._hostile() for _ in range(4)], x, y, z, mt)
        elif r < 0.75:
            msg = M.MAVLink_mission_request_int_message(VEHICLE_SYSID, comp, seq, mt)
        elif r < 0.82:
            msg = M.MAVLink_mission_request_message(VEHICLE_SYSID, comp, seq, mt)
        elif r < 0.9:
            msg = M.MAVLink_mission_set_current_message(VEHICLE_SYSID, comp, seq)
        elif r < 0.95:
            msg = M.MAVLink_mission_ack_message(VEHICLE_SYSID, comp, int(rng.integers(256)), mt)
        else:
            msg = M.MAVLink_mission_clear_all_message(VEHICLE_SYSID, comp, mt)
        return self._frame(msg), {}

    def param_abuse(self):
        r, rng = self.rng.random(), self.rng
        comp = self._pick((0, AUTOPILOT, AUTOPILOT, CAMERA, int(rng.integers(256))))
        if r < 0.6:
            name = self._pick(self.param_names) if rng.random() < 0.8 else bytes(rng.integers(1, 256, 16, dtype=np.uint8))
            name = name.encode() if isinstance(name, str) else name
            ptype = int(self._pick((M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_UINT8, 0, 255)))
            msg = M.MAVLink_param_set_message(VEHICLE_SYSID, comp, name, float(self._pick(REFUSE_ONLY)), ptype)
        elif r < 0.97:
            name = self._pick(self.param_names).encode() if rng.random() < 0.5 else bytes(rng.integers(0, 256, 16, dtype=np.uint8))
            msg = M.MAVLink_param_request_read_message(VEHICLE_SYSID, comp, name,
                                                       int(self._pick((-1, -2, 0, 32767, -32768, int(rng.integers(-32768, 32768))))))
        else:
            msg = M.MAVLink_param_request_list_message(VEHICLE_SYSID, comp)
        return self._frame(msg), {}

    def nan_setpoint(self):
        rng = self.rng
        h = lambda: float(self._pick((math.nan, math.inf, -math.inf, 3.4e38, math.nan, 0.0)))  # noqa: E731
        mask = int(rng.integers(0, 65536))
        frame = int(self._pick((1, 7, 8, 9, 0, 255)))
        r = rng.random()
        if r < 0.5:
            msg = M.MAVLink_set_position_target_local_ned_message(0, VEHICLE_SYSID, self._target_comp(), frame, mask,
                                                                  *[h() for _ in range(11)])
        elif r < 0.8:
            msg = M.MAVLink_set_position_target_global_int_message(0, VEHICLE_SYSID, self._target_comp(), frame, mask,
                                                                   int(rng.integers(-2**31, 2**31)), int(rng.integers(-2**31, 2**31)),
                                                                   *[h() for _ in range(9)])
        else:
            msg = M.MAVLink_set_attitude_target_message(0, VEHICLE_SYSID, self._target_comp(), int(rng.integers(256)),
                                                        [h() for _ in range(4)], h(), h(), h(), h())
        return self._frame(msg), {}

    def wrong_target(self):
        rng = self.rng
        sysid = int(rng.integers(2, 256))
        r = rng.random()
        if r < 0.7:
            command, params = self._pick([(M.MAV_CMD_NAV_LAND, [0] * 7), (M.MAV_CMD_NAV_RETURN_TO_LAUNCH, [0] * 7),
                                          (M.MAV_CMD_COMPONENT_ARM_DISARM, [0, 21196]),
                                          (M.MAV_CMD_DO_REPOSITION, [-1, 1, 0, math.nan, 47.3980, 8.5460, 520.0]),
                                          (M.MAV_CMD_DO_SET_MODE, [1, 4, 6]),  # Auto.Land
                                          (M.MAV_CMD_SET_MESSAGE_INTERVAL, [0, -1]),
                                          (M.MAV_CMD_IMAGE_START_CAPTURE, [0, 1e-6, 1e9])])
            msg, _ = self._command(command, params, target_sys=sysid, target_comp=self._pick((0, 1, 100)))
        elif r < 0.85:
            msg = M.MAVLink_param_set_message(sysid, 1, b"MC_ROLLRATE_P", 0.01, M.MAV_PARAM_TYPE_REAL32)
        else:
            msg = M.MAVLink_mission_clear_all_message(sysid, 1, 0)
        return self._frame(msg), {}

    def camera_abuse(self):
        rng = self.rng
        r = rng.random()
        comp = self._pick((CAMERA, CAMERA, 0, AUTOPILOT))
        if r < 0.7:
            interval = float(self._pick((math.nan, math.inf, -math.inf, 1e-9, 1e-7, 0.0, -1.0, 1e-3, 0.5, 3.4e38)))
            count = float(self._pick((math.nan, math.inf, 1e9, 2.0**31, 2.0**32, 65535.0, -1.0, 0.0, 1.0, 5.0)))
            msg, acks = self._command(M.MAV_CMD_IMAGE_START_CAPTURE, [0, interval, count, float(rng.integers(0, 10))],
                                      target_comp=comp)
        elif r < 0.8:
            msg, acks = self._command(M.MAV_CMD_IMAGE_STOP_CAPTURE, [0], target_comp=comp)
        else:
            command = self._pick((M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_SET_CAMERA_MODE, M.MAV_CMD_REQUEST_CAMERA_INFORMATION))
            msg, acks = self._command(command, [self._hostile() for _ in range(7)], target_comp=comp)
        return self._frame(msg), acks

    def next(self):
        cat = self._pick(self.categories)
        data, acks = getattr(self, cat)()
        return cat, data, acks


def _array_lengths(cls):
    """Per field in `fieldnames` order: the array length (0 for a scalar)."""
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths))
    return [lengths.get(n, 0) for n in cls.fieldnames]


def rss_kib(pid: int) -> int:
    """Resident set size of a process and its children (the render worker), in KiB."""
    total = 0
    pids = [pid]
    try:
        pids += [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        pass
    for p in pids:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except OSError:
            pass
    return total


# --------------------------------------------------------------------------------------------------- flight


@dataclass
class LinkWatch:
    """Autopilot heartbeats and positions seen on one link, on the wall clock."""

    last_hb: float | None = None
    max_gap_s: float = 0.0
    heartbeats: int = 0

    def heartbeat(self, now: float) -> None:
        if self.last_hb is not None:
            self.max_gap_s = max(self.max_gap_s, now - self.last_hb)
        self.last_hb = now
        self.heartbeats += 1

    def close(self, now: float) -> None:
        if self.last_hb is not None:
            self.max_gap_s = max(self.max_gap_s, now - self.last_hb)


@dataclass
class FuzzResult:
    seed: int
    packets: int
    per_category: dict
    fuzz_wall_s: float
    max_hb_gap_api_s: float
    max_hb_gap_gcs_s: float
    max_deviation_m: float
    rss_before_kib: int
    rss_after_kib: int
    commands_expecting_ack: int
    commands_unanswered: int
    answers: bool
    landed: bool
    alive: bool
    exit_code: int | None
    notes: list = field(default_factory=list)
    sources: int = 1
    acks_misrouted: int = 0  # COMMAND_ACKs that reached another source than the one that asked

    @property
    def ok(self) -> bool:
        return self.alive and self.answers and self.landed


class _Vehicle:
    """A pymavlink connection on one link port: reads everything, keeps the watch up to date."""

    def __init__(self, port: int, watch: LinkWatch, sink=None):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190,
                                               dialect="common")
        self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.watch = watch
        self.sink = sink
        self.last_pos = None

    def drain(self, limit: int = 10000) -> list:
        out = []
        for _ in range(limit):
            m = self.conn.recv_msg()
            if m is None:
                break
            t = m.get_type()
            now = time.monotonic()
            if t == "HEARTBEAT" and m.get_srcComponent() == AUTOPILOT and m.get_srcSystem() == VEHICLE_SYSID:
                self.watch.heartbeat(now)
            elif t == "LOCAL_POSITION_NED":
                self.last_pos = (m.x, m.y, m.z)
            if self.sink is not None:
                self.sink(m)
            out.append(m)
        return out

    def wait(self, pred, timeout: float):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in self.drain():
                if pred(m):
                    return m
            time.sleep(0.002)
        return None

    def command(self, command: int, *params: float, comp: int = AUTOPILOT, timeout: float = 5.0):
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(VEHICLE_SYSID, comp, command, 0, *p)
        return self.wait(lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, timeout)

    def send_raw(self, data: bytes) -> None:
        for addr in self.conn.clients:  # the vehicle's link socket (udpin learns it from the first packet)
            self.conn.port.sendto(data, addr)


def _hold_point(v: _Vehicle, seconds: float):
    """Mean LOCAL_POSITION_NED over a short settled window."""
    pts = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        v.drain()
        if v.last_pos is not None:
            pts.append(v.last_pos)
        time.sleep(0.02)
    return np.mean(np.asarray(pts), axis=0) if pts else None


class _Sources:
    """N sockets the fuzz packets leave from (peers of the API link); counts the COMMAND_ACKs each gets back."""

    def __init__(self, n: int, seed: int):
        self.rng = np.random.default_rng([seed, 7])  # its own stream: the packets are the same whatever N
        self.socks = []
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
            s.setblocking(False)
            self.socks.append(s)
        self.parsers = [M.MAVLink(None) for _ in self.socks]
        for prs in self.parsers:
            prs.robust_parsing = True
        self.expected = [dict() for _ in self.socks]
        self.got = [dict() for _ in self.socks]

    def send(self, data: bytes, acks: dict, addr) -> None:
        i = int(self.rng.integers(len(self.socks)))
        for c, n in acks.items():
            self.expected[i][c] = self.expected[i].get(c, 0) + n
        self.socks[i].sendto(data, addr)

    def drain(self) -> None:
        for s, prs, got in zip(self.socks, self.parsers, self.got):
            while True:
                try:
                    data, _ = s.recvfrom(65535)
                except (BlockingIOError, InterruptedError):
                    break
                for m in prs.parse_buffer(data) or []:
                    if m.get_type() == "COMMAND_ACK":
                        got[m.command] = got.get(m.command, 0) + 1

    def tally(self) -> tuple[int, int, int]:
        """(expected, unanswered, misrouted): an ACK at the wrong socket counts as both."""
        expected = unanswered = misrouted = 0
        for exp, got in zip(self.expected, self.got):
            expected += sum(exp.values())
            unanswered += sum(max(0, n - got.get(c, 0)) for c, n in exp.items())
            misrouted += sum(max(0, n - exp.get(c, 0)) for c, n in got.items())
        return expected, unanswered, misrouted

    def close(self) -> None:
        for s in self.socks:
            s.close()


def fuzz_flight(seed: int, packets: int, speed: str = "1", rate_hz: float = 250.0, alt_m: float = 10.0,
                categories=CATEGORIES, run_dir: Path | None = None, progress=print, sources: int = 1) -> FuzzResult:
    """Take off to a hold, fuzz it with `packets` packets, check it still answers and lands. `sources` > 1:
    the packets leave from that many sockets besides the flying client's."""
    tmp = None
    if run_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="fuzz_")
        run_dir = Path(tmp.name)
    sitl = SitlProcess(Path(run_dir), "--seed", str(seed), "--scene", "0", "--param", f"MIS_TAKEOFF_ALT={alt_m}",
                       speed=speed, camera=True)
    api_watch, gcs_watch = LinkWatch(), LinkWatch()
    srcs = _Sources(sources, seed) if sources > 1 else None
    api = _Vehicle(sitl.api_port, api_watch)
    gcs = _Vehicle(sitl.gcs_port, gcs_watch)
    notes = []
    per_cat = {c: 0 for c in categories}
    expected_acks: dict = {}
    got_acks: dict = {}
    try:
        if api.wait(lambda m: m.get_type() == "HEARTBEAT", 20) is None:
            raise RuntimeError("no heartbeat from the vehicle")
        gcs.wait(lambda m: m.get_type() == "HEARTBEAT", 20)
        names, total = set(), None
        api.conn.mav.param_request_list_send(VEHICLE_SYSID, AUTOPILOT)
        end = time.monotonic() + 5
        while time.monotonic() < end and (total is None or len(names) < total):
            for m in api.drain():
                if m.get_type() == "PARAM_VALUE":
                    names.add(m.param_id)
                    total = m.param_count
            time.sleep(0.01)
        gen = Packets(seed, categories, sorted(set(names)))
        for _ in range(60):  # the estimator needs a few seconds before arming
            ack = api.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout=2)
            if ack is not None and ack.result == 0:
                break
            time.sleep(0.5)
        else:
            raise RuntimeError("cannot arm")
        ack = api.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        if ack is None or ack.result != 0:
            raise RuntimeError(f"takeoff refused: {ack}")
        end = time.monotonic() + 120
        while time.monotonic() < end:  # Hold (4, 3) at altitude
            hb = api.wait(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == AUTOPILOT, 5)
            if hb is not None and (hb.custom_mode >> 16) & 0xFF == 4 and (hb.custom_mode >> 24) & 0xFF == 3 \
                    and api.last_pos is not None and -api.last_pos[2] > alt_m - 0.5:
                break
        else:
            raise RuntimeError("did not reach the hold")
        hold = _hold_point(api, 3.0)
        for side in (api, gcs):  # heartbeats queued while only the API link was read are no gap
            side.drain()
            side.watch.max_gap_s, side.watch.last_hb = 0.0, None
        rss0 = rss_kib(sitl.proc.pid)
        max_dev = 0.0
        progress(f"seed {seed}: holding at N {hold[0]:.2f} E {hold[1]:.2f} D {hold[2]:.2f}; fuzzing {packets} packets")

        def on_ack(m):
            if m.get_type() == "COMMAND_ACK":
                got_acks[m.command] = got_acks.get(m.command, 0) + 1

        api.sink = on_ack
        t0 = time.monotonic()
        for i in range(packets):
            cat, data, acks = gen.next()
            per_cat[cat] += 1
            if srcs is not None:
                srcs.send(data, acks, sitl.link_address("api"))
                srcs.drain()
            else:
                for c, n in acks.items():
                    expected_acks[c] = expected_acks.get(c, 0) + n
                api.send_raw(data)
            for side in (api, gcs):
                side.drain()
            if api.last_pos is not None:
                max_dev = max(max_dev, float(np.linalg.norm(np.asarray(api.last_pos) - hold)))
            if gcs.last_pos is not None:
                max_dev = max(max_dev, float(np.linalg.norm(np.asarray(gcs.last_pos) - hold)))
            due = t0 + (i + 1) / rate_hz
            while time.monotonic() < due:
                for side in (api, gcs):
                    side.drain()
                time.sleep(0.001)
            if sitl.proc.poll() is not None:
                notes.append(f"vehicle exited during the fuzz after {i + 1} packets")
                break
        fuzz_wall = time.monotonic() - t0
        settle_end = time.monotonic() + 2.0  # the last ACKs and positions
        while time.monotonic() < settle_end:
            for side in (api, gcs):
                side.drain()
            if srcs is not None:
                srcs.drain()
            if api.last_pos is not None:
                max_dev = max(max_dev, float(np.linalg.norm(np.asarray(api.last_pos) - hold)))
            time.sleep(0.005)
        now = time.monotonic()
        api_watch.close(now)
        gcs_watch.close(now)
        api.sink = None
        rss1 = rss_kib(sitl.proc.pid)
        misrouted = 0
        if srcs is not None:
            n_expected, unanswered, misrouted = srcs.tally()
            if unanswered or misrouted:
                notes.append(f"COMMAND_ACKs: {unanswered} missing at the asking socket, {misrouted} at another")
        else:
            missing = {c: n - got_acks.get(c, 0) for c, n in expected_acks.items() if n != got_acks.get(c, 0)}
            unanswered = sum(max(0, n) for n in missing.values())
            n_expected = sum(expected_acks.values())
            if missing:
                notes.append(f"COMMAND_ACKs missing (+) or extra (-) by command: {missing}")
        alive = sitl.proc.poll() is None
        api.command(M.MAV_CMD_IMAGE_STOP_CAPTURE, comp=CAMERA, timeout=2)
        api.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0)  # HEARTBEAT back to its default rate, whatever happened
        api.conn.mav.param_request_read_send(VEHICLE_SYSID, AUTOPILOT, b"MPC_XY_P", -1)
        answered_param = api.wait(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "MPC_XY_P", 5) is not None
        ack = api.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        answers = alive and answered_param and ack is not None and ack.result == 0
        landed = False
        if alive:
            ack = api.command(M.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
            end = time.monotonic() + 120
            while ack is not None and ack.result == 0 and time.monotonic() < end:
                hb = api.wait(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == AUTOPILOT, 5)
                if hb is not None and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED:
                    landed = True
                    break
        return FuzzResult(seed, packets, per_cat, fuzz_wall, api_watch.max_gap_s, gcs_watch.max_gap_s, max_dev,
                          rss0, rss1, n_expected, unanswered, answers, landed, alive, None, notes, sources, misrouted)
    finally:
        if srcs is not None:
            srcs.close()
        api.conn.close()
        gcs.conn.close()
        code, out = sitl.stop()
        if "Traceback" in out:
            notes.append("vehicle printed a traceback: " + out.strip().splitlines()[-1])
        if tmp is not None:
            tmp.cleanup()


# --------------------------------------------------------------------------------------------------- signing

KEY = bytes(range(32))
WRONG_KEY = bytes(range(1, 33))


class _Signer:
    """Frames of one sender (sysid, compid) signed with a key, a link id and a timestamp we choose."""

    def __init__(self, key: bytes | None, sysid: int = 255, compid: int = 190, link_id: int = 0):
        self.mav = M.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.link_id = link_id
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)

    def frame(self, msg, timestamp: int | None = None) -> bytes:
        if timestamp is not None:
            self.mav.signing.timestamp = timestamp
        buf = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf


def _request(command: int = M.MAV_CMD_REQUEST_MESSAGE):
    return M.MAVLink_command_long_message(VEHICLE_SYSID, AUTOPILOT, command, 0, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                          0, 0, 0, 0, 0, 0)


def _count_acks(sock, vehicle_addr, datagrams, command=M.MAV_CMD_REQUEST_MESSAGE, settle_s: float = 1.0,
                gap_s: float = 0.001) -> int:
    parser = M.MAVLink(None)
    parser.robust_parsing = True
    n = 0

    def read() -> bool:
        """Drain the socket; whether an ack of `command` (any result) came."""
        nonlocal n
        got = False
        while True:
            try:
                data, _ = sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return got
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "COMMAND_ACK" and m.command == command:
                    got = True
                    n += m.result == 0

    for d in datagrams:
        sock.sendto(d, vehicle_addr)
        read()
        time.sleep(gap_s)
    # settle until no ack has come for settle_s (a loaded machine answers late), at most 10 x that
    quiet_until, give_up = time.monotonic() + settle_s, time.monotonic() + 10 * settle_s
    while time.monotonic() < min(quiet_until, give_up):
        if read():
            quiet_until = time.monotonic() + settle_s
        time.sleep(0.01)
    return n


def _cross_link_replay(sitl, replays: int) -> dict:
    """A signed frame accepted on one link, copied to the other `replays` times: how many were accepted there."""
    socks = {}
    for link, port in (("api", sitl.api_port), ("gcs", sitl.gcs_port)):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", port))
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        s.setblocking(False)
        socks[link] = s
    out = {}
    try:
        good = _Signer(KEY, 255, 190)
        for src, dst in (("api", "gcs"), ("gcs", "api")):
            legit = good.frame(_request())
            out[f"{src}_original"] = _count_acks(socks[src], sitl.link_address(src), [legit])
            out[f"{src}_to_{dst}"] = _count_acks(socks[dst], sitl.link_address(dst), [legit] * replays)
        out["offered"] = replays
    finally:
        for s in socks.values():
            s.close()
    return out


def signing_check(count: int = 1000, replays: int = 100, speed: str = "max", strict_api: bool = False) -> dict:
    """Per link: accepted counts of unsigned, wrong-key, replayed, forged-timestamp and mixed-datagram frames."""
    key_hex = KEY.hex()
    args = ["--signing-key", key_hex] + (["--sign-api-strict"] if strict_api else [])
    with tempfile.TemporaryDirectory(prefix="fuzzsign_") as tmp:
        sitl = SitlProcess(Path(tmp), *args, speed=speed)
        results = {}
        try:
            for link, port in (("api", sitl.api_port), ("gcs", sitl.gcs_port)):
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                sock.bind(("127.0.0.1", port))
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
                sock.settimeout(10)
                _, addr = sock.recvfrom(65535)  # the vehicle's first packet tells its address
                sock.setblocking(False)
                good = _Signer(KEY, 255, 190)
                r = {}
                r["legit_before"] = _count_acks(sock, addr, [good.frame(_request()) for _ in range(20)])
                r["unsigned"] = _count_acks(sock, addr, [_Signer(None).frame(_request()) for _ in range(count)])
                bad = _Signer(WRONG_KEY, 255, 190)
                r["wrong_key"] = _count_acks(sock, addr, [bad.frame(_request()) for _ in range(count)])
                unsigned = _Signer(None, 255, 191)
                mixed = []
                for i in range(count // 2):
                    lead = b"\x00" if i % 2 == 0 else unsigned.frame(
                        M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
                    mixed.append(lead + bad.frame(_request()))
                r["wrong_key_after_junk_or_unsigned"] = _count_acks(sock, addr, mixed)
                legit = good.frame(_request())
                r["replay_original"] = _count_acks(sock, addr, [legit])
                r["replayed"] = _count_acks(sock, addr, [legit] * replays)
                far = int((time.time() - 1420070400 + 10 * 365 * 86400) * 1e5)
                forger = _Signer(WRONG_KEY, 255, 190, link_id=0)
                r["forged_timestamp"] = _count_acks(sock, addr, [forger.frame(_request(), timestamp=far + i) for i in range(100)])
                r["legit_after_forgery"] = _count_acks(sock, addr, [good.frame(_request()) for _ in range(20)])
                r["offered"] = dict(unsigned=count, wrong_key=count, mixed=count // 2, replayed=replays, forged=100, legit=20)
                sock.close()
                results[link] = r
            results["cross_link"] = _cross_link_replay(sitl, replays)
        finally:
            code, out = sitl.stop()
        results["strict_api"] = strict_api
        return results


# --------------------------------------------------------------------------------------------------- CLI


def _table(results: list[FuzzResult]) -> str:
    cats = list(results[0].per_category)
    lines = ["| seed | packets | " + " | ".join(cats) + " | max HB gap API / GCS (s) | max dev (m) | RSS growth (MiB)"
             " | cmds unanswered | answers | lands |",
             "|---" * (len(cats) + 8) + "|"]
    for r in results:
        lines.append(f"| {r.seed} | {r.packets} | " + " | ".join(str(r.per_category[c]) for c in cats)
                     + f" | {r.max_hb_gap_api_s:.2f} / {r.max_hb_gap_gcs_s:.2f} | {r.max_deviation_m:.2f} | "
                     f"{(r.rss_after_kib - r.rss_before_kib) / 1024:+.1f} | {r.commands_unanswered}/"
                     f"{r.commands_expecting_ack} | {'yes' if r.answers else 'NO'} | {'yes' if r.landed else 'NO'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--packets", type=int, default=10000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--speed", default="1", help="sitl --speed (default 1: real time, heartbeat gaps in wall seconds)")
    ap.add_argument("--rate", type=float, default=250.0, help="packets per wall second (default 250)")
    ap.add_argument("--categories", nargs="+", default=list(CATEGORIES), choices=CATEGORIES)
    ap.add_argument("--sources", type=int, default=1,
                    help="send the packets from N sockets (peers of the API link); every ACK must reach its asker")
    ap.add_argument("--signing", action="store_true", help="run the signing check instead")
    ap.add_argument("--count", type=int, default=1000, help="(--signing) frames per kind")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    a = ap.parse_args(argv)
    if a.signing:
        out = {"default": signing_check(a.count), "strict_api": signing_check(a.count, strict_api=True)}
        for mode, res in out.items():
            print(f"signing, {mode}: accepted of offered (COMMAND_ACK ACCEPTED received)")
            print("| link | unsigned | wrong key | wrong key after junk/unsigned | replayed | forged timestamp "
                  "| legit before / after forgery |")
            print("|---|---|---|---|---|---|---|")
            for link in ("api", "gcs"):
                r = res[link]
                o = r["offered"]
                print(f"| {link} | {r['unsigned']}/{o['unsigned']} | {r['wrong_key']}/{o['wrong_key']} | "
                      f"{r['wrong_key_after_junk_or_unsigned']}/{o['mixed']} | {r['replayed']}/{o['replayed']} | "
                      f"{r['forged_timestamp']}/{o['forged']} | {r['legit_before']}/{o['legit']} / "
                      f"{r['legit_after_forgery']}/{o['legit']} |")
            x = res["cross_link"]
            print(f"a signed frame accepted on one link, replayed on the other: API -> GCS "
                  f"{x['api_to_gcs']}/{x['offered']} (original {x['api_original']}/1), GCS -> API "
                  f"{x['gcs_to_api']}/{x['offered']} (original {x['gcs_original']}/1)")
        if a.json:
            a.json.write_text(json.dumps(out, indent=2) + "\n")
        return 0
    results = []
    for seed in a.seeds:
        r = fuzz_flight(seed, a.packets, a.speed, a.rate, categories=a.categories, sources=a.sources)
        results.append(r)
        print(f"seed {seed}: {'ok' if r.ok else 'FAILED'}; " + "; ".join(r.notes), flush=True)
    print(_table(results))
    if a.sources > 1:
        print(f"packets from {a.sources} sockets; COMMAND_ACKs at another socket than the asker's: "
              + ", ".join(f"seed {r.seed} {r.acks_misrouted}" for r in results))
    print(f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
    if a.json:
        a.json.write_text(json.dumps([asdict(r) for r in results], indent=2) + "\n")
    return 0 if all(r.ok for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())

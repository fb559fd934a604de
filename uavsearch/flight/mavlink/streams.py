"""Telemetry streams: which message goes out how often on each link, on simulation time.

PX4 sends each message at its own rate per link; clients change a rate with SET_MESSAGE_INTERVAL, read it
with GET_MESSAGE_INTERVAL, or ask for one message now with REQUEST_MESSAGE. Each message is built once per
tick and packed per link (own sequence numbers and signing). Nothing here blocks or advances time.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import Callable

from pymavlink.dialects.v20 import common as M

from ..commander import Result
from .links import Link, Peer

log = logging.getLogger(__name__)

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
    # The simulator's ground truth (as ArduPilot SITL sends it; PX4 SITL does not): off unless a client asks
    # with SET_MESSAGE_INTERVAL, e.g. to log estimator error against truth.
    M.MAVLINK_MSG_ID_SIM_STATE: 0.0,
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
EXTRA_HEARTBEAT = "camera_hb"  # a second component's 1 Hz heartbeat, scheduled with the streams
MAX_MESSAGE_ID = (1 << 24) - 1  # MAVLink 2 message ids are 24 bits
HEARTBEAT_MAX_INTERVAL_US = 1_000_000  # a link without a 1 Hz heartbeat looks like a dead vehicle


def message_id(value: float) -> int | None:
    """A command parameter that names a message: an integral id in MAVLink 2's range, else None.

    Parameters travel as floats; 0.5 or 1e-9 must not become HEARTBEAT's id 0 by truncation."""
    if not (math.isfinite(value) and value == int(value) and 0 <= value <= MAX_MESSAGE_ID):
        return None
    return int(value)


class Streams:
    """Per-link message intervals and the send schedule (to every destination of the link); answers the
    message-interval commands (a rate belongs to the link, as on PX4: every peer of it gets the new rate)."""

    def __init__(self, ep, links: list[Link], extra_heartbeat: Callable[[Link], None] | None = None):
        self.ep = ep
        self.links = links
        self.extra_heartbeat = extra_heartbeat  # the camera component's heartbeat, when there is a camera
        self._next_due_any = 0  # the earliest deadline over every link
        for link in links:
            link.default_rates_hz = link.cfg.rates_hz or DEFAULT_RATES_HZ
            link.intervals_us = {mid: int(1e6 / hz) if hz > 0 else 0 for mid, hz in link.default_rates_hz.items()}
            link.next_due_us = {mid: 0 for mid in link.intervals_us}
        self.commands = {
            M.MAV_CMD_SET_MESSAGE_INTERVAL: self._on_set_message_interval,
            M.MAV_CMD_GET_MESSAGE_INTERVAL: self._on_get_message_interval,
            M.MAV_CMD_REQUEST_MESSAGE: self._on_request_message,
            M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._on_request_autopilot_capabilities,
        }

    def send_due(self, now: int) -> None:
        """Every message whose interval has run out on a link (simulation time `now`, us)."""
        if now < self._next_due_any:
            return
        build_safe = self.ep.telemetry.build_safe
        built: dict = {}  # one message object per id and tick, packed per link (own sequence, signing)
        for link in self.links:
            if self.extra_heartbeat is not None and now >= link.next_due_us.get(EXTRA_HEARTBEAT, 0):
                link.next_due_us[EXTRA_HEARTBEAT] = now + 1_000_000
                self._extra_then_autopilot_heartbeat(link, now, built)
            for mid, interval in link.intervals_us.items():
                if interval <= 0 or now < link.next_due_us.get(mid, 0):
                    continue
                link.next_due_us[mid] = now + interval
                msg = built[mid] if mid in built else built.setdefault(mid, build_safe(mid))
                if msg is not None:
                    try:
                        link.send(msg)
                    except (struct.error, OverflowError, ValueError):  # a field out of its wire range
                        log.warning("cannot pack %s", msg.get_type(), exc_info=True)
                        built[mid] = None
        due = [t for link in self.links for mid, t in link.next_due_us.items()
               if mid == EXTRA_HEARTBEAT or link.intervals_us.get(mid, 0) > 0]
        self._next_due_any = min(due) if due else now + 1_000_000

    def _extra_then_autopilot_heartbeat(self, link: Link, now: int, built: dict) -> None:
        """The camera's heartbeat, followed by the autopilot's in the same datagram.

        pymavlink (so MAVProxy and pymavlink scripts) routes `set_mode(name)` by the autopilot type of the LAST
        heartbeat from the system, whichever component sent it: after the camera's (MAV_AUTOPILOT_INVALID) it
        takes the ArduPilot path and fails ("required argument is not a float"). A client parses a datagram at
        once, so it never acts between the two."""
        hb = M.MAVLINK_MSG_ID_HEARTBEAT
        link.flush()
        self.extra_heartbeat(link)
        msg = built[hb] if hb in built else built.setdefault(hb, self.ep.telemetry.build_safe(hb))
        if msg is not None:
            link.send(msg)
        if link.intervals_us.get(hb, 0) > 0:
            link.next_due_us[hb] = now + link.intervals_us[hb]

    # ------------------------------------------------------------------ commands
    def _on_set_message_interval(self, peer: Peer, m, command: int, p: list) -> None:
        self.ep.ack(peer, m, command, self._set_interval(peer.link, p))

    def _set_interval(self, link: Link, p) -> Result:
        """PX4's rules (param2: -1 off, 0 default rate, > 0 interval in us), except that HEARTBEAT is never off nor
        slower than 1 Hz; ids must be integral and streamable, intervals finite."""
        mid, iv = message_id(p[0]), p[1]
        if mid is None or not math.isfinite(iv) or (iv < 0 and iv != -1):
            return Result.DENIED
        if mid not in DEFAULT_RATES_HZ:
            return Result.UNSUPPORTED
        if mid == M.MAVLINK_MSG_ID_HEARTBEAT and (iv < 0 or iv > HEARTBEAT_MAX_INTERVAL_US):
            return Result.DENIED
        if iv == 0:
            hz = link.default_rates_hz.get(mid, 0.0)
            link.intervals_us[mid] = int(1e6 / hz) if hz > 0 else 0
        elif iv < 0:
            link.intervals_us[mid] = 0
        else:
            link.intervals_us[mid] = min(max(int(iv), 1000), 2**31 - 1)  # at most 1 kHz of simulation time
        link.next_due_us[mid] = 0
        self._next_due_any = 0
        return Result.ACCEPTED

    def _on_get_message_interval(self, peer: Peer, m, command: int, p: list) -> None:
        mid = message_id(p[0])
        if mid is None or mid > 0xFFFF:  # MESSAGE_INTERVAL carries the id in 16 bits
            return self.ep.ack(peer, m, command, Result.DENIED)
        iv = peer.link.intervals_us.get(mid)
        self.ep.ack(peer, m, command, Result.ACCEPTED)
        # MESSAGE_INTERVAL: -1 = not sent, 0 = not available here
        peer.send(M.MAVLink_message_interval_message(mid, 0 if iv is None else iv if iv > 0 else -1))

    def _on_request_message(self, peer: Peer, m, command: int, p: list) -> None:
        mid = message_id(p[0])
        if mid is None:
            return self.ep.ack(peer, m, command, Result.DENIED)
        msg = self.ep.telemetry.build(mid) if mid != M.MAVLINK_MSG_ID_HOME_POSITION or self.ep.cmd.home_set else None
        if msg is None:
            result = Result.TEMPORARILY_REJECTED if mid == M.MAVLINK_MSG_ID_HOME_POSITION else Result.UNSUPPORTED
            return self.ep.ack(peer, m, command, result)
        self.ep.ack(peer, m, command, Result.ACCEPTED)  # the ACK first, then the message (as PX4)
        peer.send(msg)

    def _on_request_autopilot_capabilities(self, peer: Peer, m, command: int, p: list) -> None:
        self.ep.ack(peer, m, command, Result.ACCEPTED)
        peer.send(self.ep.telemetry.autopilot_version())

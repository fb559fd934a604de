"""The mission protocol: upload, download, clear, set-current, with PX4's retries and ACK results.

An upload is a session with one partner (its address on its link, its sysid and compid): MISSION_COUNT,
then MISSION_REQUEST_INT / MISSION_ITEM_INT item by item, then MISSION_ACK, every message to that partner
alone. A lost item is requested again on the wall clock, and an upload whose partner stopped answering is
cancelled. One upload runs at a time (there is one mission): another partner's MISSION_COUNT or items
meanwhile get MISSION_ACK DENIED and a STATUSTEXT, and the running upload goes on. Downloads are stateless
and answer the asker. Only the plan (mission type 0) is stored; fences and rally points
are refused as PX4 refuses what it does not support.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as M

from ..mission import MAX_ITEMS, POSITIONED_COMMANDS, MissionItem
from .links import AUTOPILOT_COMPID, Peer

MISSION_RETRY_WALL_S = 0.25
MISSION_MAX_RETRIES = 8


@dataclass
class _Upload:
    peer: Peer  # where every message of the session goes
    partner: tuple[int, int]  # (sysid, compid) of the uploader
    count: int
    items: list = field(default_factory=list)
    last_request_wall: float = 0.0
    retries: int = 0
    mission_type: int = 0


def _invalid_field(m, x: float, y: float) -> int | None:
    """The MAV_MISSION_INVALID_* result for a field no command can use, else None.

    Infinity is never a value. NaN is "unused / default" (MAVSDK sends z = NaN for camera items), except in
    the position of a command that flies somewhere; x and y must fit MISSION_ITEM_INT's int32. The commander
    checks the rest (ranges, supported commands) when the upload is complete."""
    for v, err in ((m.param1, M.MAV_MISSION_INVALID_PARAM1), (m.param2, M.MAV_MISSION_INVALID_PARAM2),
                   (m.param3, M.MAV_MISSION_INVALID_PARAM3), (m.param4, M.MAV_MISSION_INVALID_PARAM4),
                   (m.z, M.MAV_MISSION_INVALID_PARAM7)):
        if math.isinf(v):
            return err
    positioned = m.command in POSITIONED_COMMANDS
    for v, err in ((x, M.MAV_MISSION_INVALID_PARAM5_X), (y, M.MAV_MISSION_INVALID_PARAM6_Y)):
        if math.isnan(v) and not positioned:
            continue
        if not (math.isfinite(v) and -2**31 <= v < 2**31):
            return err
    return None


def _int(v: float) -> int:
    return 0 if math.isnan(v) else int(round(v))


class MissionProtocol:
    """Serves the commander's mission to every link; one upload session at a time."""

    def __init__(self, ep):
        self.ep = ep
        self.upload: _Upload | None = None
        self.messages = {
            "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "MISSION_REQUEST_INT": lambda peer, m: self._send_item(peer, m, True),
            "MISSION_REQUEST": lambda peer, m: self._send_item(peer, m, False),
            "MISSION_COUNT": self._on_mission_count,
            "MISSION_ITEM_INT": lambda peer, m: self._receive_item(peer, m, m.x, m.y),
            "MISSION_ITEM": lambda peer, m: self._receive_item(peer, m, m.x * 1e7, m.y * 1e7),
            "MISSION_CLEAR_ALL": self._on_mission_clear_all,
            "MISSION_SET_CURRENT": self._on_mission_set_current,
            "MISSION_ACK": lambda peer, m: None,  # end of a download: nothing to release
        }

    def _addressed(self, m) -> bool:
        return self.ep.for_me(m.target_system) and m.target_component in (0, AUTOPILOT_COMPID)

    def _ack(self, peer: Peer, partner, result: int, mission_type: int = 0) -> None:
        peer.send(M.MAVLink_mission_ack_message(partner[0], partner[1], result, mission_type))

    def _item_message(self, it: MissionItem, partner, as_int: bool):
        current = int(it.seq == self.ep.cmd.mission.current_seq)
        if as_int:
            return M.MAVLink_mission_item_int_message(partner[0], partner[1], it.seq, it.frame, it.command, current,
                                                      it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                                                      it.x, it.y, it.z, 0)
        return M.MAVLink_mission_item_message(partner[0], partner[1], it.seq, it.frame, it.command, current,
                                              it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                                              it.x * 1e-7, it.y * 1e-7, it.z, 0)

    def _on_mission_request_list(self, peer: Peer, m) -> None:
        if not self._addressed(m):
            return
        mt = getattr(m, "mission_type", 0)
        n = len(self.ep.cmd.mission.items) if mt == M.MAV_MISSION_TYPE_MISSION else 0
        peer.send(M.MAVLink_mission_count_message(m.get_srcSystem(), m.get_srcComponent(), n, mt))

    def _send_item(self, peer: Peer, m, as_int: bool) -> None:
        if not self._addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        items = self.ep.cmd.mission.items
        if getattr(m, "mission_type", 0) != M.MAV_MISSION_TYPE_MISSION or not 0 <= m.seq < len(items):
            return self._ack(peer, partner, M.MAV_MISSION_INVALID_SEQUENCE, getattr(m, "mission_type", 0))
        peer.send(self._item_message(items[m.seq], partner, as_int))

    def _on_mission_count(self, peer: Peer, m) -> None:
        if not self._addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        mt = getattr(m, "mission_type", 0)
        if mt != M.MAV_MISSION_TYPE_MISSION:
            return self._ack(peer, partner, M.MAV_MISSION_UNSUPPORTED, mt)
        if m.count > MAX_ITEMS:
            return self._ack(peer, partner, M.MAV_MISSION_NO_SPACE)
        if self._busy_with_another(peer, partner):
            return
        if m.count == 0:
            self.upload = None
            self.ep.cmd.clear_mission()
            self._ack(peer, partner, M.MAV_MISSION_ACCEPTED)
            return self.ep.flush_events()
        self.upload = _Upload(peer, partner, m.count, [], self.ep.wall_s, 0, mt)  # the same partner may start over
        peer.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], 0, mt))

    def _receive_item(self, peer: Peer, m, x: float, y: float) -> None:
        """Every item addressed here gets an answer: the next request, or a MISSION_ACK saying what is wrong."""
        if not self._addressed(m):
            return
        up = self.upload
        partner = (m.get_srcSystem(), m.get_srcComponent())
        if up is None:
            return self._ack(peer, partner, M.MAV_MISSION_ERROR, getattr(m, "mission_type", 0))  # no upload running
        if self._busy_with_another(peer, partner):
            return
        expected = len(up.items)
        if m.seq != expected:  # a repeat or a gap: ask for the item we need
            peer.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], expected, up.mission_type))
            return
        bad = _invalid_field(m, x, y)
        if bad is not None:  # PX4 ends the transfer with the field's error
            self.upload = None
            return self._ack(peer, partner, bad, up.mission_type)
        up.items.append(MissionItem(m.seq, m.frame, m.command, m.current, m.autocontinue, m.param1, m.param2, m.param3,
                                    m.param4, _int(x), _int(y), float(m.z)))
        up.retries = 0
        up.last_request_wall = self.ep.wall_s
        if len(up.items) < up.count:
            peer.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], len(up.items), up.mission_type))
            return
        self.upload = None
        result, _reason = self.ep.cmd.upload_mission(up.items)
        self._ack(peer, partner, result)
        self.ep.flush_events()

    def _busy_with_another(self, peer: Peer, partner) -> bool:
        """True (and the asker refused) while an upload from another partner runs: that upload goes on."""
        up = self.upload
        if up is None or (up.peer.link is peer.link and up.peer.addr == peer.addr and up.partner == partner):
            return False
        self._ack(peer, partner, M.MAV_MISSION_DENIED, up.mission_type)
        self.ep.cmd.text(4, "mission upload busy with another client")
        self.ep.flush_events()
        return True

    def retry(self) -> None:
        """Ask again for the item the upload waits for, or cancel it after MISSION_MAX_RETRIES (wall clock)."""
        up = self.upload
        if up is None or self.ep.wall_s - up.last_request_wall < MISSION_RETRY_WALL_S:
            return
        if up.retries >= MISSION_MAX_RETRIES:
            self.upload = None
            return self._ack(up.peer, up.partner, M.MAV_MISSION_OPERATION_CANCELLED)
        up.retries += 1
        up.last_request_wall = self.ep.wall_s
        up.peer.send(M.MAVLink_mission_request_int_message(up.partner[0], up.partner[1], len(up.items),
                                                           up.mission_type))

    def _on_mission_clear_all(self, peer: Peer, m) -> None:
        if not self._addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        if getattr(m, "mission_type", 0) not in (M.MAV_MISSION_TYPE_MISSION, M.MAV_MISSION_TYPE_ALL):
            return self._ack(peer, partner, M.MAV_MISSION_ACCEPTED, m.mission_type)
        self.ep.cmd.clear_mission()
        self._ack(peer, partner, M.MAV_MISSION_ACCEPTED)
        self.ep.flush_events()

    def _on_mission_set_current(self, peer: Peer, m) -> None:
        if not self._addressed(m):
            return
        if not self.ep.cmd.set_mission_current(m.seq):
            self.ep.cmd.text(4, f"mission item {m.seq} does not exist")
        self.ep.flush_events()

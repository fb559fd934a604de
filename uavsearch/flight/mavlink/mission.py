"""The mission protocol: upload, download, clear, set-current, with PX4's retries and ACK results.

An upload is a small per-link state machine (MISSION_COUNT, then MISSION_REQUEST_INT / MISSION_ITEM_INT
item by item, then MISSION_ACK); a lost item is requested again on the wall clock, and an upload whose
client stopped answering is cancelled. Only the plan (mission type 0) is stored; fences and rally points
are refused as PX4 refuses what it does not support.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as M

from ..mission import MissionItem
from .links import AUTOPILOT_COMPID, Link

MISSION_RETRY_WALL_S = 0.25
MISSION_MAX_RETRIES = 8
MISSION_MAX_ITEMS = 500


@dataclass
class _Upload:
    partner: tuple[int, int]
    count: int
    items: list = field(default_factory=list)
    last_request_wall: float = 0.0
    retries: int = 0
    mission_type: int = 0


class MissionProtocol:
    """Serves the commander's mission to every link; one upload at a time per link."""

    def __init__(self, ep):
        self.ep = ep
        self.messages = {
            "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "MISSION_REQUEST_INT": lambda link, m: self._send_item(link, m, True),
            "MISSION_REQUEST": lambda link, m: self._send_item(link, m, False),
            "MISSION_COUNT": self._on_mission_count,
            "MISSION_ITEM_INT": lambda link, m: self._receive_item(link, m, m.x, m.y),
            "MISSION_ITEM": lambda link, m: self._receive_item(link, m, int(round(m.x * 1e7)), int(round(m.y * 1e7))),
            "MISSION_CLEAR_ALL": self._on_mission_clear_all,
            "MISSION_SET_CURRENT": self._on_mission_set_current,
            "MISSION_ACK": lambda link, m: None,  # end of a download: nothing to release
        }

    def _addressed(self, m) -> bool:
        return self.ep.for_me(m.target_system) and m.target_component in (0, AUTOPILOT_COMPID)

    def _ack(self, link: Link, partner, result: int, mission_type: int = 0) -> None:
        link.send(M.MAVLink_mission_ack_message(partner[0], partner[1], result, mission_type))

    def _item_message(self, it: MissionItem, partner, as_int: bool):
        current = int(it.seq == self.ep.cmd.mission.current_seq)
        if as_int:
            return M.MAVLink_mission_item_int_message(partner[0], partner[1], it.seq, it.frame, it.command, current,
                                                      it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                                                      it.x, it.y, it.z, 0)
        return M.MAVLink_mission_item_message(partner[0], partner[1], it.seq, it.frame, it.command, current,
                                              it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                                              it.x * 1e-7, it.y * 1e-7, it.z, 0)

    def _on_mission_request_list(self, link: Link, m) -> None:
        if not self._addressed(m):
            return
        mt = getattr(m, "mission_type", 0)
        n = len(self.ep.cmd.mission.items) if mt == M.MAV_MISSION_TYPE_MISSION else 0
        link.send(M.MAVLink_mission_count_message(m.get_srcSystem(), m.get_srcComponent(), n, mt))

    def _send_item(self, link: Link, m, as_int: bool) -> None:
        if not self._addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        items = self.ep.cmd.mission.items
        if getattr(m, "mission_type", 0) != M.MAV_MISSION_TYPE_MISSION or not 0 <= m.seq < len(items):
            return self._ack(link, partner, M.MAV_MISSION_INVALID_SEQUENCE, getattr(m, "mission_type", 0))
        link.send(self._item_message(items[m.seq], partner, as_int))

    def _on_mission_count(self, link: Link, m) -> None:
        if not self._addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        mt = getattr(m, "mission_type", 0)
        if mt != M.MAV_MISSION_TYPE_MISSION:
            return self._ack(link, partner, M.MAV_MISSION_UNSUPPORTED, mt)
        if m.count > MISSION_MAX_ITEMS:
            return self._ack(link, partner, M.MAV_MISSION_NO_SPACE)
        if m.count == 0:
            self.ep.cmd.clear_mission()
            self._ack(link, partner, M.MAV_MISSION_ACCEPTED)
            return self.ep.flush_events()
        link.upload = _Upload(partner, m.count, [], self.ep.wall_s, 0, mt)
        link.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], 0, mt))

    def _receive_item(self, link: Link, m, x: int, y: int) -> None:
        up = link.upload
        if up is None or not self._addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        if partner != up.partner:
            return self._ack(link, partner, M.MAV_MISSION_DENIED)
        expected = len(up.items)
        if m.seq != expected:
            if m.seq > expected:
                link.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], expected, up.mission_type))
            return
        up.items.append(MissionItem(m.seq, m.frame, m.command, m.current, m.autocontinue, m.param1, m.param2, m.param3,
                                    m.param4, int(x), int(y), float(m.z)))
        up.retries = 0
        up.last_request_wall = self.ep.wall_s
        if len(up.items) < up.count:
            link.send(M.MAVLink_mission_request_int_message(partner[0], partner[1], len(up.items), up.mission_type))
            return
        link.upload = None
        result, _reason = self.ep.cmd.upload_mission(up.items)
        self._ack(link, partner, result)
        self.ep.flush_events()

    def retry(self, link: Link) -> None:
        """Ask again for the item an upload waits for, or cancel it after MISSION_MAX_RETRIES (wall clock)."""
        up = link.upload
        if up is None or self.ep.wall_s - up.last_request_wall < MISSION_RETRY_WALL_S:
            return
        if up.retries >= MISSION_MAX_RETRIES:
            link.upload = None
            return self._ack(link, up.partner, M.MAV_MISSION_OPERATION_CANCELLED)
        up.retries += 1
        up.last_request_wall = self.ep.wall_s
        link.send(M.MAVLink_mission_request_int_message(up.partner[0], up.partner[1], len(up.items), up.mission_type))

    def _on_mission_clear_all(self, link: Link, m) -> None:
        if not self._addressed(m):
            return
        partner = (m.get_srcSystem(), m.get_srcComponent())
        if getattr(m, "mission_type", 0) not in (M.MAV_MISSION_TYPE_MISSION, M.MAV_MISSION_TYPE_ALL):
            return self._ack(link, partner, M.MAV_MISSION_ACCEPTED, m.mission_type)
        self.ep.cmd.clear_mission()
        self._ack(link, partner, M.MAV_MISSION_ACCEPTED)
        self.ep.flush_events()

    def _on_mission_set_current(self, link: Link, m) -> None:
        if not self._addressed(m):
            return
        if not self.ep.cmd.set_mission_current(m.seq):
            self.ep.cmd.text(4, f"mission item {m.seq} does not exist")
        self.ep.flush_events()

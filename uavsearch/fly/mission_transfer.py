"""The mission of one System: the MAVLink mission protocol (upload, download) and the mission's progress.

Upload: MISSION_COUNT -> MISSION_REQUEST_INT per item -> MISSION_ITEM_INT ... -> MISSION_ACK.
Download: MISSION_REQUEST_LIST -> MISSION_COUNT -> MISSION_REQUEST_INT per item -> MISSION_ACK.
Progress: MISSION_CURRENT (item, mission state) and MISSION_ITEM_REACHED.
"""

from __future__ import annotations

import time

from ..errors import MissionError
from ..flight.mission import MissionItem
from .dialect import AUTOPILOT_COMPID, M

MISSION_STATE_COMPLETE = 5


def _result_name(result: int) -> str:
    e = M.enums["MAV_MISSION_RESULT"].get(result)
    return e.name if e is not None else str(result)


class Mission:
    def __init__(self, system, compid: int = AUTOPILOT_COMPID):
        self.system, self.compid = system, compid
        self.current_seq: int | None = None
        self.mission_state: int | None = None
        self.reached: list[int] = []
        self._on_reached: list = []
        system.subscribe("MISSION_CURRENT", self._on_current)
        system.subscribe("MISSION_ITEM_REACHED", self._on_item_reached)

    def _on_current(self, m) -> None:
        self.current_seq, self.mission_state = int(m.seq), getattr(m, "mission_state", None)

    def _on_item_reached(self, m) -> None:
        self.reached.append(int(m.seq))
        for fn in tuple(self._on_reached):
            fn(int(m.seq))

    def on_reached(self, fn) -> None:
        """fn(seq) for each MISSION_ITEM_REACHED."""
        self._on_reached.append(fn)

    @property
    def complete(self) -> bool:
        return self.mission_state == MISSION_STATE_COMPLETE

    def _exchange(self, types: tuple, first, answer, timeout_s: float):
        """send first(), then answer(msg) each `types` frame until it returns non-None (returned); MissionError
        after timeout_s without a frame."""
        got: list = []
        s = self.system
        for t in types:
            s.subscribe(t, got.append)
        try:
            first()
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                s.pump(0.05)
                while got:
                    m = got.pop(0)
                    if getattr(m, "target_system", s.connection.source_system) not in (0, s.connection.source_system):
                        continue
                    end = time.monotonic() + timeout_s
                    r = answer(m)
                    if r is not None:
                        return r
            raise MissionError(f"mission transfer: no answer from the vehicle within {timeout_s:.0f} s")
        finally:
            for t in types:
                s.unsubscribe(t, got.append)

    def upload(self, items: list[MissionItem], timeout_s: float = 10.0) -> None:
        """Send the items; MissionError naming the vehicle's MAV_MISSION_RESULT if it refuses them."""
        s = self.system

        def answer(m):
            if m.get_type() == "MISSION_ACK":
                if m.type != M.MAV_MISSION_ACCEPTED:
                    texts = s.last_texts(1)
                    raise MissionError(f"the vehicle refused the mission: {_result_name(m.type)}"
                                       + (f" ({texts})" if texts else ""))
                return True
            if 0 <= m.seq < len(items):
                it = items[m.seq]
                s.mav.mission_item_int_send(s.sysid, self.compid, it.seq, it.frame, it.command, int(it.seq == 0),
                                            it.autocontinue, it.param1, it.param2, it.param3, it.param4, it.x, it.y,
                                            it.z, M.MAV_MISSION_TYPE_MISSION)
            return None

        self._exchange(("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"),
                       lambda: s.mav.mission_count_send(s.sysid, self.compid, len(items), M.MAV_MISSION_TYPE_MISSION),
                       answer, timeout_s)

    def download(self, timeout_s: float = 10.0) -> list[MissionItem]:
        """The vehicle's mission, item by item."""
        s = self.system
        items: list[MissionItem] = []
        count = [None]

        def request(seq):
            s.mav.mission_request_int_send(s.sysid, self.compid, seq, M.MAV_MISSION_TYPE_MISSION)

        def answer(m):
            if m.get_type() == "MISSION_COUNT":
                count[0] = int(m.count)
                if count[0] == 0:
                    return items
                request(0)
            elif m.get_type() == "MISSION_ITEM_INT" and count[0] is not None and m.seq == len(items):
                items.append(MissionItem(m.seq, m.frame, m.command, m.current, m.autocontinue, m.param1, m.param2,
                                         m.param3, m.param4, int(m.x), int(m.y), float(m.z)))
                if len(items) == count[0]:
                    s.mav.mission_ack_send(s.sysid, self.compid, M.MAV_MISSION_ACCEPTED, M.MAV_MISSION_TYPE_MISSION)
                    return items
                request(len(items))
            elif m.get_type() == "MISSION_ACK" and m.type != M.MAV_MISSION_ACCEPTED:
                raise MissionError(f"the vehicle refused the mission download: {_result_name(m.type)}")
            return None

        return self._exchange(("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK"),
                              lambda: s.mav.mission_request_list_send(s.sysid, self.compid, M.MAV_MISSION_TYPE_MISSION),
                              answer, timeout_s)


__all__ = ["MISSION_STATE_COMPLETE", "Mission"]

"""The parameter protocol (PARAM_REQUEST_LIST / _READ / PARAM_SET -> PARAM_VALUE) over the ParamStore.

Integers travel PX4's bytewise way: an int32 parameter is sent as the float with the same four bytes, which
is what MAVSDK and QGroundControl expect from a PX4 vehicle. A rejected set is answered with the value that
is stored, so the client sees what holds.
"""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as M

from ..params import ParamError, ParamStore
from .links import AUTOPILOT_COMPID, Peer

_INT_TYPES = (M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_UINT32, M.MAV_PARAM_TYPE_INT8, M.MAV_PARAM_TYPE_UINT8,
              M.MAV_PARAM_TYPE_INT16, M.MAV_PARAM_TYPE_UINT16)


def encode_param(value: float, is_int: bool) -> tuple[float, int]:
    """PX4 bytewise encoding: an int32 parameter travels as the float with the same four bytes."""
    if is_int:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0], M.MAV_PARAM_TYPE_INT32
    return float(value), M.MAV_PARAM_TYPE_REAL32


def decode_param(value: float, param_type: int, is_int: bool) -> float:
    if is_int and param_type in _INT_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", value))[0])
    return float(value)


def param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return raw.split("\0", 1)[0].strip()


class ParamProtocol:
    """Serves one ParamStore to every link; reads and lists answer the asker alone."""

    def __init__(self, ep, params: ParamStore):
        self.ep = ep
        self.params = params
        self.messages = {
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
        }

    def _addressed(self, m) -> bool:
        return self.ep.for_me(m.target_system) and m.target_component in (0, AUTOPILOT_COMPID)

    def _param_value(self, name: str):
        d = self.params.definition(name)
        val, ptype = encode_param(self.params[name], d.type == "int")
        return M.MAVLink_param_value_message(name.encode(), val, ptype, len(self.params), self.params.index(name))

    def _on_param_request_list(self, peer: Peer, m) -> None:
        if not self._addressed(m):
            return
        for name in self.params.names():
            peer.send(self._param_value(name))

    def _on_param_request_read(self, peer: Peer, m) -> None:
        if not self._addressed(m):
            return
        names = self.params.names()
        if m.param_index >= 0:
            if m.param_index < len(names):
                peer.send(self._param_value(names[m.param_index]))
            return
        name = param_name(m.param_id)
        if name in self.params:
            peer.send(self._param_value(name))
        else:
            self.ep.cmd.text(4, f"unknown parameter {name}")
            self.ep.flush_events()

    def _on_param_set(self, peer: Peer, m) -> None:
        if not self._addressed(m):
            return
        name = param_name(m.param_id)
        if name not in self.params:
            self.ep.cmd.text(4, f"unknown parameter {name}")
            return
        d = self.params.definition(name)
        try:
            self.params.set(name, decode_param(m.param_value, m.param_type, d.type == "int"))
        except ParamError as e:
            self.ep.cmd.text(4, str(e))
        # PX4 answers with the (possibly unchanged) value, so the client sees what is stored, and tells every
        # ground station of the change: every stream destination hears it, the asker in any case.
        msg = self._param_value(name)
        self.ep.broadcast(msg)
        if peer.addr not in peer.link.destinations():
            peer.send(msg)

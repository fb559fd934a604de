"""Parameters of one System: PARAM_REQUEST_READ / PARAM_SET, each answered by PARAM_VALUE."""

from __future__ import annotations


from ..flight.mavlink.params import decode_param
from .dialect import AUTOPILOT_COMPID, M


class Params:
    def __init__(self, system, compid: int = AUTOPILOT_COMPID):
        self.system, self.compid = system, compid

    @staticmethod
    def _value(m) -> float | int:
        """int32 parameters arrive bytewise in the float (PX4's encoding): an int comes back, as the vehicle keeps it."""
        is_int = m.param_type == M.MAV_PARAM_TYPE_INT32
        value = decode_param(m.param_value, m.param_type, is_int)
        return int(value) if is_int else value

    def get(self, name: str) -> float | int | None:
        """The parameter's value, None if the vehicle has none of that name."""
        s = self.system
        m = s.request("PARAM_VALUE", lambda: s.mav.param_request_read_send(s.sysid, self.compid, name.encode(), -1),
                      cond=lambda m: m.param_id == name)
        return None if m is None else self._value(m)

    def set_float(self, name: str, value: float, timeout_s: float = 3.0) -> bool:
        """PARAM_SET (REAL32); True when the vehicle's answer holds the value."""
        s = self.system
        m = s.request("PARAM_VALUE", lambda: s.mav.param_set_send(s.sysid, self.compid, name.encode(), float(value),
                                                                  M.MAV_PARAM_TYPE_REAL32),
                      cond=lambda m: m.param_id == name, timeout_s=timeout_s)
        return m is not None and abs(self._value(m) - value) < 1e-3 * max(1.0, abs(value))


__all__ = ["Params"]

"""The MAVLink dialect the client speaks: MAVLink 2, `common`, bound explicitly (never from MAVLINK20 in the
environment, which decides what `pymavlink.mavutil.mavlink` is), and the names it gives numbers."""

from __future__ import annotations

from pymavlink.dialects.v20 import common as M

AUTOPILOT_COMPID = 1
CAMERA_COMPID = 100


def command_name(command: int) -> str:
    """'MAV_CMD_NAV_TAKEOFF (22)', or the number alone for a command the dialect does not name."""
    e = M.enums["MAV_CMD"].get(command)
    return f"{e.name} ({command})" if e is not None else f"command {command}"


def result_name(result: int | None) -> str:
    if result is None:
        return "no COMMAND_ACK"
    e = M.enums["MAV_RESULT"].get(result)
    return e.name if e is not None else f"MAV_RESULT {result}"


__all__ = ["AUTOPILOT_COMPID", "CAMERA_COMPID", "M", "command_name", "result_name"]

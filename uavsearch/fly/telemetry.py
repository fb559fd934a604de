"""Telemetry and health of one System: what its autopilot reports (its estimate), never the simulator's truth."""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np

from ..flight.mavlink import wire_units as wire
from .dialect import AUTOPILOT_COMPID, M

class FlightMode(NamedTuple):
    """A PX4 custom mode (main, sub) as HEARTBEAT.custom_mode = sub << 24 | main << 16: equal to the plain tuple,
    printed as PX4's name (HOLD, LAND, ...), which `name` gives."""

    main: int
    sub: int

    @property
    def name(self) -> str:
        from ..flight.commander import PX4_MODES  # lazy: only when printed (fly's start imports no autopilot)

        return next((n for n, ms in PX4_MODES.items() if ms == tuple(self)), f"custom mode {self.main}.{self.sub}")

    def __str__(self) -> str:
        return self.name


# PX4 custom modes (main, sub) as HEARTBEAT.custom_mode = sub << 24 | main << 16.
MODE_HOLD = (4, 3)
MODE_TAKEOFF = (4, 2)
MODE_LAND = (4, 6)
MODE_RTL = (4, 5)
# SYS_STATUS sensor bits the autopilot must report present and healthy before we arm.
HEALTH_SENSORS = ((M.MAV_SYS_STATUS_SENSOR_3D_GYRO, "gyro"), (M.MAV_SYS_STATUS_SENSOR_3D_ACCEL, "accel"),
                  (M.MAV_SYS_STATUS_SENSOR_3D_MAG, "mag"), (M.MAV_SYS_STATUS_SENSOR_GPS, "GPS"))
HEALTH_BITS = 0
for _bit, _ in HEALTH_SENSORS:
    HEALTH_BITS |= _bit

# Telemetry the client reads, at the rates it needs (Hz); everything else the autopilot streams on our link
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


class Telemetry:
    """The last HEARTBEAT (mode, armed), GLOBAL_POSITION_INT, SYS_STATUS, EXTENDED_SYS_STATE of one system.

    `on_position(fn)`: fn(msg) on every position report, so a condition over the whole track (arrived and
    settled) judges each report, not only the last one when the caller looks."""

    def __init__(self, system):
        self.system = system
        self.heartbeat: dict | None = None  # main, sub, armed, t (wall clock)
        self.global_position = None
        self.sys_status = None
        self.extended_state = None
        self._position_listeners: list = []
        for t, fn in (("HEARTBEAT", self._on_heartbeat), ("GLOBAL_POSITION_INT", self._on_position),
                      ("SYS_STATUS", self._on_sys_status), ("EXTENDED_SYS_STATE", self._on_ext_state)):
            system.subscribe(t, fn)

    def _on_heartbeat(self, m) -> None:
        if m.get_srcComponent() == AUTOPILOT_COMPID and m.type != M.MAV_TYPE_GCS:
            self.heartbeat = {"main": (m.custom_mode >> 16) & 0xFF, "sub": (m.custom_mode >> 24) & 0xFF,
                              "armed": bool(m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED), "t": time.monotonic()}

    def _on_position(self, m) -> None:
        self.global_position = m
        for fn in tuple(self._position_listeners):
            fn(m)

    def _on_sys_status(self, m) -> None:
        self.sys_status = m

    def _on_ext_state(self, m) -> None:
        self.extended_state = m

    def on_position(self, fn) -> None:
        self._position_listeners.append(fn)

    def set_rates(self, rates_hz: dict | None = None) -> None:
        """SET_MESSAGE_INTERVAL for each message id (0 Hz: off)."""
        for mid, hz in (STREAM_RATES_HZ if rates_hz is None else rates_hz).items():
            self.system.commands.long(M.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 1e6 / hz if hz > 0 else -1)

    # ------------------------------------------------------------------ state
    @property
    def sim_time_s(self) -> float | None:
        """The vehicle's clock (time since boot) from its last position report."""
        g = self.global_position
        return None if g is None else wire.seconds(g.time_boot_ms)

    def mode(self) -> FlightMode | None:
        hb = self.heartbeat
        return FlightMode(hb["main"], hb["sub"]) if hb else None

    @property
    def armed(self) -> bool:
        return bool(self.heartbeat and self.heartbeat["armed"])

    def position_enu(self, origin) -> np.ndarray | None:
        """The reported position in the scene frame whose origin (home) is `origin`."""
        g = self.global_position
        return None if g is None else wire.position_enu(g, origin)

    def velocity_enu_m_s(self) -> np.ndarray | None:
        g = self.global_position
        return None if g is None else wire.velocity_enu_m_s(g)

    def altitude_amsl_m(self) -> float:
        g = self.global_position
        return math.nan if g is None else float(wire.lla(g)[2])

    def healthy(self) -> bool:
        """Gyro, accel, mag and GPS present and healthy, a position and a landed state received."""
        s = self.sys_status
        return (s is not None and self.global_position is not None and self.extended_state is not None
                and (s.onboard_control_sensors_present & HEALTH_BITS) == HEALTH_BITS
                and (s.onboard_control_sensors_health & HEALTH_BITS) == HEALTH_BITS)

    def missing_health(self) -> str:
        """What the health check still waits for, e.g. 'GPS, position'."""
        s, missing = self.sys_status, []
        if s is None:
            missing.append("SYS_STATUS")
        else:
            ok = s.onboard_control_sensors_present & s.onboard_control_sensors_health
            missing += [name for bit, name in HEALTH_SENSORS if not ok & bit]
        if self.global_position is None:
            missing.append("position")
        if self.extended_state is None:
            missing.append("landed state")
        return ", ".join(missing) or "nothing"


__all__ = ["HEALTH_BITS", "MODE_HOLD", "MODE_LAND", "MODE_RTL", "MODE_TAKEOFF", "STREAM_RATES_HZ", "Telemetry"]

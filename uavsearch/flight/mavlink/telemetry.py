"""Telemetry messages built from the vehicle's outputs: what a PX4 vehicle reports about itself.

Each builder turns one vehicle output (attitude, position, battery, ...) into one MAVLink message, in
simulation time. Outputs are read once per tick and shared by every message and link (`snapshot`).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from pymavlink.dialects.v20 import common as M

from ..quaternion import quat_from_euler

log = logging.getLogger(__name__)

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
PX4_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255  # reported as PX4 v1.15.0 (official release)


class Telemetry:
    """Builders of the vehicle's own messages; `build(msg_id)` is what streams and REQUEST_MESSAGE send."""

    def __init__(self, commander, rx_dropped):
        self.cmd = commander
        self.vehicle = commander.vehicle
        self._rx_dropped = rx_dropped  # () -> packets dropped on every link, for SYS_STATUS.errors_comm
        self._snap: dict = {}
        self._builders = {
            M.MAVLINK_MSG_ID_HEARTBEAT: self.heartbeat,
            M.MAVLINK_MSG_ID_SYS_STATUS: self.sys_status,
            M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self.extended_sys_state,
            M.MAVLINK_MSG_ID_ATTITUDE: self.attitude,
            M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self.attitude_quaternion,
            M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self.local_position,
            M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self.global_position,
            M.MAVLINK_MSG_ID_GPS_RAW_INT: self.gps_raw,
            M.MAVLINK_MSG_ID_VFR_HUD: self.vfr_hud,
            M.MAVLINK_MSG_ID_BATTERY_STATUS: self.battery_status,
            M.MAVLINK_MSG_ID_HOME_POSITION: self.home_position,
            M.MAVLINK_MSG_ID_MISSION_CURRENT: self.mission_current,
            M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: self.position_target,
            M.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.autopilot_version,
            M.MAVLINK_MSG_ID_SIM_STATE: self.sim_state,
        }

    def new_tick(self) -> None:
        """Forget the outputs read so far: the next builders read the vehicle afresh."""
        self._snap.clear()

    def time_boot_ms(self) -> int:
        return int(self.vehicle.time_us // 1000) & 0xFFFFFFFF

    def v(self, name: str):
        """A vehicle output, read once per tick."""
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

    def build(self, mid: int):
        f = self._builders.get(mid)
        return f() if f else None

    def build_safe(self, mid: int):
        """A telemetry message, or None when the state cannot be encoded (e.g. a NaN estimate)."""
        try:
            return self.build(mid)
        except (ValueError, OverflowError):
            log.warning("cannot build message %d", mid, exc_info=True)
            return None

    # ------------------------------------------------------------------ builders
    def heartbeat(self):
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.cmd.armed:
            base |= M.MAV_MODE_FLAG_SAFETY_ARMED
        if self.cmd.mode in ("TAKEOFF", "HOLD", "MISSION", "RTL", "LAND", "OFFBOARD"):
            base |= M.MAV_MODE_FLAG_AUTO_ENABLED | M.MAV_MODE_FLAG_GUIDED_ENABLED | M.MAV_MODE_FLAG_STABILIZE_ENABLED
        status = M.MAV_STATE_ACTIVE if self.cmd.armed else M.MAV_STATE_STANDBY
        return M.MAVLink_heartbeat_message(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, base, self.cmd.custom_mode, status, 3)

    def extended_sys_state(self):
        return M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_UNDEFINED, self.cmd.landed_state)

    def sys_status(self):
        h = self.v("sensor_health")
        present = ALWAYS_OK_BITS | M.MAV_SYS_STATUS_PREARM_CHECK
        health = ALWAYS_OK_BITS
        for name, bit in HEALTH_BITS.items():
            present |= bit
            if getattr(h, name):
                health |= bit
        if not self.cmd.arming_failures() or self.cmd.armed:
            health |= M.MAV_SYS_STATUS_PREARM_CHECK
        b = self.v("battery")
        return M.MAVLink_sys_status_message(
            present, present, health, 0, int(b.voltage_v * 1000), int(b.current_a * 100), int(round(b.remaining * 100)),
            0, min(self._rx_dropped(), 65535), 0, 0, 0, 0, 0, 0, 0,
        )

    def attitude(self):
        a = self.v("attitude")
        w0, x, y_, z = (float(q) for q in a.q_wxyz)
        r = math.atan2(2.0 * (w0 * x + y_ * z), 1.0 - 2.0 * (x * x + y_ * y_))
        p = math.asin(max(-1.0, min(1.0, 2.0 * (w0 * y_ - z * x))))
        y = math.atan2(2.0 * (w0 * z + x * y_), 1.0 - 2.0 * (y_ * y_ + z * z))
        w = a.angular_velocity_frd_rad_s
        return M.MAVLink_attitude_message(self.time_boot_ms(), r, p, y, float(w[0]), float(w[1]), float(w[2]))

    def attitude_quaternion(self):
        a = self.v("attitude")
        q = [float(x) for x in a.q_wxyz]
        w = a.angular_velocity_frd_rad_s
        return M.MAVLink_attitude_quaternion_message(self.time_boot_ms(), *q, float(w[0]), float(w[1]), float(w[2]),
                                                     [0.0] * 4)

    def local_position(self):
        lp = self.v("local_position")
        p, v = lp.position_ned_m, lp.velocity_ned_m_s
        return M.MAVLink_local_position_ned_message(self.time_boot_ms(), *(float(x) for x in p), *(float(x) for x in v))

    def global_position(self):
        gp = self.v("global_position")
        lp = self.v("local_position")
        v = lp.velocity_ned_m_s
        hdg = int(round(math.degrees(lp.heading_rad) % 360.0 * 100)) % 36000
        return M.MAVLink_global_position_int_message(
            self.time_boot_ms(), int(round(gp.lat_deg * 1e7)), int(round(gp.lon_deg * 1e7)), int(round(gp.alt_amsl_m * 1000)),
            int(round((gp.alt_amsl_m - self.cmd.home_alt_amsl_m) * 1000)), int(round(v[0] * 100)), int(round(v[1] * 100)),
            int(round(v[2] * 100)), hdg,
        )

    def sim_state(self):
        """The simulator's true state (JSBSim), for logs that compare the estimate with the truth."""
        t = self.v("true_state")
        lat, lon, alt = self.cmd.origin.enu_to_geodetic(t.position_enu_m)
        q = quat_from_euler(t.roll_rad, t.pitch_rad, t.yaw_rad)  # the vehicle's own: no scipy in its process
        ve, vn, vu = (float(x) for x in t.velocity_enu_m_s)
        w = t.angular_velocity_frd_rad_s
        return M.MAVLink_sim_state_message(
            *(float(x) for x in q), t.roll_rad, t.pitch_rad, t.yaw_rad, 0.0, 0.0, 0.0, float(w[0]), float(w[1]),
            float(w[2]), float(lat), float(lon), float(alt), 0.0, 0.0, vn, ve, -vu,
            int(round(lat * 1e7)), int(round(lon * 1e7)))

    def gps_raw(self):
        """The raw GPS solution (not the estimate), as a GPS receiver reports it."""
        fix = self.v("gps_fix")
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

    def vfr_hud(self):
        lp = self.v("local_position")
        v = lp.velocity_ned_m_s
        gs = float(np.hypot(v[0], v[1]))
        hdg = int(round(math.degrees(lp.heading_rad))) % 360
        thr = int(np.clip(getattr(self.vehicle, "thrust_setpoint", 0.0) * 100, 0, 100))
        return M.MAVLink_vfr_hud_message(gs, gs, hdg, thr, float(self.v("global_position").alt_amsl_m), float(-v[2]))

    def battery_status(self):
        b = self.v("battery")
        volts = [min(int(b.voltage_v * 1000), 65534)] + [65535] * 9
        return M.MAVLink_battery_status_message(
            0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, volts, int(b.current_a * 100),
            int(b.discharged_mah), -1, int(round(b.remaining * 100)),
        )

    def home_position(self):
        if not self.cmd.home_set:
            return None
        lla = self.cmd.home_lla()
        h = self.cmd.home_ned
        return M.MAVLink_home_position_message(
            int(round(lla[0] * 1e7)), int(round(lla[1] * 1e7)), int(round(lla[2] * 1000)), float(h[0]), float(h[1]),
            float(h[2]), [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(self.vehicle.time_us),
        )

    def mission_current(self):
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

    def position_target(self):
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
        return M.MAVLink_position_target_local_ned_message(self.time_boot_ms(), M.MAV_FRAME_LOCAL_NED, mask, *clean,
                                                           0.0, 0.0, 0.0, yaw, 0.0)

    def autopilot_version(self):
        caps = (
            M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
        )
        return M.MAVLink_autopilot_version_message(
            caps, PX4_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x5541565345415243, [0] * 18
        )

"""Client-side decoding of MAVLink wire units into SI units and the scene frame, in one place.

MAVLink packs positions as integers (degE7, mm), velocities in cm/s and times in ms, all in NED; the
flying client (fly/vehicle.py) and replay (replay/replay.py) read the same messages and must
decode them the same way. Frame conversions themselves stay in geometry.py (the one module that converts
frames); this module only undoes the wire scaling and hands over to it.
"""

from __future__ import annotations

import numpy as np

from ...geometry import GeodeticOrigin, euler_from_quaternion, ned_to_enu

DEG_E7 = 1e-7  # degE7 -> deg
MM = 1e-3  # mm -> m
CM_S = 0.01  # cm/s -> m/s
MS = 1e-3  # ms -> s


def lla_from_int(lat_e7: int, lon_e7: int, alt_mm: int) -> tuple[float, float, float]:
    """(lat_deg, lon_deg, alt_m) from the wire's (degE7, degE7, mm)."""
    return lat_e7 * DEG_E7, lon_e7 * DEG_E7, alt_mm * MM


def lla(msg) -> tuple[float, float, float]:
    """WGS84 position of a message with lat / lon / alt fields (GLOBAL_POSITION_INT, CAMERA_IMAGE_CAPTURED,
    GPS_RAW_INT); alt is AMSL."""
    return lla_from_int(msg.lat, msg.lon, msg.alt)


def home_lla(msg) -> tuple[float, float, float]:
    """WGS84 home of HOME_POSITION (latitude / longitude / altitude)."""
    return lla_from_int(msg.latitude, msg.longitude, msg.altitude)


def position_enu(msg, origin: GeodeticOrigin) -> np.ndarray:
    """The scene-frame (ENU m) position of a message with lat / lon / alt fields."""
    return origin.geodetic_to_enu(lla(msg))


def velocity_enu_m_s(msg) -> np.ndarray:
    """GLOBAL_POSITION_INT's ground velocity (vx, vy, vz: cm/s NED) in m/s ENU."""
    return ned_to_enu(np.array([msg.vx, msg.vy, msg.vz], dtype=float) * CM_S)


def rpy_rad(q_wxyz) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad of a MAVLink attitude quaternion [w, x, y, z] (body FRD in NED)."""
    return euler_from_quaternion(list(q_wxyz))


def seconds(time_boot_ms: int) -> float:
    return time_boot_ms * MS


def deg_to_e7(deg: float) -> int:
    """The wire's degE7 integer of an angle in degrees (COMMAND_INT x / y, MISSION_ITEM_INT)."""
    return int(round(deg * 1e7))

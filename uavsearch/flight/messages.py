"""Typed messages between the flight stack's blocks, named like PX4's uORB topics.

Conventions: `timestamp_us` first (simulation time), local frame NED about home, SI units in the
field names, NaN = axis not controlled. The flight log can record exactly these.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

NAN = math.nan


def _nan3() -> np.ndarray:
    return np.full(3, np.nan)


@dataclass(frozen=True)
class TrajectorySetpoint:
    """What the navigator asks of the position controller. NaN components are not controlled."""

    timestamp_us: int
    position_ned_m: np.ndarray = field(default_factory=_nan3)
    velocity_ned_m_s: np.ndarray = field(default_factory=_nan3)
    acceleration_ned_m_s2: np.ndarray = field(default_factory=_nan3)
    yaw_rad: float = NAN
    yawspeed_rad_s: float = NAN


@dataclass(frozen=True)
class VehicleLocalPosition:
    """The estimator's position and velocity in the local NED frame about home."""

    timestamp_us: int
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    heading_rad: float
    xy_valid: bool = True
    z_valid: bool = True
    eph_m: float = 0.0  # horizontal position accuracy (1 sigma)
    epv_m: float = 0.0


@dataclass(frozen=True)
class VehicleAttitude:
    """The estimator's attitude: quaternion [w, x, y, z] of body FRD -> NED, and body rates."""

    timestamp_us: int
    q_wxyz: np.ndarray
    angular_velocity_frd_rad_s: np.ndarray


@dataclass(frozen=True)
class VehicleGlobalPosition:
    timestamp_us: int
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_home_m: float


@dataclass(frozen=True)
class VehicleTrueState:
    """JSBSim's ground truth, scene ENU (for the camera renderer, logs and error measurement only)."""

    timestamp_us: int
    position_enu_m: np.ndarray
    velocity_enu_m_s: np.ndarray
    roll_rad: float
    pitch_rad: float
    yaw_rad: float  # NED heading, clockwise from north
    angular_velocity_frd_rad_s: np.ndarray


@dataclass(frozen=True)
class VehicleLandDetected:
    timestamp_us: int
    landed: bool
    ground_contact: bool


@dataclass(frozen=True)
class BatteryStatus:
    timestamp_us: int
    voltage_v: float
    current_a: float
    discharged_mah: float
    remaining: float  # 0..1


@dataclass(frozen=True)
class SensorHealth:
    """Which sensors are present and healthy (drives SYS_STATUS and the arming checks)."""

    gyro: bool = True
    accel: bool = True
    mag: bool = True
    baro: bool = True
    gps: bool = True

"""Sensor models: IMU, GPS, barometer and magnetometer readings made from JSBSim's true state.

Every reading draws its noise from one seeded numpy Generator (in blocks, so the per-step cost is an
index, not a call), which makes a flight a pure function of the seed. Errors follow the shapes that
matter to an estimator: white noise plus slowly wandering biases (random walk for the IMU,
first-order Gauss-Markov for GPS position and baro), so the EKF has something real to do.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..geometry import GeodeticOrigin
from .params import ParamDef

SENSOR_PARAMS: list[ParamDef] = [
    ParamDef("SIM_GYRO_NOISE", 0.003, 0.0, 1.0, "rad/s", description="gyro white noise per sample (1 sigma)"),
    ParamDef("SIM_GYRO_BIAS", 0.003, 0.0, 0.5, "rad/s", description="initial gyro bias (1 sigma per axis)"),
    ParamDef("SIM_ACC_NOISE", 0.08, 0.0, 10.0, "m/s^2", description="accelerometer white noise per sample"),
    ParamDef("SIM_ACC_BIAS", 0.05, 0.0, 2.0, "m/s^2", description="initial accelerometer bias (1 sigma per axis)"),
    ParamDef("SIM_GPS_NOISE_H", 0.5, 0.0, 50.0, "m", description="GPS horizontal white noise (1 sigma)"),
    ParamDef("SIM_GPS_NOISE_V", 0.8, 0.0, 50.0, "m", description="GPS vertical white noise (1 sigma)"),
    ParamDef("SIM_GPS_DRIFT", 0.2, 0.0, 50.0, "m", description="GPS slow position error (Gauss-Markov sigma)"),
    ParamDef("SIM_GPS_VNOISE", 0.1, 0.0, 5.0, "m/s", description="GPS velocity white noise (1 sigma)"),
    ParamDef("SIM_BARO_NOISE", 0.1, 0.0, 10.0, "m", description="barometer altitude white noise (1 sigma)"),
    ParamDef("SIM_MAG_NOISE", 0.005, 0.0, 1.0, "gauss", description="magnetometer white noise (1 sigma)"),
    ParamDef("SIM_GPS_BLOCK", 0, 0, 1, "", type="int", description="1: the GPS delivers nothing (failure test)"),
]

GPS_DRIFT_TAU_S = 60.0
BARO_DRIFT_SIGMA_M = 0.1
BARO_DRIFT_TAU_S = 120.0
GYRO_BIAS_RW = 2e-5  # rad/s per sqrt(s)
ACC_BIAS_RW = 5e-4  # m/s^2 per sqrt(s)
# Full-scale ranges of a flight controller's IMU (PX4's ICM-42688P / BMI088 settings: 2000 deg/s, 16 g): a
# reading past them saturates, as the real part's does. Only a tumbling crash reaches them; they keep a
# vehicle that hit the ground spinning from driving its estimator to overflow.
GYRO_RANGE_RAD_S = math.radians(2000.0)
ACCEL_RANGE_M_S2 = 16.0 * 9.80665


def _saturate(x: float, limit: float) -> float:
    return limit if x > limit else -limit if x < -limit else x
# Earth field about home (gauss, NED): horizontal 0.21, inclination 63 deg, declination taken as 0.
MAG_FIELD_NED_GAUSS = (0.21, 0.0, 0.42)


class GpsFix(NamedTuple):
    """One GPS solution, in the fields GPS_RAW_INT needs."""

    time_us: int
    fix_type: int  # 3 = 3D fix
    satellites_visible: int
    eph_m: float
    epv_m: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    position_ned_m: tuple
    velocity_ned_m_s: tuple

    @property
    def ground_speed_m_s(self) -> float:
        return math.hypot(self.velocity_ned_m_s[0], self.velocity_ned_m_s[1])

    @property
    def course_rad(self) -> float:
        return math.atan2(self.velocity_ned_m_s[1], self.velocity_ned_m_s[0]) % (2.0 * math.pi)


class ImuSample(NamedTuple):
    gyro_frd_rad_s: tuple
    accel_frd_m_s2: tuple


class _NormalStream:
    """Standard normals from a Generator, drawn a block at a time (same sequence for the same seed)."""

    def __init__(self, rng: np.random.Generator, block: int = 8192):
        self._rng = rng
        self._block = block
        self._buf = rng.standard_normal(block).tolist()
        self._i = 0

    def take(self, n: int) -> list:
        if self._i + n > self._block:
            self._buf = self._rng.standard_normal(self._block).tolist()
            self._i = 0
        i = self._i
        self._i = i + n
        return self._buf[i : i + n]


class SensorSuite:
    """Makes noisy readings from true state; the caller decides when each sensor samples."""

    def __init__(self, params, home: GeodeticOrigin, rng: np.random.Generator):
        self.params = params
        self.home = home
        self._n = _NormalStream(rng)
        n = self._n.take(6)
        self.gyro_bias = [params["SIM_GYRO_BIAS"] * v for v in n[:3]]
        self.accel_bias = [params["SIM_ACC_BIAS"] * v for v in n[3:]]
        n = self._n.take(4)
        drift = params["SIM_GPS_DRIFT"]
        self._gps_drift = [drift * n[0], drift * n[1], drift * n[2]]
        self._baro_drift = BARO_DRIFT_SIGMA_M * n[3]
        self.last_gps: GpsFix | None = None
        self.last_baro_alt_m = math.nan
        self.last_mag_gauss = (math.nan, math.nan, math.nan)
        self.last_imu: ImuSample | None = None
        self.configure(params)

    def imu(self, rates_frd, specific_force_frd, dt: float) -> ImuSample:
        """One gyro + accelerometer sample; `dt` is the time since the previous one (bias random walk)."""
        n0, n1, n2, n3, n4, n5, n6, n7, n8, n9, n10, n11 = self._n.take(12)
        sg, sa = self._imu_noise
        kg, ka = GYRO_BIAS_RW * math.sqrt(dt), ACC_BIAS_RW * math.sqrt(dt)
        bg, ba = self.gyro_bias, self.accel_bias
        bg[0] += kg * n6
        bg[1] += kg * n7
        bg[2] += kg * n8
        ba[0] += ka * n9
        ba[1] += ka * n10
        ba[2] += ka * n11
        g, a = GYRO_RANGE_RAD_S, ACCEL_RANGE_M_S2
        s = ImuSample(
            (_saturate(rates_frd[0] + bg[0] + sg * n0, g), _saturate(rates_frd[1] + bg[1] + sg * n1, g),
             _saturate(rates_frd[2] + bg[2] + sg * n2, g)),
            (
                _saturate(specific_force_frd[0] + ba[0] + sa * n3, a),
                _saturate(specific_force_frd[1] + ba[1] + sa * n4, a),
                _saturate(specific_force_frd[2] + ba[2] + sa * n5, a),
            ),
        )
        self.last_imu = s
        return s

    def configure(self, params) -> None:
        """Copy the per-sample noise levels (read at IMU rate; called again when a parameter changes)."""
        self._imu_noise = (params["SIM_GYRO_NOISE"], params["SIM_ACC_NOISE"])

    def gps(self, time_us: int, position_enu, velocity_ned, dt: float) -> GpsFix:
        """A 3D fix: true position + Gauss-Markov drift + white noise; `dt` since the previous fix."""
        p = self.params
        n = self._n.take(9)
        a = math.exp(-dt / GPS_DRIFT_TAU_S)
        b = p["SIM_GPS_DRIFT"] * math.sqrt(1.0 - a * a)
        d = self._gps_drift
        for i in range(3):
            d[i] = a * d[i] + b * n[i]
        sh, sv, svel = p["SIM_GPS_NOISE_H"], p["SIM_GPS_NOISE_V"], p["SIM_GPS_VNOISE"]
        pos_ned = (
            position_enu[1] + d[0] + sh * n[3],
            position_enu[0] + d[1] + sh * n[4],
            -position_enu[2] + d[2] + sv * n[5],
        )
        vel = (velocity_ned[0] + svel * n[6], velocity_ned[1] + svel * n[7], velocity_ned[2] + svel * n[8])
        lat, lon, alt = self.home.enu_to_geodetic(np.array([pos_ned[1], pos_ned[0], -pos_ned[2]])).tolist()
        fix = GpsFix(
            time_us,
            3,
            12,
            math.hypot(sh, p["SIM_GPS_DRIFT"]) * 1.2,
            math.hypot(sv, p["SIM_GPS_DRIFT"]) * 1.2,
            lat,
            lon,
            alt,
            pos_ned,
            vel,
        )
        self.last_gps = fix
        return fix

    def baro(self, altitude_enu_m: float, dt: float) -> float:
        """Pressure altitude AMSL in metres (white noise + slow drift)."""
        n = self._n.take(2)
        a = math.exp(-dt / BARO_DRIFT_TAU_S)
        self._baro_drift = a * self._baro_drift + BARO_DRIFT_SIGMA_M * math.sqrt(1.0 - a * a) * n[0]
        alt = self.home.alt_m + altitude_enu_m + self._baro_drift + self.params["SIM_BARO_NOISE"] * n[1]
        self.last_baro_alt_m = alt
        return alt

    def mag(self, roll: float, pitch: float, yaw: float) -> tuple:
        """Body-frame field in gauss: the NED Earth field rotated into the body, plus white noise."""
        n = self._n.take(3)
        s = self.params["SIM_MAG_NOISE"]
        mn, me, md = MAG_FIELD_NED_GAUSS
        cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
        # R^T (body from NED) applied to the field, ZYX Euler
        h1 = cy * mn + sy * me  # yaw removed
        h2 = -sy * mn + cy * me
        x = cp * h1 - sp * md
        z1 = sp * h1 + cp * md
        y = cr * h2 + sr * z1
        z = -sr * h2 + cr * z1
        m = (x + s * n[0], y + s * n[1], z + s * n[2])
        self.last_mag_gauss = m
        return m


def baro_pressure_pa(alt_amsl_m: float) -> float:
    """ISA pressure at an altitude (for SCALED_PRESSURE-style telemetry)."""
    return 101325.0 * (1.0 - 2.25577e-5 * alt_amsl_m) ** 5.25588

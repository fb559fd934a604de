"""The navigation filter: a 15-state error-state EKF fusing IMU, GPS, baro and magnetometer.

Why this shape: a multicopter's accelerometer does not see gravity's direction in flight (it reads the
thrust axis), so tilt is not measured directly; as in PX4's EKF2 it becomes observable through GPS
velocity, which an INS-style filter gets for free. The attitude lives in a nominal quaternion and the
filter carries only its small world-frame error (3 states), folded back after every update, so no
Euler singularity and small matrices.

State x (column vector): position NED (3), velocity NED (3), attitude error NED (3, zero
between updates), gyro bias FRD (3), accelerometer bias FRD (3). The IMU is the prediction input,
averaged over each filter period (delta angle / delta velocity, as EKF2 does).

The covariance algebra is filterpy's ExtendedKalmanFilter written out (`_Ekf`, the same operations in the
same order, so the same flights to the bit): importing filterpy imports scipy.stats for the likelihoods
this filter never asks for, 1.4 s of every vehicle's start, where its equations are ten lines.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import inv

from .params import ParamDef
from .quaternion import quat_from_euler, quat_from_rotvec, quat_multiply, quat_normalize, quat_to_euler, quat_to_matrix

EKF_PARAMS: list[ParamDef] = [
    ParamDef("EKF2_GYR_NOISE", 0.015, 0.0001, 0.1, "rad/s", description="gyro process noise"),
    ParamDef("EKF2_ACC_NOISE", 0.2, 0.01, 1.0, "m/s^2", description="accelerometer process noise"),
    ParamDef("EKF2_GYR_B_NOISE", 1e-4, 0.0, 0.01, "rad/s^2", description="gyro bias process noise"),
    ParamDef("EKF2_ACC_B_NOISE", 3e-3, 0.0, 0.01, "m/s^3", description="accelerometer bias process noise"),
    ParamDef("EKF2_GPS_P_NOISE", 1.5, 0.01, 10.0, "m", description="GPS position measurement noise"),
    ParamDef("EKF2_GPS_V_NOISE", 0.6, 0.01, 5.0, "m/s", description="GPS velocity measurement noise"),
    ParamDef("EKF2_BARO_NOISE", 0.3, 0.01, 15.0, "m", description="barometric height measurement noise"),
    ParamDef("EKF2_HEAD_NOISE", 0.1, 0.01, 1.0, "rad", description="magnetic heading measurement noise"),
]


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def mag_heading(mag_frd, roll: float, pitch: float) -> float:
    """Tilt-compensated magnetic heading (declination 0) from a body-frame field vector."""
    mx, my, mz = mag_frd
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    # undo roll then pitch: the field in the heading-only (yawed) frame
    y1 = cr * my - sr * mz
    z1 = sr * my + cr * mz
    x2 = cp * mx + sp * z1
    return -math.atan2(y1, x2)


class _Ekf:
    """filterpy's ExtendedKalmanFilter predict (the nominal state by `propagate`, then P = F P F' + Q) and
    update (gain through scipy's inverse, Joseph-form covariance), term for term."""

    def __init__(self, n: int, propagate):
        self.x = np.zeros((n, 1))
        self.P = np.eye(n)
        self.F = np.eye(n)
        self.Q = np.eye(n)
        self._I = np.eye(n)
        self._propagate = propagate

    def predict(self, u) -> None:
        self._propagate(*u)
        self.P = np.dot(self.F, self.P).dot(self.F.T) + self.Q

    def update(self, z, H, hx, R) -> None:
        """z (m, 1), H (m, n), hx(x) -> the measurement the state predicts, R (m, m)."""
        PHT = np.dot(self.P, H.T)
        K = PHT.dot(inv(np.dot(H, PHT) + R))
        self.x = self.x + np.dot(K, np.subtract(z, hx(self.x)))
        I_KH = self._I - np.dot(K, H)
        self.P = np.dot(I_KH, self.P).dot(I_KH.T) + np.dot(K, R).dot(K.T)


class NavigationEkf:
    """Error-state EKF. Call `initialize` once, then `predict` each period and the `fuse_*` as data comes."""

    N = 15

    def __init__(self, params, gravity_m_s2: float = 9.80665):
        self.params = params
        self.g = gravity_m_s2
        self.kf = _Ekf(self.N, self._propagate_nominal)
        self.q = (1.0, 0.0, 0.0, 0.0)  # nominal attitude, body FRD -> NED
        self.initialized = False
        self.kf.F = np.eye(self.N)
        self.kf.Q = np.zeros((self.N, self.N))
        self._dt_F = None
        self._H_gps = np.zeros((6, self.N))
        self._H_gps[:, :6] = np.eye(6)
        self._H_baro_head = np.zeros((2, self.N))
        self._H_baro_head[0, 2] = 1.0
        self._H_baro_head[1, 8] = 1.0
        self._H_all = np.vstack([self._H_gps, self._H_baro_head])
        self._set_q(self.q)
        self.configure(params)

    def configure(self, p) -> None:
        """Copy the noise parameters (called again whenever a parameter changes)."""
        self._q_noise = (p["EKF2_ACC_NOISE"], p["EKF2_GYR_NOISE"], p["EKF2_GYR_B_NOISE"], p["EKF2_ACC_B_NOISE"])
        sp, sv = p["EKF2_GPS_P_NOISE"], p["EKF2_GPS_V_NOISE"]
        self._R_gps = np.diag([sp * sp, sp * sp, (1.5 * sp) ** 2, sv * sv, sv * sv, (1.5 * sv) ** 2])
        self._R_baro_head = np.diag([p["EKF2_BARO_NOISE"] ** 2, p["EKF2_HEAD_NOISE"] ** 2])
        self._R_all = np.zeros((8, 8))
        self._R_all[:6, :6] = self._R_gps
        self._R_all[6:, 6:] = self._R_baro_head
        self._dt_F = None  # rebuild Q

    # ------------------------------------------------------------------ life cycle
    def initialize(self, position_ned, velocity_ned, accel_frd, mag_frd) -> None:
        """Level from the accelerometer (at rest it reads -g along body down), heading from the magnetometer."""
        ax, ay, az = accel_frd
        roll = math.atan2(-ay, -az)
        pitch = math.atan2(ax, math.hypot(ay, az))
        yaw = mag_heading(mag_frd, roll, pitch)
        self._set_q(quat_from_euler(roll, pitch, yaw))
        kf = self.kf
        kf.x = np.zeros((self.N, 1))
        kf.x[0:3, 0] = position_ned
        kf.x[3:6, 0] = velocity_ned
        kf.P = np.diag([1.0, 1.0, 1.0, 0.2, 0.2, 0.2, 0.03, 0.03, 0.1, 0.005, 0.005, 0.005, 0.1, 0.1, 0.1]) ** 2
        self.initialized = True

    def predict(self, gyro_frd, accel_frd, dt: float) -> None:
        """Propagate with IMU averages over dt (gyro rad/s, specific force m/s^2, both FRD)."""
        kf = self.kf
        if dt != self._dt_F:
            self._set_dt(dt)
        xl = kf.x[:, 0].tolist()  # as floats: the 3-vector work below is cheaper in Python than in numpy
        fx, fy, fz = accel_frd[0] - xl[12], accel_frd[1] - xl[13], accel_frd[2] - xl[14]
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._Rl
        ax = r00 * fx + r01 * fy + r02 * fz  # specific force in NED
        ay = r10 * fx + r11 * fy + r12 * fz
        az = r20 * fx + r21 * fy + r22 * fz
        F = kf.F
        F[3:6, 6:9] = ((0.0, az * dt, -ay * dt), (-az * dt, 0.0, ax * dt), (ay * dt, -ax * dt, 0.0))
        Rdt = self._R * -dt
        F[3:6, 12:15] = Rdt
        F[6:9, 9:12] = Rdt
        w = (gyro_frd[0] - xl[9], gyro_frd[1] - xl[10], gyro_frd[2] - xl[11])
        kf.predict((xl, w, (ax, ay, az + self.g), dt))  # the nominal state, then P = F P F' + Q

    def _set_dt(self, dt: float) -> None:
        kf = self.kf
        kf.F[0:3, 3:6] = np.eye(3) * dt
        qv, qa, qbg, qba = ((n * dt) ** 2 for n in self._q_noise)
        kf.Q = np.diag([0.0, 0.0, 0.0, qv, qv, qv, qa, qa, qa, qbg, qbg, qbg, qba, qba, qba])
        self._dt_F = dt

    def _propagate_nominal(self, xl, w, a_ned, dt: float) -> None:
        """Strapdown step: acceleration (NED, gravity added) into velocity and position, rate into attitude."""
        h = 0.5 * dt * dt
        self.kf.x[0:6, 0] = (
            xl[0] + xl[3] * dt + h * a_ned[0],
            xl[1] + xl[4] * dt + h * a_ned[1],
            xl[2] + xl[5] * dt + h * a_ned[2],
            xl[3] + a_ned[0] * dt,
            xl[4] + a_ned[1] * dt,
            xl[5] + a_ned[2] * dt,
        )
        # attitude: body-frame increment, right-multiplied
        self._set_q(quat_normalize(quat_multiply(self.q, quat_from_rotvec(w[0] * dt, w[1] * dt, w[2] * dt))))

    def _set_q(self, q) -> None:
        self.q = q
        self._R = quat_to_matrix(q)
        self._Rl = self._R.tolist()

    # ------------------------------------------------------------------ measurements
    def _fold_attitude_error(self) -> None:
        x = self.kf.x
        dq = quat_from_rotvec(x[6, 0], x[7, 0], x[8, 0])
        self._set_q(quat_normalize(quat_multiply(dq, self.q)))  # world-frame error: left-multiplied
        x[6:9, 0] = 0.0

    def fuse_gps(self, position_ned, velocity_ned) -> None:
        z = np.array([[*position_ned, *velocity_ned]], dtype=float).T
        H = self._H_gps
        self.kf.update(z, H, lambda x: x[0:6], self._R_gps)
        self._fold_attitude_error()

    def fuse_baro_heading(self, height_above_home_m: float, mag_frd) -> None:
        """Baro height and magnetic heading in one update (one instead of two)."""
        innov = self._heading_innovation(mag_frd)
        # the heading residual is taken on the circle: z carries it and Hx is the zero attitude error
        z = np.array([[-height_above_home_m], [innov]])
        H = self._H_baro_head
        self.kf.update(z, H, lambda x: np.array([[x[2, 0]], [x[8, 0]]]), self._R_baro_head)
        self._fold_attitude_error()

    def fuse_all(self, position_ned, velocity_ned, height_above_home_m: float, mag_frd) -> None:
        """GPS, baro and heading together: one 8-row update when they arrive at the same tick."""
        innov = self._heading_innovation(mag_frd)
        z = np.array([[*position_ned, *velocity_ned, -height_above_home_m, innov]], dtype=float).T
        H = self._H_all

        def hx(x):
            h = np.empty((8, 1))
            h[0:6] = x[0:6]
            h[6, 0] = x[2, 0]
            h[7, 0] = x[8, 0]
            return h

        self.kf.update(z, H, hx, self._R_all)
        self._fold_attitude_error()

    def _heading_innovation(self, mag_frd) -> float:
        roll, pitch, yaw = quat_to_euler(self.q)
        return _wrap(mag_heading(mag_frd, roll, pitch) - yaw)

    # ------------------------------------------------------------------ outputs
    @property
    def position_ned(self) -> np.ndarray:
        return self.kf.x[0:3, 0]

    @property
    def velocity_ned(self) -> np.ndarray:
        return self.kf.x[3:6, 0]

    @property
    def gyro_bias(self) -> np.ndarray:
        return self.kf.x[9:12, 0]

    @property
    def accel_bias(self) -> np.ndarray:
        return self.kf.x[12:15, 0]

    @property
    def position_std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.kf.P)[0:3])

    def euler(self) -> tuple:
        return quat_to_euler(self.q)

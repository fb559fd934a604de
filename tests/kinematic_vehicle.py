"""A kinematic stand-in with Multicopter's interface, for unit tests of the autopilot's mode logic ONLY.

Point mass with first-order velocity tracking and a ground at z = 0; no JSBSim, no noise. Every test of
MAVLink, MAVSDK or the runner flies the real `uavsearch.flight.multicopter.Multicopter`.
"""

from __future__ import annotations

import math

import numpy as np

from uavsearch.geometry import GeodeticOrigin, enu_to_ned, ned_to_enu, quaternion_from_euler
from uavsearch.flight.messages import (
    BatteryStatus,
    SensorHealth,
    TrajectorySetpoint,
    VehicleAttitude,
    VehicleGlobalPosition,
    VehicleLandDetected,
    VehicleLocalPosition,
    VehicleTrueState,
)


class KinematicVehicle:
    def __init__(self, params=None, home: GeodeticOrigin = GeodeticOrigin(), seed: int = 0, start_enu=(0, 0, 0),
                 start_yaw_rad=0.0, physics_hz: int = 100, ctrl_hz: int = 50):
        self.home = home
        self.physics_hz = physics_hz
        self.dt = 1.0 / physics_hz
        self.time_us = 0
        self.p = enu_to_ned(start_enu)
        self.v = np.zeros(3)
        self.yaw = start_yaw_rad
        self.armed = False
        self.sp = None
        self.sensor_health = SensorHealth()
        self.gps_fix = 3
        self.remaining = 1.0
        self._landed = True
        self._ground_s = 0.0

    def arm(self):
        self.armed = True

    def disarm(self):
        self.armed = False
        self.sp = None

    def set_setpoint(self, sp: TrajectorySetpoint):
        self.sp = sp

    def step(self):
        dt = self.dt
        v_des = np.zeros(3)
        if self.armed and self.sp is not None:
            for i in range(3):
                p_sp, v_sp = self.sp.position_ned_m[i], self.sp.velocity_ned_m_s[i]
                ff = v_sp if math.isfinite(v_sp) else 0.0
                v_des[i] = (1.5 * (p_sp - self.p[i]) + ff) if math.isfinite(p_sp) else ff
            v_des[:2] = np.clip(v_des[:2], -12, 12)
            v_des[2] = np.clip(v_des[2], -3, 2)
            if math.isfinite(self.sp.yaw_rad):
                self.yaw = self.sp.yaw_rad
            self.remaining = max(0.0, self.remaining - 1e-5 * dt)
        elif not self.armed:
            v_des[2] = 2.0
        self.v += np.clip((v_des - self.v) * 4.0 * dt, -8 * dt, 8 * dt)
        self.p += self.v * dt
        if self.p[2] >= 0.0:
            self.p[2] = 0.0
            self.v[2] = min(self.v[2], 0.0)
            if not self.armed:
                self.v[:] = 0.0
        on_ground = self.p[2] > -0.05 and abs(self.v[2]) < 0.3
        self._ground_s = self._ground_s + dt if on_ground else 0.0
        self._landed = self._ground_s > 0.3 or (on_ground and not self.armed)
        self.time_us += int(round(dt * 1e6))

    def run_for(self, seconds: float):
        for _ in range(int(round(seconds * self.physics_hz))):
            self.step()

    @property
    def local_position(self):
        return VehicleLocalPosition(self.time_us, self.p.copy(), self.v.copy(), self.yaw, True, True, 0.5, 0.3)

    @property
    def attitude(self):
        return VehicleAttitude(self.time_us, quaternion_from_euler(0.0, 0.0, self.yaw), np.zeros(3))

    @property
    def global_position(self):
        lla = self.home.enu_to_geodetic(ned_to_enu(self.p))
        return VehicleGlobalPosition(self.time_us, lla[0], lla[1], lla[2], -self.p[2])

    @property
    def true_state(self):
        return VehicleTrueState(self.time_us, ned_to_enu(self.p), ned_to_enu(self.v), 0.0, 0.0, self.yaw, np.zeros(3))

    @property
    def land_detected(self):
        return VehicleLandDetected(self.time_us, self._landed, self.p[2] > -0.05)

    @property
    def battery(self):
        return BatteryStatus(self.time_us, 16.8 * (0.8 + 0.2 * self.remaining), 10.0 if self.armed else 0.3,
                             (1 - self.remaining) * 5000, self.remaining)

"""Flight-quality scenarios measured in simulated time: climb, 10 m moves, hover hold, landing, EKF error.

Shared by tools/flight_step_response.py (table + PNG) and tests/test_flight_quality.py (bounds), so the
numbers in the report and the numbers the tests hold are the same computation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..geometry import GeodeticOrigin
from .quaternion import quat_to_euler
from .messages import TrajectorySetpoint
from .multicopter import MC_PARAMS, Multicopter
from .params import ParamStore

NAN = math.nan
SETTLE_POS_M = 0.5
SETTLE_SPEED_M_S = 0.3


@dataclass
class Trace:
    """Samples at the sample rate: time, true and estimated NED position/velocity, true attitude."""

    t: list = field(default_factory=list)
    true_pos: list = field(default_factory=list)
    true_vel: list = field(default_factory=list)
    est_pos: list = field(default_factory=list)
    est_vel: list = field(default_factory=list)
    att_err: list = field(default_factory=list)  # |estimated - true| roll, pitch, yaw (rad)
    sp_pos: list = field(default_factory=list)

    def arrays(self) -> dict:
        return {k: np.asarray(v, dtype=float) for k, v in self.__dict__.items()}


class Flight:
    """Drives a Multicopter through setpoints and records a trace (at `sample_hz`)."""

    def __init__(self, seed: int = 0, params: dict | None = None, sample_hz: int = 20, **vehicle_kw):
        self.params = ParamStore(MC_PARAMS)
        for k, v in (params or {}).items():
            self.params.set(k, v)
        self.vehicle = Multicopter(self.params, GeodeticOrigin(), seed=seed, **vehicle_kw)
        self.trace = Trace()
        self._every = self.vehicle.physics_hz // sample_hz
        self._sp = (NAN, NAN, NAN)

    def goto(self, n: float, e: float, d: float, yaw: float = 0.0) -> None:
        self._sp = (n, e, d)
        self.vehicle.set_setpoint(TrajectorySetpoint(self.vehicle.time_us, np.array([n, e, d]), yaw_rad=yaw))

    def descend(self, n: float, e: float, speed_m_s: float, yaw: float = 0.0) -> None:
        """Position hold in xy, constant descent speed in z (the landing setpoint)."""
        self._sp = (n, e, NAN)
        self.vehicle.set_setpoint(
            TrajectorySetpoint(
                self.vehicle.time_us, np.array([n, e, NAN]), np.array([NAN, NAN, speed_m_s]), yaw_rad=yaw
            )
        )

    def run(self, seconds: float, until=None) -> float:
        """Step for `seconds` (or until `until(vehicle)` is true); returns the simulated time spent."""
        v = self.vehicle
        t0 = v.time_us
        for i in range(int(round(seconds * v.physics_hz))):
            v.step()
            if i % self._every == 0:
                self._record()
                if until is not None and until(v):
                    break
        return (v.time_us - t0) / 1e6

    def _record(self) -> None:
        v, tr = self.vehicle, self.trace
        ts = v.true_state
        lp = v.local_position
        e, n, u = ts.position_enu_m
        ve, vn, vu = ts.velocity_enu_m_s
        tr.t.append(v.time_us / 1e6)
        tr.true_pos.append((n, e, -u))
        tr.true_vel.append((vn, ve, -vu))
        tr.est_pos.append(tuple(lp.position_ned_m))
        tr.est_vel.append(tuple(lp.velocity_ned_m_s))
        er, ep, ey = quat_to_euler(v.attitude.q_wxyz)
        dy = (ey - ts.yaw_rad + math.pi) % (2 * math.pi) - math.pi
        tr.att_err.append((er - ts.roll_rad, ep - ts.pitch_rad, dy))
        tr.sp_pos.append(self._sp)


def _settle_time(t, err_pos, speed, t0, pos_tol=SETTLE_POS_M, speed_tol=SETTLE_SPEED_M_S) -> float:
    """Time after t0 from which the error and speed stay within tolerance to the end of the window."""
    ok = (err_pos < pos_tol) & (speed < speed_tol)
    bad = np.nonzero(~ok)[0]
    if len(bad) == 0:
        return 0.0
    if bad[-1] == len(ok) - 1:
        return math.inf
    return float(t[bad[-1] + 1] - t0)


def mission_profile(seed: int = 0, params: dict | None = None, alt_m: float = 70.0, move_m: float = 10.0,
                    move_window_s: float = 15.0, hover_s: float = 30.0, **vehicle_kw) -> tuple[dict, Flight]:
    """Takeoff to alt_m, hover, four moves (N, E, S, W like the search's actions), descent and landing.

    Returns the measured numbers (all in simulated seconds / metres) and the flight with its trace.
    """
    f = Flight(seed, params, **vehicle_kw)
    v = f.vehicle
    res: dict = {}
    f.run(1.0)
    v.arm()
    # -- climb
    i0 = len(f.trace.t)
    t0 = v.time_us / 1e6
    f.goto(0.0, 0.0, -alt_m)
    f.run(alt_m / v.params["MPC_Z_VEL_MAX_UP"] + 15.0)
    a = f.trace.arrays()
    t, alt = a["t"][i0:], -a["true_pos"][i0:, 2]
    res["climb_time_to_90pct_s"] = float(t[np.argmax(alt >= 0.9 * alt_m)] - t0)
    res["climb_settle_s"] = _settle_time(t, np.abs(alt - alt_m), np.abs(a["true_vel"][i0:, 2]), t0)
    res["climb_overshoot_m"] = float(max(0.0, alt.max() - alt_m))
    # -- hover hold
    i0 = len(f.trace.t)
    f.run(hover_s)
    a = f.trace.arrays()
    herr = np.hypot(a["true_pos"][i0:, 0], a["true_pos"][i0:, 1])
    verr = np.abs(a["true_pos"][i0:, 2] + alt_m)
    res["hover_err_h_rms_m"] = float(np.sqrt(np.mean(herr**2)))
    res["hover_err_h_max_m"] = float(herr.max())
    res["hover_err_v_rms_m"] = float(np.sqrt(np.mean(verr**2)))
    herr_est = np.hypot(a["est_pos"][i0:, 0], a["est_pos"][i0:, 1])
    res["hover_err_h_rms_est_m"] = float(np.sqrt(np.mean(herr_est**2)))
    # -- four 10 m moves
    settle, overshoot, settle_est, overshoot_est = [], [], [], []
    pos = np.zeros(2)
    for d in ((1, 0), (0, 1), (-1, 0), (0, -1)):
        target = pos + move_m * np.array(d, dtype=float)
        i0 = len(f.trace.t)
        t0 = v.time_us / 1e6
        f.goto(target[0], target[1], -alt_m)
        f.run(move_window_s)
        a = f.trace.arrays()
        t = a["t"][i0:]
        p, vel = a["true_pos"][i0:, :2], a["true_vel"][i0:, :2]
        settle.append(_settle_time(t, np.linalg.norm(p - target, axis=1), np.linalg.norm(vel, axis=1), t0))
        pe, ve = a["est_pos"][i0:, :2], a["est_vel"][i0:, :2]
        settle_est.append(_settle_time(t, np.linalg.norm(pe - target, axis=1), np.linalg.norm(ve, axis=1), t0))
        along = (p - pos) @ np.array(d, dtype=float)
        overshoot.append(float(max(0.0, along.max() - move_m)))
        along_est = (pe - pos) @ np.array(d, dtype=float)
        overshoot_est.append(float(max(0.0, along_est.max() - move_m)))
        pos = target
    res["move_settle_s"] = settle
    res["move_settle_est_s"] = settle_est
    res["move_overshoot_m"] = overshoot
    res["move_overshoot_est_m"] = overshoot_est
    # -- descend at 3 m/s-ish (position), then land at MPC_LAND_SPEED
    f.goto(0.0, 0.0, -5.0)
    f.run(alt_m / v.params["MPC_Z_VEL_MAX_DN"] + 10.0)
    i0 = len(f.trace.t)
    t0 = v.time_us / 1e6
    f.descend(0.0, 0.0, v.params["MPC_LAND_SPEED"])
    f.run(30.0, until=lambda veh: veh.land_detected.landed)
    a = f.trace.arrays()
    res["land_detect_s"] = float(v.time_us / 1e6 - t0) if v.land_detected.landed else math.inf
    res["touchdown_speed_m_s"] = float(np.max(a["true_vel"][i0:, 2][-a["true_pos"][i0:, 2] < 0.5]))
    # -- estimation error over the whole flight
    a = f.trace.arrays()
    dp = a["est_pos"] - a["true_pos"]
    dh = np.hypot(dp[:, 0], dp[:, 1])
    res["ekf_pos_err_h_rms_m"] = float(np.sqrt(np.mean(dh**2)))
    res["ekf_pos_err_h_max_m"] = float(dh.max())
    res["ekf_pos_err_v_rms_m"] = float(np.sqrt(np.mean(dp[:, 2] ** 2)))
    res["ekf_pos_err_v_max_m"] = float(np.abs(dp[:, 2]).max())
    res["ekf_vel_err_rms_m_s"] = float(np.sqrt(np.mean(np.sum((a["est_vel"] - a["true_vel"]) ** 2, axis=1))))
    ae = np.degrees(a["att_err"])
    res["ekf_tilt_err_rms_deg"] = float(np.sqrt(np.mean(ae[:, 0] ** 2 + ae[:, 1] ** 2)))
    res["ekf_yaw_err_rms_deg"] = float(np.sqrt(np.mean(ae[:, 2] ** 2)))
    res["sim_time_s"] = v.time_us / 1e6
    res["battery_used_mah"] = v.battery.discharged_mah
    return res, f

"""Multicopter control cascade, PX4 style: position -> velocity -> attitude -> rate -> mixer.

Each stage is a pure core (`configure(params)`, `set_state`, `set_setpoint`, `update(dt)`) with no
JSBSim, bus or MAVLink inside, so it is unit-tested alone. Gains and limits carry PX4's parameter
names; `configure` copies them into attributes so the per-step cost is arithmetic on floats
(these loops run hundreds of times per simulated second).

Conventions: NED, FRD body, radians, SI. NaN in a setpoint component means "not controlled" and the
next lower derivative takes over (position NaN -> velocity given, both NaN -> hold still).
Normalised outputs follow PX4: collective thrust in [0, 1] of the maximum, torques in [-1, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .quaternion import quat_multiply
from .params import ParamDef

# Minimum / maximum are PX4's own (mc_pos_control, mc_att_control, mc_rate_control parameter metadata), so a
# value PX4 refuses is refused here too. Where PX4 gives no bound (the I gains and integrator limits have no
# maximum, the rate D gains of pitch and yaw none) ours is a sanity limit. One deviation: MC_YAWRATE_P's
# maximum is 3 (PX4: 0.6) because this airframe's default, 1.0, is above PX4's range.
CONTROL_PARAMS: list[ParamDef] = [
    # position / velocity (mc_pos_control)
    ParamDef("MPC_XY_P", 0.95, 0.0, 2.0, "1/s", description="horizontal position gain"),
    ParamDef("MPC_XY_VEL_P_ACC", 1.8, 1.2, 5.0, "1/s", description="horizontal velocity P gain"),
    ParamDef("MPC_XY_VEL_I_ACC", 0.4, 0.0, 60.0, "1/s^2", description="horizontal velocity I gain"),
    ParamDef("MPC_XY_VEL_D_ACC", 0.2, 0.1, 2.0, "", description="horizontal velocity D gain"),
    ParamDef("MPC_Z_P", 1.0, 0.0, 1.5, "1/s", description="vertical position gain"),
    ParamDef("MPC_Z_VEL_P_ACC", 4.0, 2.0, 15.0, "1/s", description="vertical velocity P gain"),
    ParamDef("MPC_Z_VEL_I_ACC", 2.0, 0.2, 3.0, "1/s^2", description="vertical velocity I gain"),
    ParamDef("MPC_Z_VEL_D_ACC", 0.0, 0.0, 2.0, "", description="vertical velocity D gain"),
    ParamDef("MPC_XY_CRUISE", 5.0, 0.5, 20.0, "m/s", description="horizontal speed in position (auto) control"),
    ParamDef("MPC_XY_VEL_MAX", 12.0, 0.5, 20.0, "m/s", description="hard horizontal speed limit"),
    ParamDef("MPC_Z_VEL_MAX_UP", 3.0, 0.5, 8.0, "m/s", description="climb speed limit"),
    ParamDef("MPC_Z_VEL_MAX_DN", 1.5, 0.5, 4.0, "m/s", description="descent speed limit"),
    ParamDef("MPC_ACC_HOR", 3.0, 0.5, 15.0, "m/s^2", description="horizontal acceleration of the velocity setpoint"),
    ParamDef("MPC_ACC_UP_MAX", 4.0, 0.5, 15.0, "m/s^2", description="upward acceleration of the velocity setpoint"),
    ParamDef("MPC_ACC_DOWN_MAX", 3.0, 0.5, 15.0, "m/s^2", description="downward acceleration of the velocity setpoint"),
    ParamDef("MPC_TILTMAX_AIR", 35.0, 10.0, 89.0, "deg", description="maximum tilt in flight"),
    ParamDef("MPC_THR_HOVER", 0.49, 0.1, 0.9, "", description="hover thrust (normalised)"),
    ParamDef("MPC_THR_MIN", 0.12, 0.05, 0.5, "", description="minimum collective thrust in flight"),
    ParamDef("MPC_THR_MAX", 1.0, 0.1, 1.0, "", description="maximum collective thrust"),
    ParamDef("MPC_LAND_SPEED", 0.7, 0.2, 2.0, "m/s", description="final landing descent speed"),
    ParamDef("MPC_LAND_ALT1", 10.0, 0.0, 122.0, "m", description="below: landing descent slows toward MPC_LAND_SPEED"),
    ParamDef("MPC_LAND_ALT2", 5.0, 0.0, 122.0, "m", description="below: landing descent at MPC_LAND_SPEED"),
    # attitude (mc_att_control)
    ParamDef("MC_ROLL_P", 6.5, 0.0, 12.0, "1/s", description="roll angle gain"),
    ParamDef("MC_PITCH_P", 6.5, 0.0, 12.0, "1/s", description="pitch angle gain"),
    ParamDef("MC_YAW_P", 2.0, 0.0, 5.0, "1/s", description="yaw angle gain"),
    ParamDef("MC_ROLLRATE_MAX", 220.0, 0.0, 1800.0, "deg/s", description="roll rate limit"),
    ParamDef("MC_PITCHRATE_MAX", 220.0, 0.0, 1800.0, "deg/s", description="pitch rate limit"),
    ParamDef("MC_YAWRATE_MAX", 120.0, 0.0, 1800.0, "deg/s", description="yaw rate limit"),
    # body rates (mc_rate_control)
    ParamDef("MC_ROLLRATE_P", 0.15, 0.01, 0.5, "", description="roll rate P gain"),
    ParamDef("MC_ROLLRATE_I", 0.2, 0.0, 2.0, "", description="roll rate I gain"),
    ParamDef("MC_ROLLRATE_D", 0.003, 0.0, 0.01, "", description="roll rate D gain"),
    ParamDef("MC_PITCHRATE_P", 0.15, 0.01, 0.6, "", description="pitch rate P gain"),
    ParamDef("MC_PITCHRATE_I", 0.2, 0.0, 2.0, "", description="pitch rate I gain"),
    ParamDef("MC_PITCHRATE_D", 0.003, 0.0, 0.05, "", description="pitch rate D gain"),
    ParamDef("MC_YAWRATE_P", 1.0, 0.0, 3.0, "", description="yaw rate P gain (this airframe's yaw authority is low)"),
    ParamDef("MC_YAWRATE_I", 0.3, 0.0, 2.0, "", description="yaw rate I gain"),
    ParamDef("MC_RR_INT_LIM", 0.3, 0.0, 1.0, "", description="roll rate integrator limit"),
    ParamDef("MC_PR_INT_LIM", 0.3, 0.0, 1.0, "", description="pitch rate integrator limit"),
    ParamDef("MC_YR_INT_LIM", 0.3, 0.0, 1.0, "", description="yaw rate integrator limit"),
]


def _finite(x: float) -> bool:
    return x == x and x not in (math.inf, -math.inf)


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else (hi if x > hi else x)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class AttitudeSetpoint:
    """What the position controller asks of the attitude controller (PX4 vehicle_attitude_setpoint)."""

    q_d: tuple  # [w, x, y, z] body FRD -> NED
    thrust: float  # normalised collective, 0..1
    yaw_rad: float
    yawspeed_ff_rad_s: float = 0.0


# ==================================================================================================
class PositionControl:
    """Position + velocity loops: setpoint shaping (speed, acceleration, braking), PID, tilt limit.

    A position setpoint is approached along a velocity setpoint that is capped by the cruise speed
    and by a braking curve, and slew-limited by the acceleration limits, so a jump of the target
    gives a smooth trapezoid instead of a tilt spike.
    """

    def __init__(self, gravity_m_s2: float = 9.80665):
        self.g = gravity_m_s2
        self.cruise_override_m_s: float | None = None
        self.pos = (0.0, 0.0, 0.0)
        self.vel = (0.0, 0.0, 0.0)
        self.yaw = 0.0
        self.sp_pos = (math.nan,) * 3
        self.sp_vel = (math.nan,) * 3
        self.sp_acc = (math.nan,) * 3
        self.sp_yaw = math.nan
        self.sp_yawspeed = math.nan
        self.set_setpoint(self.sp_pos, self.sp_vel, self.sp_acc, self.sp_yaw, self.sp_yawspeed)
        self.reset()

    def configure(self, p) -> None:
        self.xy_p, self.z_p = p["MPC_XY_P"], p["MPC_Z_P"]
        self.xy_kp, self.xy_ki, self.xy_kd = p["MPC_XY_VEL_P_ACC"], p["MPC_XY_VEL_I_ACC"], p["MPC_XY_VEL_D_ACC"]
        self.z_kp, self.z_ki, self.z_kd = p["MPC_Z_VEL_P_ACC"], p["MPC_Z_VEL_I_ACC"], p["MPC_Z_VEL_D_ACC"]
        self.cruise, self.vel_max = p["MPC_XY_CRUISE"], p["MPC_XY_VEL_MAX"]
        self.vz_up, self.vz_dn = p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"]
        self.acc_hor, self.acc_up, self.acc_dn = p["MPC_ACC_HOR"], p["MPC_ACC_UP_MAX"], p["MPC_ACC_DOWN_MAX"]
        self.tan_tilt = math.tan(math.radians(p["MPC_TILTMAX_AIR"]))
        self.thr_hover, self.thr_min, self.thr_max = p["MPC_THR_HOVER"], p["MPC_THR_MIN"], p["MPC_THR_MAX"]

    def reset(self, vel=(0.0, 0.0, 0.0)) -> None:
        """Forget integrators and the shaped setpoint (at takeoff, after landing)."""
        self.v_sp = list(vel)
        self.a_ff = [0.0, 0.0, 0.0]
        self.integ = [0.0, 0.0, 0.0]
        self.vel_prev = list(vel)
        self.dv_filt = [0.0, 0.0, 0.0]
        self.yaw_hold = math.nan
        self.thrust = 0.0
        self.ground_contact = False  # set by the land detector: stop pushing sideways against the ground
        self.maybe_landed = False  # ... and stop pushing at all

    def set_state(self, pos_ned, vel_ned, yaw: float) -> None:
        self.pos, self.vel, self.yaw = pos_ned, vel_ned, yaw

    def set_setpoint(self, pos_ned, vel_ned, acc_ned, yaw: float, yawspeed: float) -> None:
        self.sp_pos, self.sp_vel, self.sp_acc = pos_ned, vel_ned, acc_ned
        self.sp_yaw, self.sp_yawspeed = yaw, yawspeed
        # which axes are controlled, worked out once per setpoint rather than every update
        self._has_pos_xy = _finite(pos_ned[0]) and _finite(pos_ned[1])
        self._has_vel_xy = _finite(vel_ned[0]) and _finite(vel_ned[1])
        self._acc_ff = tuple(a if _finite(a) else 0.0 for a in acc_ned)

    # ------------------------------------------------------------------
    def _shape_xy(self, dt: float) -> None:
        px, py = self.sp_pos[0], self.sp_pos[1]
        vx, vy = self.sp_vel[0], self.sp_vel[1]
        if self._has_pos_xy:
            ex, ey = px - self.pos[0], py - self.pos[1]
            d = math.hypot(ex, ey)
            cruise = self.cruise_override_m_s or self.cruise
            # P law, capped by cruise speed and by the speed from which MPC_ACC_HOR/2 still stops in d
            vmax = min(cruise, math.sqrt(self.acc_hor * d))
            vx, vy = self.xy_p * ex, self.xy_p * ey
            n = math.hypot(vx, vy)
            if n > vmax:
                vx, vy = vx * vmax / n, vy * vmax / n
            if self._has_vel_xy:
                vx, vy = vx + self.sp_vel[0], vy + self.sp_vel[1]
        elif not self._has_vel_xy:
            vx = vy = 0.0
        n = math.hypot(vx, vy)
        if n > self.vel_max:
            vx, vy = vx * self.vel_max / n, vy * self.vel_max / n
        # slew limit (the acceleration the setpoint asks for)
        dx, dy = vx - self.v_sp[0], vy - self.v_sp[1]
        dn = math.hypot(dx, dy)
        lim = self.acc_hor * dt
        if dn > lim:
            dx, dy = dx * lim / dn, dy * lim / dn
        self.v_sp[0] += dx
        self.v_sp[1] += dy
        self.a_ff[0], self.a_ff[1] = dx / dt, dy / dt

    def _shape_z(self, dt: float) -> None:
        pz, vz = self.sp_pos[2], self.sp_vel[2]
        if pz == pz:  # not NaN (infinities are refused upstream)
            v = self.z_p * (pz - self.pos[2])
            if vz == vz:
                v += vz
        elif vz == vz:
            v = vz
        else:
            v = 0.0
        v = _clamp(v, -self.vz_up, self.vz_dn)
        dv = v - self.v_sp[2]
        # NED: negative dv = accelerating upwards
        dv = _clamp(dv, -self.acc_up * dt, self.acc_dn * dt)
        self.v_sp[2] += dv
        self.a_ff[2] = dv / dt

    def update(self, dt: float) -> AttitudeSetpoint:
        self._shape_xy(dt)
        self._shape_z(dt)
        acc = [0.0, 0.0, 0.0]
        for i in range(3):
            e = self.v_sp[i] - self.vel[i]
            kp, ki, kd = (self.z_kp, self.z_ki, self.z_kd) if i == 2 else (self.xy_kp, self.xy_ki, self.xy_kd)
            # derivative on the measurement, low-passed: the estimate's velocity is noisy at GPS rate
            dv = (self.vel[i] - self.vel_prev[i]) / dt
            self.vel_prev[i] = self.vel[i]
            self.dv_filt[i] += 0.3 * (dv - self.dv_filt[i])
            ff = self.a_ff[i] + self._acc_ff[i]
            acc[i] = kp * e + self.integ[i] - kd * self.dv_filt[i] + ff
        if self.ground_contact or self.maybe_landed:
            # PX4's landing thrust limit: level, integrators emptied, only the vertical push remains
            acc[0] = acc[1] = 0.0
            self.integ[0] = self.integ[1] = 0.0
            if self.maybe_landed:
                acc[2] = self.g  # -> minimum thrust
                self.integ[2] = 0.0
        # specific force the rotors must give: f = a - g (NED); thrust points along it
        fx, fy, fz = acc[0], acc[1], acc[2] - self.g
        # keep some upward thrust, then limit the tilt by shortening the horizontal part
        fz = min(fz, -self.g * self.thr_min / self.thr_hover)
        h = math.hypot(fx, fy)
        hmax = -fz * self.tan_tilt
        sat_xy = h > hmax
        if sat_xy:
            fx, fy = fx * hmax / h, fy * hmax / h
        fmax = self.g * self.thr_max / self.thr_hover
        sat_z = False
        if fz < -fmax:
            fz, fx, fy, sat_z = -fmax, 0.0, 0.0, True
        elif fx * fx + fy * fy + fz * fz > fmax * fmax:  # vertical first, horizontal gets what is left
            hmax2 = math.sqrt(fmax * fmax - fz * fz)
            h = math.hypot(fx, fy)
            fx, fy, sat_xy = fx * hmax2 / h, fy * hmax2 / h, True
        # integrators, frozen while saturated in the direction of the error (anti-windup)
        for i in range(3):
            e = self.v_sp[i] - self.vel[i]
            ki = self.z_ki if i == 2 else self.xy_ki
            if (i == 2 and sat_z and e < 0) or (i < 2 and (sat_xy or self.ground_contact)) or self.maybe_landed:
                continue
            self.integ[i] = _clamp(self.integ[i] + ki * e * dt, -self.g, self.g)
        f = math.sqrt(fx * fx + fy * fy + fz * fz)
        thrust = _clamp(f / self.g * self.thr_hover, self.thr_min, self.thr_max)
        self.thrust = thrust
        # yaw: follow the setpoint; NaN holds the heading at the moment it went NaN
        ysp, yrate = self.sp_yaw, self.sp_yawspeed
        if ysp == ysp:
            yaw_sp = ysp
            self.yaw_hold = math.nan
        else:
            if self.yaw_hold != self.yaw_hold:
                self.yaw_hold = self.yaw
            if yrate == yrate:
                self.yaw_hold = _wrap(self.yaw_hold + yrate * dt)
            yaw_sp = self.yaw_hold
        yawspeed_ff = yrate if yrate == yrate else 0.0
        return AttitudeSetpoint(attitude_from_thrust(fx / f, fy / f, fz / f, yaw_sp), thrust, yaw_sp, yawspeed_ff)


def attitude_from_thrust(zx: float, zy: float, zz: float, yaw: float) -> tuple:
    """Attitude [w, x, y, z] with the thrust (body -z) along the unit NED vector (zx, zy, zz) and heading `yaw`."""
    bz = (-zx, -zy, -zz)
    yc = (-math.sin(yaw), math.cos(yaw), 0.0)
    # x_b = y_c x z_b
    bx = (yc[1] * bz[2] - yc[2] * bz[1], yc[2] * bz[0] - yc[0] * bz[2], yc[0] * bz[1] - yc[1] * bz[0])
    n = math.sqrt(bx[0] ** 2 + bx[1] ** 2 + bx[2] ** 2)
    bx = (bx[0] / n, bx[1] / n, bx[2] / n)
    by = (bz[1] * bx[2] - bz[2] * bx[1], bz[2] * bx[0] - bz[0] * bx[2], bz[0] * bx[1] - bz[1] * bx[0])
    # rotation matrix columns bx, by, bz -> quaternion
    m00, m11, m22 = bx[0], by[1], bz[2]
    tr = m00 + m11 + m22
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        return (0.25 * s, (by[2] - bz[1]) / s, (bz[0] - bx[2]) / s, (bx[1] - by[0]) / s)
    if m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        return ((by[2] - bz[1]) / s, 0.25 * s, (by[0] + bx[1]) / s, (bz[0] + bx[2]) / s)
    if m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        return ((bz[0] - bx[2]) / s, (by[0] + bx[1]) / s, 0.25 * s, (bz[1] + by[2]) / s)
    s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
    return ((bx[1] - by[0]) / s, (bz[0] + bx[2]) / s, (bz[1] + by[2]) / s, 0.25 * s)


# ==================================================================================================
class AttitudeControl:
    """Quaternion attitude error -> body rate setpoint, tilt before heading (as PX4's mc_att_control).

    The desired attitude is split into the tilt that brings the thrust axis where it must be and the
    remaining rotation about it (heading); the heading part is scaled by MC_YAW_P / MC_ROLL_P, so a large
    heading change cannot drag the vehicle through a large tilt (a plain quaternion error would).
    """

    def __init__(self):
        self.q = (1.0, 0.0, 0.0, 0.0)
        self.q_d = (1.0, 0.0, 0.0, 0.0)
        self.yawspeed_ff = 0.0

    def configure(self, p) -> None:
        kr, kp, ky = p["MC_ROLL_P"], p["MC_PITCH_P"], p["MC_YAW_P"]
        self.yaw_w = min(1.0, max(0.0, ky / kr)) if kr > 0 else 1.0
        self.k = (kr, kp, kr)  # the heading error arrives pre-scaled by yaw_w
        self.rmax = tuple(math.radians(p[n]) for n in ("MC_ROLLRATE_MAX", "MC_PITCHRATE_MAX", "MC_YAWRATE_MAX"))

    def _reduced_setpoint(self) -> tuple:
        q, qd = self.q, self.q_d
        w, x, y, z = q
        dw, dx, dy, dz = qd
        # body z axes (third columns of the rotation matrices), in NED
        ez = (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))
        ezd = (2 * (dx * dz + dw * dy), 2 * (dy * dz - dw * dx), 1 - 2 * (dx * dx + dy * dy))
        c = ez[0] * ezd[0] + ez[1] * ezd[1] + ez[2] * ezd[2]
        if c < -0.99:  # thrust axis nearly reversed: no well-defined shortest tilt, use the full setpoint
            return qd
        cr = (ez[1] * ezd[2] - ez[2] * ezd[1], ez[2] * ezd[0] - ez[0] * ezd[2], ez[0] * ezd[1] - ez[1] * ezd[0])
        n = math.sqrt((1.0 + c) ** 2 + cr[0] ** 2 + cr[1] ** 2 + cr[2] ** 2)
        tilt = ((1.0 + c) / n, cr[0] / n, cr[1] / n, cr[2] / n)  # shortest rotation ez -> ezd, NED frame
        q_red = quat_multiply(tilt, q)  # current heading, desired thrust axis
        # what is left is a rotation about the body z axis: keep a yaw_w share of its angle
        mw, _, _, mz = quat_multiply((q_red[0], -q_red[1], -q_red[2], -q_red[3]), qd)
        if mw < 0.0:
            mw, mz = -mw, -mz
        half = self.yaw_w * math.atan2(mz, mw)
        return quat_multiply(q_red, (math.cos(half), 0.0, 0.0, math.sin(half)))

    def set_state(self, q) -> None:
        self.q = q

    def set_setpoint(self, q_d, yawspeed_ff: float = 0.0) -> None:
        self.q_d, self.yawspeed_ff = q_d, yawspeed_ff

    def update(self, dt: float = 0.0) -> tuple:
        w, x, y, z = self.q
        dw, dx, dy, dz = self._reduced_setpoint()
        # q_e = conj(q) * q_d: the rotation from the current to the desired attitude, in body axes
        ew = w * dw + x * dx + y * dy + z * dz
        ex = w * dx - x * dw - y * dz + z * dy
        ey = w * dy + x * dz - y * dw - z * dx
        ez = w * dz - x * dy + y * dx - z * dw
        if ew < 0.0:
            ex, ey, ez = -ex, -ey, -ez
        kr, kp, ky = self.k
        p, q, r = 2.0 * kr * ex, 2.0 * kp * ey, 2.0 * ky * ez
        ff = self.yawspeed_ff
        if ff:
            # the feedforward is about NED down; express it in body axes (third row of R)
            p += 2.0 * (x * z - w * y) * ff
            q += 2.0 * (y * z + w * x) * ff
            r += (1.0 - 2.0 * (x * x + y * y)) * ff
        mp, mq, mr = self.rmax
        return (
            -mp if p < -mp else (mp if p > mp else p),
            -mq if q < -mq else (mq if q > mq else q),
            -mr if r < -mr else (mr if r > mr else r),
        )


# ==================================================================================================
class RateControl:
    """Body-rate PID (derivative on the measurement) -> normalised torque in [-1, 1]."""

    def __init__(self):
        self.rates = (0.0, 0.0, 0.0)
        self.sp = (0.0, 0.0, 0.0)
        self.reset()

    def configure(self, p) -> None:
        self.kp = (p["MC_ROLLRATE_P"], p["MC_PITCHRATE_P"], p["MC_YAWRATE_P"])
        self.ki = (p["MC_ROLLRATE_I"], p["MC_PITCHRATE_I"], p["MC_YAWRATE_I"])
        self.kd = (p["MC_ROLLRATE_D"], p["MC_PITCHRATE_D"], 0.0)
        self.ilim = (p["MC_RR_INT_LIM"], p["MC_PR_INT_LIM"], p["MC_YR_INT_LIM"])

    def reset(self) -> None:
        self.integ = [0.0, 0.0, 0.0]
        self.prev = None

    def set_state(self, rates_frd) -> None:
        self.rates = rates_frd

    def set_setpoint(self, rates_sp) -> None:
        self.sp = rates_sp

    def update(self, dt: float, integrate: bool = True) -> tuple:
        rates, sp, integ = self.rates, self.sp, self.integ
        prev = self.prev or rates
        out = [0.0, 0.0, 0.0]
        for i in (0, 1, 2):
            e = sp[i] - rates[i]
            u = self.kp[i] * e + integ[i] - self.kd[i] * (rates[i] - prev[i]) / dt
            out[i] = -1.0 if u < -1.0 else (1.0 if u > 1.0 else u)
            if integrate:
                v, lim = integ[i] + self.ki[i] * e * dt, self.ilim[i]
                integ[i] = -lim if v < -lim else (lim if v > lim else v)
        self.prev = rates
        return out


# ==================================================================================================
class QuadXMixer:
    """Collective thrust + normalised torques -> four normalised rotor commands (PX4 quad-x order).

    Saturation: yaw gives way first, then the collective shifts so roll and pitch stay as asked
    (attitude matters more than altitude for a moment), then outputs clip to [idle, 1].
    """

    def __init__(self, rotors, idle: float = 0.05):
        # rotors: (sign of x forward, sign of y right, spin) per rotor
        self.roll = tuple(-0.5 * y for _, y, _ in rotors)
        self.pitch = tuple(0.5 * x for x, _, _ in rotors)
        self.yaw = tuple(0.5 * s for _, _, s in rotors)
        self.idle = idle

    def mix(self, thrust: float, torque) -> list:
        r, p, y = torque
        ro, pi, ya = self.roll, self.pitch, self.yaw
        lo, hi = self.idle, 1.0
        m = [thrust + r * ro[i] + p * pi[i] + y * ya[i] for i in (0, 1, 2, 3)]
        if max(m) > hi or min(m) < lo:
            rp = [r * ro[i] + p * pi[i] for i in (0, 1, 2, 3)]
            yw = [y * ya[i] for i in (0, 1, 2, 3)]
            # shrink yaw to what fits around the roll/pitch mix
            scale = 1.0
            for i in (0, 1, 2, 3):
                base = thrust + rp[i]
                if yw[i] > 0 and base + yw[i] > hi:
                    scale = min(scale, max(0.0, (hi - base) / yw[i]))
                elif yw[i] < 0 and base + yw[i] < lo:
                    scale = min(scale, max(0.0, (lo - base) / yw[i]))
            m = [thrust + rp[i] + scale * yw[i] for i in (0, 1, 2, 3)]
            top, bot = max(m), min(m)
            if top - bot <= hi - lo:  # fits after a shift of the collective
                shift = (hi - top) if top > hi else ((lo - bot) if bot < lo else 0.0)
                m = [v + shift for v in m]
            m = [lo if v < lo else (hi if v > hi else v) for v in m]
        return m

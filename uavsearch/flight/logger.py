"""The vehicle's on-board logger, as PX4's logger module: every flight writes `flight.ulg` (ULog, see ulog.py).

Inputs (read, never changed): the multicopter (estimator outputs, true state, IMU, GPS, motors, battery, land
detector), the commander (arming, mode), the navigator's goal, the parameter store (initial values and every
change) and the status texts the vehicle sends. Output: the ULog file, with PX4's topic names, field names and
types (from PX4's msg/*.msg), each topic at the interval PX4's default logging profile gives it, so Flight Review,
PlotJuggler and pyulog read it as a PX4 log. PX4 SITL's `*_groundtruth` topics (the flight dynamics' truth) come
at the intervals of the estimates they are the truth of.

`update()` runs once per physics step on simulation time (SimVehicle.tick); it checks each topic only when its
interval is due, and writes a sample only when the source published a new one (or, for state topics logged on
change, when the state changed or its keep-alive passed). It draws no random number and changes no state,
so a flight flies the same with and without its log.
"""

from __future__ import annotations

import math
import platform
import struct
import time

from .. import __version__
from .quaternion import quat_from_euler
from .ulog import MessageDef, ULogWriter

ULOG_NAME = "flight.ulg"
NAN = math.nan

# ------------------------------------------------------------------------------------------ PX4 messages
# Field lists as in PX4's msg/*.msg (constants left out); MessageDef applies the generator's ordering and padding.
VEHICLE_LOCAL_POSITION = """
uint64 timestamp
uint64 timestamp_sample
bool xy_valid
bool z_valid
bool v_xy_valid
bool v_z_valid
float32 x
float32 y
float32 z
float32[2] delta_xy
uint8 xy_reset_counter
float32 delta_z
uint8 z_reset_counter
float32 vx
float32 vy
float32 vz
float32 z_deriv
float32[2] delta_vxy
uint8 vxy_reset_counter
float32 delta_vz
uint8 vz_reset_counter
float32 ax
float32 ay
float32 az
float32 heading
float32 unaided_heading
float32 delta_heading
uint8 heading_reset_counter
bool heading_good_for_control
bool xy_global
bool z_global
uint64 ref_timestamp
float64 ref_lat
float64 ref_lon
float32 ref_alt
float32 dist_bottom
bool dist_bottom_valid
uint8 dist_bottom_sensor_bitfield
float32 eph
float32 epv
float32 evh
float32 evv
bool dead_reckoning
float32 vxy_max
float32 vz_max
float32 hagl_min
float32 hagl_max
"""

VEHICLE_GLOBAL_POSITION = """
uint64 timestamp
uint64 timestamp_sample
float64 lat
float64 lon
float32 alt
float32 alt_ellipsoid
bool lat_lon_valid
bool alt_valid
bool alt_ellipsoid_valid
float32 delta_alt
float32 delta_terrain
uint8 lat_lon_reset_counter
uint8 alt_reset_counter
uint8 terrain_reset_counter
float32 eph
float32 epv
float32 terrain_alt
bool terrain_alt_valid
bool dead_reckoning
"""

VEHICLE_ATTITUDE = """
uint64 timestamp
uint64 timestamp_sample
float32[4] q
float32[4] delta_q_reset
uint8 quat_reset_counter
"""

VEHICLE_STATUS = """
uint64 timestamp
uint64 armed_time
uint64 takeoff_time
uint8 arming_state
uint8 latest_arming_reason
uint8 latest_disarming_reason
uint64 nav_state_timestamp
uint8 nav_state_user_intention
uint8 nav_state
uint16 failure_detector_status
uint8 hil_state
uint8 vehicle_type
bool failsafe
bool failsafe_and_user_took_over
bool gcs_connection_lost
uint8 gcs_connection_lost_counter
bool high_latency_data_link_lost
bool is_vtol
bool is_vtol_tailsitter
bool in_transition_mode
bool in_transition_to_fw
uint8 system_type
uint8 system_id
uint8 component_id
bool safety_button_available
bool safety_off
bool power_input_valid
bool usb_connected
bool open_drone_id_system_present
bool open_drone_id_system_healthy
bool parachute_system_present
bool parachute_system_healthy
bool avoidance_system_required
bool avoidance_system_valid
bool rc_calibration_in_progress
bool calibration_enabled
bool pre_flight_checks_pass
"""

ACTUATOR_OUTPUTS = """
uint64 timestamp
uint8 noutputs
float32[16] output
"""

ACTUATOR_MOTORS = """
uint64 timestamp
uint64 timestamp_sample
uint16 reversible_flags
float32[12] control
"""

BATTERY_STATUS = """
uint64 timestamp
bool connected
float32 voltage_v
float32 voltage_filtered_v
float32 current_a
float32 current_filtered_a
float32 current_average_a
float32 discharged_mah
float32 remaining
float32 scale
float32 time_remaining_s
float32 temperature
uint8 cell_count
uint8 source
uint8 priority
uint16 capacity
uint16 cycle_count
uint16 average_time_to_empty
uint16 serial_number
uint16 manufacture_date
uint16 state_of_health
uint16 max_error
uint8 id
uint16 interface_error
float32[14] voltage_cell_v
float32 max_cell_voltage_delta
bool is_powering_off
bool is_required
uint16 faults
uint32 custom_faults
uint8 warning
uint8 mode
"""

SENSOR_COMBINED = """
uint64 timestamp
float32[3] gyro_rad
uint32 gyro_integral_dt
int32 accelerometer_timestamp_relative
float32[3] accelerometer_m_s2
uint32 accelerometer_integral_dt
uint8 accelerometer_clipping
uint8 gyro_clipping
uint8 accel_calibration_count
uint8 gyro_calibration_count
"""

SENSOR_GPS = """
uint64 timestamp
uint64 timestamp_sample
uint32 device_id
float64 latitude_deg
float64 longitude_deg
float64 altitude_msl_m
float64 altitude_ellipsoid_m
float32 s_variance_m_s
float32 c_variance_rad
uint8 fix_type
float32 eph
float32 epv
float32 hdop
float32 vdop
int32 noise_per_ms
uint16 automatic_gain_control
uint8 jamming_state
int32 jamming_indicator
uint8 spoofing_state
uint8 authentication_state
float32 vel_m_s
float32 vel_n_m_s
float32 vel_e_m_s
float32 vel_d_m_s
float32 cog_rad
bool vel_ned_valid
int32 timestamp_time_relative
uint64 time_utc_usec
uint8 satellites_used
uint32 system_error
float32 heading
float32 heading_offset
float32 heading_accuracy
float32 rtcm_injection_rate
uint8 selected_rtcm_instance
bool rtcm_crc_failed
uint8 rtcm_msg_used
uint8 quality_corrections
uint8 quality_receiver
uint8 quality_gnss_signals
uint8 quality_post_processing
"""

POSITION_SETPOINT = """
uint64 timestamp
bool valid
uint8 type
float32 vx
float32 vy
float32 vz
float64 lat
float64 lon
float32 alt
float32 yaw
float32 yawspeed
float32 loiter_radius
float32 loiter_minor_radius
bool loiter_direction_counter_clockwise
float32 loiter_orientation
uint8 loiter_pattern
float32 acceptance_radius
float32 cruising_speed
bool gliding_enabled
float32 cruising_throttle
"""

POSITION_SETPOINT_TRIPLET = """
uint64 timestamp
position_setpoint previous
position_setpoint current
position_setpoint next
"""

VEHICLE_LAND_DETECTED = """
uint64 timestamp
bool freefall
bool ground_contact
bool maybe_landed
bool landed
bool in_ground_effect
bool in_descend
bool has_low_throttle
bool vertical_movement
bool horizontal_movement
bool rotational_movement
bool close_to_ground_or_skipped_check
bool at_rest
"""

_POSITION_SETPOINT = MessageDef("position_setpoint", POSITION_SETPOINT)

# vehicle_status.nav_state (PX4's NAVIGATION_STATE_*) of each commander mode
NAV_STATE = {"POSCTL": 2, "MISSION": 3, "HOLD": 4, "RTL": 5, "OFFBOARD": 14, "TAKEOFF": 17, "LAND": 18}
# position_setpoint.type (SETPOINT_TYPE_*) of each mode's goal
SETPOINT_TYPE = {"TAKEOFF": 3, "LAND": 4, "HOLD": 2}
ARMING_STATE_DISARMED, ARMING_STATE_ARMED = 1, 2
VEHICLE_TYPE_ROTARY_WING = 1
MAV_TYPE_QUADROTOR = 2
# What the vehicle is, as PX4 keeps it in parameters (Flight Review and pyulog read the vehicle type from MAV_TYPE
# and the airframe from SYS_AUTOSTART: 4001 is PX4's generic quadrotor x): logged with the vehicle's own.
IDENTITY_PARAMS = {"MAV_TYPE": MAV_TYPE_QUADROTOR, "SYS_AUTOSTART": 4001}
PWM_DISARMED_US, PWM_MIN_US, PWM_MAX_US = 900.0, 1000.0, 2000.0


def _release(version: str) -> int:
    """ver_sw_release: major << 24 | minor << 16 | patch << 8 | 255 (a release)."""
    parts = [int(p) if p.isdigit() else 0 for p in (version.split(".") + ["0", "0"])[:3]]
    return (parts[0] & 0xFF) << 24 | (parts[1] & 0xFF) << 16 | (parts[2] & 0xFF) << 8 | 0xFF


class _Topic:
    """One logged topic: checked every `interval_us` of simulation time; written when `key()` changed (a new
    publication, or a new state), or when `keepalive_us` passed since the last sample."""

    __slots__ = ("mdef", "msg_id", "interval_us", "keepalive_us", "key", "values", "next_us", "last_key", "last_us")

    def __init__(self, name: str, fields: str, interval_ms: int, key, values,
                 keepalive_ms: int | None = None, nested: dict | None = None):
        self.mdef = MessageDef(name, fields, nested)
        self.msg_id = -1
        self.interval_us = interval_ms * 1000
        self.keepalive_us = None if keepalive_ms is None else keepalive_ms * 1000
        self.key, self.values = key, values
        self.next_us, self.last_key, self.last_us = 0, None, 0


class FlightLogger:
    """Writes one vehicle's flight.ulg. `sim` is its SimVehicle: .vehicle, .commander, .params, .cfg (home,
    instance), .sysid, .goal_enu(); `on_text(severity, text)` is to be called with every status text it sends."""

    def __init__(self, sim, path):
        self.sim = sim
        v = self.vehicle = sim.vehicle
        self.commander = sim.commander
        self.params = sim.params
        self.home = sim.cfg.home
        start_us = int(v.time_us)
        self.utc0_us = int(time.time() * 1e6) - start_us  # the UTC time of simulation time 0 (the GPS clock)
        self._armed_us = self._takeoff_us = 0
        self._mode, self._mode_us = None, start_us
        self._was_armed, self._was_landed = False, True
        self._truth_at = (-1, None)
        self.dropped, self.drop_reason = 0, None  # samples left out (a value its field cannot hold), and why
        w = self.writer = ULogWriter(path, start_us)
        self._info(w, sim)
        for name in self.params.names():
            w.parameter(name, self.params[name], self.params.definition(name).type == "int")
        for name, value in IDENTITY_PARAMS.items():
            if name not in self.params:
                w.parameter(name, value, True)
        self.topics = self._topics()
        for t in self.topics:
            w.format(t.mdef)
        for t in self.topics:
            t.msg_id = w.subscribe(t.mdef)
        w.flush()  # the definitions reach the file at once: a vehicle killed at start leaves a readable log
        self.params.on_change(self._param_changed)

    # ------------------------------------------------------------------ definitions
    def _info(self, w: ULogWriter, sim) -> None:
        w.info("sys_name", "uavsearch")
        w.info("ver_sw", __version__)
        w.info("ver_sw_release", _release(__version__), "uint32_t")
        w.info("ver_hw", "UAVSEARCH_SITL")
        w.info("sys_os_name", platform.system())
        w.info("sys_toolchain", platform.python_implementation())
        w.info("sys_toolchain_ver", platform.python_version())
        w.info("sys_uuid", f"uavsearch-sitl-{sim.cfg.instance}")
        w.info("sys_mav_type", MAV_TYPE_QUADROTOR)
        w.info("time_ref_utc", 0)  # the UTC offset of the local time, seconds (PX4 SDLOG_UTC_OFFSET)

    def _topics(self) -> list[_Topic]:
        v, c = self.vehicle, self.commander
        gt = "_groundtruth"
        return [
            _Topic("vehicle_local_position", VEHICLE_LOCAL_POSITION, 100, lambda: v.local_position.timestamp_us,
                   self._local_position),
            _Topic("vehicle_global_position", VEHICLE_GLOBAL_POSITION, 200,
                   lambda: v.global_position.timestamp_us, self._global_position),
            _Topic("vehicle_attitude", VEHICLE_ATTITUDE, 50, lambda: v.attitude.timestamp_us, self._attitude),
            _Topic("vehicle_status", VEHICLE_STATUS, 20, lambda: (c.armed, c.mode), self._status, keepalive_ms=500),
            _Topic("actuator_outputs", ACTUATOR_OUTPUTS, 100, lambda: v.time_us, self._outputs),
            _Topic("actuator_motors", ACTUATOR_MOTORS, 100, lambda: v.time_us, self._motors),
            _Topic("battery_status", BATTERY_STATUS, 200, lambda: v.time_us, self._battery),
            _Topic("sensor_combined", SENSOR_COMBINED, 0, lambda: v.sensors.last_imu, self._sensor_combined),
            _Topic("vehicle_gps_position", SENSOR_GPS, 100, lambda: (v.gps_fix.time_us, v.gps_fix.fix_type),
                   self._gps),
            _Topic("position_setpoint_triplet", POSITION_SETPOINT_TRIPLET, 200, self._goal_key, self._triplet,
                   nested={"position_setpoint": _POSITION_SETPOINT}),
            _Topic("vehicle_land_detected", VEHICLE_LAND_DETECTED, 20, self._land_key, self._land_detected,
                   keepalive_ms=1000),
            _Topic("vehicle_local_position" + gt, VEHICLE_LOCAL_POSITION, 100, lambda: v.time_us,
                   self._local_position_truth),
            _Topic("vehicle_attitude" + gt, VEHICLE_ATTITUDE, 50, lambda: v.time_us, self._attitude_truth),
            _Topic("vehicle_global_position" + gt, VEHICLE_GLOBAL_POSITION, 200, lambda: v.time_us,
                   self._global_position_truth),
        ]

    # ------------------------------------------------------------------ the calls the vehicle makes
    def update(self) -> None:
        """Log what is due at the vehicle's current simulation time."""
        w = self.writer
        if w.closed:
            return
        now = self.vehicle.time_us
        for t in self.topics:
            if now < t.next_us:
                continue
            t.next_us = now - now % t.interval_us + t.interval_us if t.interval_us else now + 1  # on its grid
            key = t.key()
            if key == t.last_key and (t.keepalive_us is None or now - t.last_us < t.keepalive_us):
                continue
            t.last_key, t.last_us = key, now
            try:
                w.data(t.msg_id, t.mdef.pack(t.values(now)))
            except (struct.error, ValueError, TypeError, KeyError) as e:  # a value the field cannot hold: the
                self.dropped += 1  # sample is left out and counted; the vehicle flies on
                self.drop_reason = self.drop_reason or f"{t.mdef.name}: {e}"
        w.maybe_flush()

    def on_text(self, severity: int, text: str) -> None:
        if not self.writer.closed:
            self.writer.log(severity, self.vehicle.time_us, text)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()

    @property
    def error(self) -> OSError | None:
        return self.writer.error

    def _param_changed(self, name: str, value) -> None:
        if not self.writer.closed:
            self.writer.parameter(name, value, self.params.definition(name).type == "int")

    # ------------------------------------------------------------------ topic values
    def _local_position(self, now: int) -> dict:
        lp = self.vehicle.local_position
        x, y, z = lp.position_ned_m.tolist()
        vx, vy, vz = lp.velocity_ned_m_s.tolist()
        h = self.home
        return {"timestamp": lp.timestamp_us, "timestamp_sample": lp.timestamp_us, "xy_valid": lp.xy_valid,
                "z_valid": lp.z_valid, "v_xy_valid": lp.xy_valid, "v_z_valid": lp.z_valid, "x": x, "y": y, "z": z,
                "vx": vx, "vy": vy, "vz": vz, "z_deriv": vz, "heading": lp.heading_rad,
                "unaided_heading": lp.heading_rad, "heading_good_for_control": True, "xy_global": True,
                "z_global": True, "ref_lat": h.lat_deg, "ref_lon": h.lon_deg, "ref_alt": h.alt_m, "dist_bottom": -z,
                "eph": lp.eph_m, "epv": lp.epv_m}

    def _truth(self, now: int):
        """(position ENU, velocity NED, roll-pitch-yaw) from the flight dynamics at `now`, read once for the
        truth topics due at the same step (straight from JSBSim's properties: `true_state` builds arrays)."""
        if self._truth_at[0] != now:
            f = self.vehicle.fdm
            self._truth_at = (now, (f.position_enu_m(), f.velocity_ned_m_s(), f.euler_rad()))
        return self._truth_at[1]

    def _local_position_truth(self, now: int) -> dict:
        (e, n, u), (vn, ve, vd), (_, _, yaw) = self._truth(now)
        h = self.home
        return {"timestamp": now, "timestamp_sample": now, "xy_valid": True, "z_valid": True, "v_xy_valid": True,
                "v_z_valid": True, "x": n, "y": e, "z": -u, "vx": vn, "vy": ve, "vz": vd, "z_deriv": vd,
                "heading": yaw, "unaided_heading": yaw, "heading_good_for_control": True,
                "xy_global": True, "z_global": True, "ref_lat": h.lat_deg, "ref_lon": h.lon_deg, "ref_alt": h.alt_m,
                "dist_bottom": u, "dist_bottom_valid": True}

    def _global_position(self, now: int) -> dict:
        gp, lp = self.vehicle.global_position, self.vehicle.local_position
        return {"timestamp": gp.timestamp_us, "timestamp_sample": gp.timestamp_us, "lat": gp.lat_deg,
                "lon": gp.lon_deg, "alt": gp.alt_amsl_m, "alt_ellipsoid": gp.alt_amsl_m,
                "lat_lon_valid": lp.xy_valid, "alt_valid": lp.z_valid, "eph": lp.eph_m, "epv": lp.epv_m,
                "terrain_alt": self.home.alt_m, "terrain_alt_valid": True}

    def _global_position_truth(self, now: int) -> dict:
        lat, lon, alt = self.home.enu_to_geodetic(self._truth(now)[0]).tolist()
        return {"timestamp": now, "timestamp_sample": now, "lat": lat, "lon": lon, "alt": alt, "alt_ellipsoid": alt,
                "lat_lon_valid": True, "alt_valid": True, "terrain_alt": self.home.alt_m, "terrain_alt_valid": True}

    def _attitude(self, now: int) -> dict:
        att = self.vehicle.attitude
        return {"timestamp": att.timestamp_us, "timestamp_sample": att.timestamp_us, "q": att.q_wxyz.tolist()}

    def _attitude_truth(self, now: int) -> dict:
        return {"timestamp": now, "timestamp_sample": now, "q": quat_from_euler(*self._truth(now)[2])}

    def _status(self, now: int) -> dict:
        c = self.commander
        armed = c.armed
        if armed and not self._was_armed:
            self._armed_us = now
        self._was_armed = armed
        if c.mode != self._mode:
            self._mode, self._mode_us = c.mode, now
        nav = NAV_STATE.get(c.mode, 0)
        return {"timestamp": now, "armed_time": self._armed_us if armed else 0,
                "takeoff_time": self._takeoff_us if armed else 0,
                "arming_state": ARMING_STATE_ARMED if armed else ARMING_STATE_DISARMED,
                "nav_state_timestamp": self._mode_us, "nav_state_user_intention": nav, "nav_state": nav,
                "vehicle_type": VEHICLE_TYPE_ROTARY_WING, "system_type": MAV_TYPE_QUADROTOR,
                "system_id": int(self.sim.sysid) & 0xFF, "component_id": 1, "safety_off": True,
                "power_input_valid": True, "pre_flight_checks_pass": True}

    def _motor_commands(self) -> list:
        return list(self.vehicle.motor_outputs)

    def _outputs(self, now: int) -> dict:
        u = self._motor_commands()
        armed = self.commander.armed
        out = [PWM_MIN_US + (PWM_MAX_US - PWM_MIN_US) * x if armed else PWM_DISARMED_US for x in u]
        return {"timestamp": now, "noutputs": len(out), "output": (out + [0.0] * 16)[:16]}

    def _motors(self, now: int) -> dict:
        u = self._motor_commands() if self.commander.armed else [NAN] * len(self._motor_commands())
        return {"timestamp": now, "timestamp_sample": now, "control": (u + [NAN] * 12)[:12]}

    def _battery(self, now: int) -> dict:
        b, p = self.vehicle.battery, self.params
        n = int(p["BAT1_N_CELLS"])
        rem = b.remaining
        warning = 3 if rem < p["BAT_EMERGEN_THR"] else 2 if rem < p["BAT_CRIT_THR"] else 1 if rem < p["BAT_LOW_THR"] else 0
        return {"timestamp": now, "connected": True, "voltage_v": b.voltage_v, "voltage_filtered_v": b.voltage_v,
                "current_a": b.current_a, "current_filtered_a": b.current_a, "current_average_a": b.current_a,
                "discharged_mah": b.discharged_mah, "remaining": rem, "scale": 1.0, "time_remaining_s": NAN,
                "temperature": NAN, "cell_count": n, "capacity": min(int(p["BAT1_CAPACITY"]), 0xFFFF), "id": 1,
                "state_of_health": 100, "voltage_cell_v": ([b.voltage_v / n] * n + [0.0] * 14)[:14],
                "warning": warning}

    def _sensor_combined(self, now: int) -> dict:
        v = self.vehicle
        imu = v.sensors.last_imu
        div = v.physics_hz // v.ctrl_hz  # the IMU sampled at the last control step, the one before `now` or earlier
        sampled_us = max(v.step_count - 1, 0) // div * div * 1_000_000 // v.physics_hz
        dt = 1_000_000 // v.ctrl_hz
        return {"timestamp": sampled_us, "gyro_rad": imu.gyro_frd_rad_s, "gyro_integral_dt": dt,
                "accelerometer_m_s2": imu.accel_frd_m_s2, "accelerometer_integral_dt": dt}

    def _gps(self, now: int) -> dict:
        f = self.vehicle.gps_fix
        vn, ve, vd = f.velocity_ned_m_s
        return {"timestamp": f.time_us, "timestamp_sample": f.time_us, "latitude_deg": f.lat_deg,
                "longitude_deg": f.lon_deg, "altitude_msl_m": f.alt_amsl_m, "altitude_ellipsoid_m": f.alt_amsl_m,
                "fix_type": f.fix_type, "eph": f.eph_m, "epv": f.epv_m, "vel_m_s": f.ground_speed_m_s,
                "vel_n_m_s": vn, "vel_e_m_s": ve, "vel_d_m_s": vd, "cog_rad": math.remainder(f.course_rad, 2 * math.pi),
                "vel_ned_valid": f.fix_type >= 3, "time_utc_usec": self.utc0_us + f.time_us,
                "satellites_used": f.satellites_visible, "heading": NAN, "heading_offset": NAN}

    def _goal_key(self):
        g = self.sim.goal_enu()
        return self.commander.mode, None if g is None else tuple(g.tolist())

    def _triplet(self, now: int) -> dict:
        mode, goal = self._goal_key()
        current = {"timestamp": now, "valid": False}
        if goal is not None:
            lat, lon, alt = self.home.enu_to_geodetic(goal).tolist()
            current.update(valid=True, type=SETPOINT_TYPE.get(mode, 0), lat=lat, lon=lon, alt=alt, yaw=NAN,
                           yawspeed=NAN, acceptance_radius=self.params["NAV_ACC_RAD"],
                           cruising_speed=self.params["MPC_XY_CRUISE"], cruising_throttle=NAN)
        return {"timestamp": now, "current": current}

    def _land_key(self):
        ld = self.vehicle.land_detected
        return ld.landed, ld.ground_contact, self.vehicle.land_detector.maybe_landed

    def _land_detected(self, now: int) -> dict:
        landed, contact, maybe = self._land_key()
        if self._was_landed and not landed:
            self._takeoff_us = now
        self._was_landed = landed
        return {"timestamp": now, "ground_contact": contact, "maybe_landed": maybe, "landed": landed,
                "at_rest": landed, "has_low_throttle": maybe}

"""Offboard setpoints: SET_POSITION_TARGET_LOCAL_NED -> TrajectorySetpoint in the local NED frame.

The type mask becomes NaN ("not controlled") per axis, as PX4's TrajectorySetpoint; body and offset frames
are turned into local NED here, so the commander sees one frame. Infinity is not a setpoint: dropped.
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as M

from ..messages import TrajectorySetpoint
from .links import AUTOPILOT_COMPID, Peer


class Offboard:
    def __init__(self, ep):
        self.ep = ep
        self.messages = {"SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target_local_ned}

    def _on_set_position_target_local_ned(self, peer: Peer, m) -> None:
        ep = self.ep
        if not (ep.for_me(m.target_system) and m.target_component in (0, AUTOPILOT_COMPID)):
            return
        mask = m.type_mask
        nan = math.nan
        p = np.array([nan if mask & b else v for b, v in ((1, m.x), (2, m.y), (4, m.z))], dtype=float)
        v = np.array([nan if mask & b else x for b, x in ((8, m.vx), (16, m.vy), (32, m.vz))], dtype=float)
        a = np.array([nan if mask & b else x for b, x in ((64, m.afx), (128, m.afy), (256, m.afz))], dtype=float)
        yaw = nan if mask & 1024 else float(m.yaw)
        yawrate = nan if mask & 2048 else float(m.yaw_rate)
        if any(math.isinf(x) for x in (*p, *v, *a, yaw, yawrate)):
            peer.link.rx_dropped += 1  # NaN means "not controlled"; infinity means nothing
            return
        frame = m.coordinate_frame
        if frame == M.MAV_FRAME_BODY_NED or frame == M.MAV_FRAME_BODY_OFFSET_NED:
            hdg = float(ep.telemetry.v("local_position").heading_rad)
            c, s = math.cos(hdg), math.sin(hdg)
            rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            v = rot @ v if np.all(np.isfinite(v[:2])) else v
            a = rot @ a if np.all(np.isfinite(a[:2])) else a
            if frame == M.MAV_FRAME_BODY_OFFSET_NED and np.all(np.isfinite(p)):
                p = ep.telemetry.v("local_position").position_ned_m + rot @ p
        elif frame == M.MAV_FRAME_LOCAL_OFFSET_NED and np.all(np.isfinite(p)):
            p = ep.telemetry.v("local_position").position_ned_m + p
        elif frame != M.MAV_FRAME_LOCAL_NED:
            ep.cmd.text(4, f"offboard frame {frame} not supported")
            return
        ep.cmd.set_offboard_setpoint(TrajectorySetpoint(int(ep.vehicle.time_us), p, v, a, yaw, yawrate))

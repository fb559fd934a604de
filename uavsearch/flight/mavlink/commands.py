"""COMMAND_LONG / COMMAND_INT: decode, route to the component and capability that serves them, ACK the sender.

Camera commands go to the camera component (compid 100); the protocol modules register the autopilot
commands they serve (message intervals, lockstep); everything else becomes a VehicleCommand for the
commander, which reuses MAV_CMD numbers. COMMAND_INT's degE7 coordinates become degrees here, so the
commander sees one form of every command.
"""

from __future__ import annotations

import logging
import math

from pymavlink.dialects.v20 import common as M

from ..camera import CAMERA_COMPID
from ..commander import Result, VehicleCommand
from ..lockstep import MAV_CMD_SIM_ADVANCE
from .camera import CAMERA_COMMANDS
from .links import AUTOPILOT_COMPID, Peer

log = logging.getLogger(__name__)
_GLOBAL_FRAMES = (M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                  M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
_FLOAT_FRAME = {M.MAV_FRAME_GLOBAL_INT: M.MAV_FRAME_GLOBAL,
                M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: M.MAV_FRAME_GLOBAL_RELATIVE_ALT}


class Commands:
    """The command router. `handlers`: MAV_CMD -> fn(peer, m, command, params) for autopilot commands served
    outside the commander; `camera`: the camera protocol, or None when the vehicle has no camera."""

    def __init__(self, ep, handlers: dict, camera=None):
        self.ep = ep
        self.handlers = {**handlers, MAV_CMD_SIM_ADVANCE: self._on_sim_advance}
        self.camera = camera
        self.messages = {"COMMAND_LONG": self._on_command_long, "COMMAND_INT": self._on_command_int}

    def _on_command_long(self, peer: Peer, m) -> None:
        if not self.ep.for_me(m.target_system):
            return
        p = [m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7]
        self._command(peer, m, m.command, p, M.MAV_FRAME_GLOBAL, m.target_component)

    def _on_command_int(self, peer: Peer, m) -> None:
        if not self.ep.for_me(m.target_system):
            return
        p = [m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z]
        if m.frame in _GLOBAL_FRAMES:
            p[4] = m.x * 1e-7 if m.x != 0 or m.y != 0 else math.nan
            p[5] = m.y * 1e-7 if m.x != 0 or m.y != 0 else math.nan
        self._command(peer, m, m.command, p, _FLOAT_FRAME.get(m.frame, m.frame), m.target_component)

    def _command(self, peer: Peer, m, command: int, p: list, frame: int, target_comp: int) -> None:
        """Exactly one COMMAND_ACK for a command to a component that exists here, whatever is wrong with it
        (a handler that raised is answered FAILED; the lockstep grant answers later, once)."""
        to_camera = self.camera is not None and (
            target_comp == CAMERA_COMPID or (target_comp == 0 and command in CAMERA_COMMANDS))
        if not to_camera and target_comp not in (0, AUTOPILOT_COMPID):
            return  # addressed to a component that does not exist here
        compid = CAMERA_COMPID if to_camera else AUTOPILOT_COMPID
        before = self.ep.acks_sent
        self._deferred = False
        try:
            self._dispatch(peer, m, command, p, frame, to_camera)
        except (ValueError, OverflowError):  # e.g. a count of NaN / inf reaching int()
            result = Result.DENIED
        except Exception:  # noqa: BLE001 - a packet must never take the vehicle down, nor go unanswered
            log.warning("command %d failed", command, exc_info=True)
            result = Result.FAILED
        else:
            result = Result.DENIED
        if self.ep.acks_sent == before and not self._deferred:
            self.ep.ack(peer, m, command, result, compid)

    def _dispatch(self, peer: Peer, m, command: int, p: list, frame: int, to_camera: bool) -> None:
        if to_camera:
            return self.camera.command(peer, m, command, p)
        handler = self.handlers.get(command)
        if handler is not None:
            return handler(peer, m, command, p)
        vc = VehicleCommand(command, *(float(x) for x in p), frame=frame, source_system=m.get_srcSystem(),
                            source_component=m.get_srcComponent())
        result = self.ep.cmd.handle_command(vc)
        self.ep.ack(peer, m, command, result)
        self.ep.flush_events()
        self.ep.send_state_if_changed()

    def _on_sim_advance(self, peer: Peer, m, command: int, p: list) -> None:
        """Lockstep (see lockstep.py): run to time_boot_ms = param5 / x, ACK once the clock is there."""
        until_ms = p[4]
        if self.ep.lockstep is None:
            return self.ep.ack(peer, m, command, Result.UNSUPPORTED)
        if not (math.isfinite(until_ms) and 0 <= until_ms < 2**31):
            return self.ep.ack(peer, m, command, Result.DENIED)
        self._deferred = True  # answered when the clock gets there
        self.ep.lockstep.grant(int(until_ms) * 1000,
                               lambda now_ms: self.ep.ack(peer, m, command, Result.ACCEPTED, result_param2=now_ms))

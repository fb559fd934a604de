"""The vehicle's MAVLink endpoint: links plus the capability modules, driven by the runner on simulation time.

The runner calls `poll()` and `send_streams()` at a fixed simulation-time rate, never per physics step:
the endpoint never blocks and never advances time itself, and telemetry timestamps are simulation time.
Each capability (streams, commands, params, mission, camera, offboard, ftp) is its own module, as MAVSDK
splits plugins; this class owns what they share: the links, routing incoming messages to the module that
serves them, the commander's events (texts, mission progress, captures) and the lockstep hold. Malformed
or badly signed packets are dropped and counted (SYS_STATUS.errors_comm), never raised.
"""

from __future__ import annotations

import logging
import math
import select

from pymavlink.dialects.v20 import common as M

from ..camera import CAMERA_COMPID, Camera
from ..commander import Commander
from ..lockstep import HOLD_HEARTBEAT_WALL_S, LockstepGate
from ..params import ParamStore
from .camera import CameraProtocol
from .commands import Commands
from .ftp import FtpProtocol
from .links import AUTOPILOT_COMPID, Link, LinkConfig
from .mission import MissionProtocol
from .offboard import Offboard
from .params import ParamProtocol
from .streams import Streams
from .telemetry import Telemetry

log = logging.getLogger(__name__)


class MavlinkEndpoint:
    """Translates between MAVLink packets and the commander / camera / param store."""

    def __init__(self, commander: Commander, params: ParamStore, links: list[LinkConfig], camera: Camera | None = None,
                 sysid: int = 1):
        self.cmd = commander
        self.vehicle = commander.vehicle
        self.camera = camera
        self.sysid = sysid
        self.links = [Link(c, sysid) for c in links]
        self.wall_s = 0.0
        self.lockstep: LockstepGate | None = None  # set by a runner in lockstep (see lockstep.py)
        self._sent_state = None
        self._hold_hb_wall = -math.inf
        self._fds = [link.sock.fileno() for link in self.links]
        self.telemetry = Telemetry(commander, lambda: self.rx_dropped)
        self.camera_protocol = CameraProtocol(self, camera) if camera is not None else None
        self.streams = Streams(self, self.links, self.camera_protocol.heartbeat if self.camera_protocol else None)
        self.mission = MissionProtocol(self)
        commands = Commands(self, self.streams.commands, self.camera_protocol)
        self._handlers = {"HEARTBEAT": self._on_heartbeat, "TIMESYNC": self._on_timesync, **commands.messages,
                          **ParamProtocol(self, params).messages, **self.mission.messages, **Offboard(self).messages,
                          **FtpProtocol(self).messages}

    # ------------------------------------------------------------------ plumbing
    def fileno_list(self) -> list[int]:
        return [l.sock.fileno() for l in self.links]

    def wait_readable(self, timeout_s: float) -> bool:
        if timeout_s <= 0:
            return False
        r, _, _ = select.select(self.fileno_list(), [], [], timeout_s)
        return bool(r)

    @property
    def rx_dropped(self) -> int:
        return sum(l.rx_dropped for l in self.links)

    def close(self) -> None:
        for l in self.links:
            l.flush()
            l.close()

    # ------------------------------------------------------------------ what the capability modules share
    def for_me(self, target_system: int) -> bool:
        return target_system in (0, self.sysid)

    def broadcast(self, msg, compid: int = AUTOPILOT_COMPID) -> None:
        for l in self.links:
            l.send(msg, compid)

    def ack(self, link: Link, m, command: int, result: int, compid: int = AUTOPILOT_COMPID,
            result_param2: int = 0) -> None:
        link.send(link.mav.command_ack_encode(command, int(result), 0, result_param2, m.get_srcSystem(),
                                              m.get_srcComponent()), compid)

    def send_state_if_changed(self) -> None:
        """HEARTBEAT + EXTENDED_SYS_STATE at once when arming, mode or landed state changed."""
        state = (self.cmd.armed, self.cmd.custom_mode)
        if self.cmd.state_changed or state != self._sent_state:
            self.cmd.state_changed = False
            self._sent_state = state
            self.broadcast(self.telemetry.heartbeat())
            self.broadcast(self.telemetry.extended_sys_state())

    def flush_events(self) -> None:
        """The commander's outbox: status texts, mission progress, captures it triggered (mission items)."""
        for t in self.cmd.texts:
            self.broadcast(M.MAVLink_statustext_message(t.severity, t.text.encode()[:50], 0, 0))
        self.cmd.texts.clear()
        for kind, seq in self.cmd.mission_events:
            if kind == "reached":
                self.broadcast(M.MAVLink_mission_item_reached_message(seq))
            else:
                self.broadcast(self.telemetry.mission_current())
        self.cmd.mission_events.clear()
        for _item in self.cmd.captures:
            if self.camera_protocol is not None:
                self.camera_protocol.broadcast_capture(self.camera.capture())
        self.cmd.captures.clear()

    def _flush_links(self) -> None:
        for link in self.links:
            link.flush()

    # ------------------------------------------------------------------ the calls the runner makes
    def poll(self, wall_s: float) -> int:
        """Handle every waiting packet on every link; returns how many were handled."""
        self.wall_s = wall_s
        self.telemetry.new_tick()
        n = 0
        try:  # one select() tells which sockets have data: idle links cost no recv call
            readable = set(select.select(self._fds, [], [], 0)[0])
        except (OSError, ValueError):
            readable = set(self._fds)
        for link in self.links:
            if link.upload is not None:
                self.mission.retry(link)
            if link.sock.fileno() not in readable:
                continue
            for m in link.receive():
                n += 1
                try:
                    self._handle(link, m)
                except Exception as e:  # a packet must never take the vehicle down
                    link.rx_dropped += 1
                    log.debug("dropped %s", m, exc_info=True)
                    self.cmd.text(3, f"dropped {m.get_type()}: {type(e).__name__}")
        if self.cmd.texts or self.cmd.mission_events or self.cmd.captures:
            self.flush_events()
        self._flush_links()
        return n

    def send_streams(self) -> None:
        now = int(self.vehicle.time_us)
        self.telemetry.new_tick()  # vehicle outputs are read once per call, shared by every message and link
        self.send_state_if_changed()
        if self.camera is not None and self.camera.capturing_interval:
            for rec in self.camera.update():
                self.camera_protocol.broadcast_capture(rec)
        self.streams.send_due(now)
        self._flush_links()

    def hold(self, wall_s: float) -> None:
        """Lockstep: the clock reached its grant. Publish the state it stopped in, answer the grant, and
        keep a heartbeat going on the wall clock while nothing runs."""
        self.send_state_if_changed()  # the client must not learn of a change later than the ACK
        self.lockstep.arrived(int(self.vehicle.time_us))
        if wall_s - self._hold_hb_wall >= HOLD_HEARTBEAT_WALL_S:
            self._hold_hb_wall = wall_s
            self.broadcast(self.telemetry.heartbeat())
        self._flush_links()

    # ------------------------------------------------------------------ incoming
    def _handle(self, link: Link, m) -> None:
        if m.get_srcSystem() == self.sysid and m.get_srcComponent() in (AUTOPILOT_COMPID, CAMERA_COMPID):
            return  # our own echo
        h = self._handlers.get(m.get_type())
        if h is not None:
            h(link, m)

    def _on_heartbeat(self, link: Link, m) -> None:
        if m.type not in (M.MAV_TYPE_CAMERA, M.MAV_TYPE_GIMBAL) and m.get_srcSystem() != self.sysid:
            self.cmd.on_gcs_heartbeat()

    def _on_timesync(self, link: Link, m) -> None:
        if m.tc1 == 0:
            link.send(M.MAVLink_timesync_message(int(self.vehicle.time_us) * 1000, m.ts1))

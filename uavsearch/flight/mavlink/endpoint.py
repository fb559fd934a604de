"""The vehicle's MAVLink endpoint: links plus the capability modules, driven by the runner on simulation time.

The runner calls `poll()` and `send_streams()` at a fixed simulation-time rate, never per physics step:
the endpoint never blocks and never advances time itself, and telemetry timestamps are simulation time.
Each capability (streams, commands, params, mission, camera, offboard, ftp) is its own module, as MAVSDK
splits plugins; this class owns what they share: the links, routing incoming messages to the module that
serves them (each handler gets the Peer that sent the message, and replies to it alone), the commander's
events (texts, mission progress, captures: to every destination of every link) and the lockstep hold. Malformed
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
from .links import AUTOPILOT_COMPID, Link, LinkConfig, Peer
from .signing import SigningRecord
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
        records: dict = {}  # one signing record per key, shared by the links that hold it
        self.links = [Link(c, sysid, records.setdefault(c.signing_key, SigningRecord()) if c.signing_key else None, i)
                      for i, c in enumerate(links)]
        self.wall_s = 0.0
        self.lockstep: LockstepGate | None = None  # set by a runner in lockstep (see lockstep.py)
        self._sent_state = None
        self.acks_sent = 0  # COMMAND_ACKs sent (commands.py checks each command got exactly one)
        self._hold_hb_wall = -math.inf
        self._text_id = 0  # the id of the last chunked STATUSTEXT
        self.text_listeners: list = []  # callables(severity, text) that hear every status text sent (the flight log)
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

    def ack(self, peer: Peer, m, command: int, result: int, compid: int = AUTOPILOT_COMPID,
            result_param2: int = 0) -> None:
        """COMMAND_ACK to the peer that sent command `m` (and to nobody else)."""
        self.acks_sent += 1
        peer.send(M.MAVLink_command_ack_message(command, int(result), 0, result_param2, m.get_srcSystem(),
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
            self.statustext(t.severity, t.text)
        self.cmd.texts.clear()
        for kind, seq in self.cmd.mission_events:
            if kind == "reached":
                self.broadcast(M.MAVLink_mission_item_reached_message(seq))
            else:
                self.broadcast(self.telemetry.mission_current())
        self.cmd.mission_events.clear()
        for _item in self.cmd.captures:
            if self.camera is not None:
                self.camera.queue_mission_shot()  # reported by send_captures() once rendered
        self.cmd.captures.clear()

    def send_captures(self) -> None:
        """CAMERA_IMAGE_CAPTURED for every shot the camera finished (interval triggers fire here too), and what
        the camera has to say (interval capture stopped, a photo skipped)."""
        if self.camera is not None and self.camera.busy:
            for rec in self.camera.update():
                self.camera_protocol.broadcast_capture(rec)
        if self.camera is not None and self.camera.notices:
            self.camera_protocol.send_notices()

    def statustext(self, severity: int, text: str, compid: int = AUTOPILOT_COMPID) -> None:
        """STATUSTEXT to every destination; a text longer than one message (50 characters) goes in chunks
        sharing an id, as MAVLink 2 defines (a short or empty chunk ends it)."""
        for listener in self.text_listeners:
            listener(severity, text)
        data = text.encode("utf-8", "replace")
        if len(data) <= 50:
            return self.broadcast(M.MAVLink_statustext_message(severity, data, 0, 0), compid)
        self._text_id = self._text_id % 0xFFFF + 1
        chunks = [data[i:i + 50] for i in range(0, len(data), 50)][:255]
        if len(chunks[-1]) == 50 and len(chunks) < 255:
            chunks.append(b"")
        for seq, chunk in enumerate(chunks):
            self.broadcast(M.MAVLink_statustext_message(severity, chunk, self._text_id, seq), compid)

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
        self.mission.retry()
        for link in self.links:
            link.expire(wall_s)
            if link.sock.fileno() not in readable:
                continue
            for peer, m in link.receive(wall_s):
                n += 1
                try:
                    self._handle(peer, m)
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
        self.send_captures()
        self.streams.send_due(now)
        self._flush_links()

    def hold(self, wall_s: float) -> None:
        """Lockstep: the clock reached its grant. Publish the state it stopped in, answer the grant, and
        keep a heartbeat going on the wall clock while nothing runs."""
        self.send_state_if_changed()  # the client must not learn of a change later than the ACK
        self.send_captures()  # images of shots taken before the clock stopped
        self.lockstep.arrived(int(self.vehicle.time_us))
        if wall_s - self._hold_hb_wall >= HOLD_HEARTBEAT_WALL_S:
            self._hold_hb_wall = wall_s
            self.broadcast(self.telemetry.heartbeat())
        self._flush_links()

    # ------------------------------------------------------------------ incoming
    def _handle(self, peer: Peer, m) -> None:
        """Route `m` to its handler with the peer that sent it: every reply goes back to that peer."""
        if m.get_srcSystem() == self.sysid and m.get_srcComponent() in (AUTOPILOT_COMPID, CAMERA_COMPID):
            return  # our own echo
        h = self._handlers.get(m.get_type())
        if h is not None:
            h(peer, m)

    def _on_heartbeat(self, peer: Peer, m) -> None:
        if m.type not in (M.MAV_TYPE_CAMERA, M.MAV_TYPE_GIMBAL) and m.get_srcSystem() != self.sysid:
            self.cmd.on_gcs_heartbeat()

    def _on_timesync(self, peer: Peer, m) -> None:
        if m.tc1 == 0:
            peer.send(M.MAVLink_timesync_message(int(self.vehicle.time_us) * 1000, m.ts1))

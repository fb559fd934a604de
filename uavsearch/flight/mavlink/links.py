"""UDP links: one non-blocking socket per link with a table of the peers that talk to it, as mavlink-router keeps.

Like PX4 SITL, the API link sends to 14540 (MAVSDK) and the GCS link to 14550 (QGroundControl, MAVProxy) before
anybody talks. Every address that sends a good frame becomes a peer: streams and events go to the default port
and to every live peer, a reply goes only to the peer that asked (handlers get the Peer, not the link), and a
peer silent for PEER_TIMEOUT_S wall seconds is forgotten. Each link keeps one encoder (one sequence, one
signing clock): a frame is packed once and the same bytes go to each destination.
Frames are queued per destination and packed into datagrams below a typical MTU; bad frames are counted and
dropped, never raised, so a malformed packet cannot take the vehicle down.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

from .signing import SigningMAVLink, SigningRecord, enable_signing

AUTOPILOT_COMPID = 1
DATAGRAM_BYTES = 1400  # below a typical MTU; frames are never split across datagrams
PEER_TIMEOUT_S = 5.0  # wall seconds without a good frame before a peer stops getting streams (MAVSDK: 1 Hz heartbeat)
MAX_PEERS = 16  # per link; beyond it the stalest unsigned peer makes room (a signed one only for a signed newcomer)


@dataclass
class LinkConfig:
    """One UDP link: where to send, where to listen, and how to sign."""

    name: str
    remote_port: int
    remote_host: str = "127.0.0.1"
    local_port: int = 0  # 0: any free port; replies come from it
    signing_key: bytes | None = None
    require_signed: bool = True  # False: sign output but accept unsigned input (MAVSDK cannot sign)
    rates_hz: dict | None = None  # default stream rates; None = streams.DEFAULT_RATES_HZ


class Peer:
    """One address talking to a link: who it said it was, when it last spoke, whether it signs.
    `send` answers it alone (a reply); the link's own `send` goes to everyone."""

    __slots__ = ("link", "addr", "sysid", "compid", "last_seen", "signed")

    def __init__(self, link: "Link", addr: tuple, sysid: int = 0, compid: int = 0, last_seen: float = 0.0,
                 signed: bool = False):
        self.link, self.addr, self.sysid, self.compid = link, addr, sysid, compid
        self.last_seen, self.signed = last_seen, signed

    def send(self, msg, compid: int = AUTOPILOT_COMPID) -> None:
        self.link.send(msg, compid, to=self.addr)

    def __repr__(self) -> str:
        return f"Peer({self.link.cfg.name} {self.addr[0]}:{self.addr[1]} {self.sysid}/{self.compid})"


class _Writer:
    def __init__(self, link: "Link"):
        self.link = link

    def write(self, buf: bytes) -> None:
        self.link.send_raw(bytes(buf))


class Link:
    """A socket, its pymavlink parser/packer (own sequence numbers and signing), its peers, counters and
    per-link state."""

    def __init__(self, cfg: LinkConfig, sysid: int, signing_record: SigningRecord | None = None, link_id: int = 0):
        self.cfg = cfg
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.sock.bind(("127.0.0.1" if cfg.remote_host in ("127.0.0.1", "localhost") else "0.0.0.0", cfg.local_port))
        self.default_remote = (cfg.remote_host, cfg.remote_port) if cfg.remote_port else None
        self.peers: dict[tuple, Peer] = {}
        self._dests: list[tuple] = []  # destinations(), rebuilt only when the peer table changes
        self.mav = SigningMAVLink(_Writer(self), srcSystem=sysid, srcComponent=AUTOPILOT_COMPID)
        self.mav.robust_parsing = True
        if cfg.signing_key is not None:
            enable_signing(self.mav, cfg.signing_key, cfg.require_signed, signing_record, link_id)
        self.intervals_us: dict = {}  # per-message stream intervals (streams.py fills them)
        self.next_due_us: dict = {}
        self.default_rates_hz: dict = {}
        self.rx_packets = 0
        self.rx_dropped = 0
        self.tx_packets = 0
        self._out: dict[tuple, bytearray] = {}  # per destination: frames waiting for flush()
        self._to = None  # the destination of the frame being packed (None: every stream destination)
        self._peers_changed()

    @property
    def local_port(self) -> int:
        return self.sock.getsockname()[1]

    def destinations(self) -> list[tuple]:
        """Where streams and events go: the default port and every live peer."""
        return self._dests

    def _peers_changed(self) -> None:
        self._dests = ([self.default_remote] if self.default_remote is not None else []) + \
            [a for a in self.peers if a != self.default_remote]

    def send_raw(self, buf: bytes) -> None:
        """Queue one frame; flush() packs queued frames into datagrams of at most DATAGRAM_BYTES (as PX4 does)."""
        for addr in (self.destinations() if self._to is None else (self._to,)):
            out = self._out.get(addr)
            if out is None:
                out = self._out[addr] = bytearray()
            elif len(out) + len(buf) > DATAGRAM_BYTES:
                self._sendto(out, addr)
            out += buf
        self.tx_packets += 1

    def _sendto(self, out: bytearray, addr: tuple) -> None:
        try:
            self.sock.sendto(bytes(out), addr)
        except OSError:
            pass  # nobody listening (ICMP port unreachable) or a full buffer: telemetry is best effort
        out.clear()

    def flush(self) -> None:
        for addr, out in self._out.items():
            if out:
                self._sendto(out, addr)
        if len(self._out) > 2 * MAX_PEERS:  # forget buffers of peers long gone
            self._out = {a: b for a, b in self._out.items() if a in self.peers or a == self.default_remote}

    def send(self, msg, compid: int = AUTOPILOT_COMPID, to: tuple | None = None) -> None:
        """Pack `msg` once; to every stream destination, or only to address `to` (a reply)."""
        self.mav.srcComponent = compid
        self._to = to
        try:
            self.mav.send(msg)
        finally:
            self._to = None

    def expire(self, now_wall: float) -> None:
        """Forget peers silent for PEER_TIMEOUT_S."""
        gone = [a for a, p in self.peers.items() if now_wall - p.last_seen > PEER_TIMEOUT_S]
        for a in gone:
            del self.peers[a]
        if gone:
            self._peers_changed()

    def _peer(self, addr: tuple, m, now_wall: float) -> Peer:
        """The table entry for `addr`, made or refreshed by its good frame `m`; a transient Peer (replies still reach
        it) when the table is full of peers it may not displace."""
        signed = bool(getattr(m, "_signed", False))
        p = self.peers.get(addr)
        if p is None:
            p = Peer(self, addr, m.get_srcSystem(), m.get_srcComponent(), now_wall, signed)
            if m.get_srcSystem() == self.mav.srcSystem:
                return p  # our own frames coming back (a forwarding router): streaming to it would loop
            if len(self.peers) >= MAX_PEERS and not self._make_room(signed):
                return p
            self.peers[addr] = p
            self._peers_changed()
        p.sysid, p.compid, p.last_seen = m.get_srcSystem(), m.get_srcComponent(), now_wall
        p.signed = p.signed or signed
        return p

    def _make_room(self, signed: bool) -> bool:
        """Drop the stalest unsigned peer; a signed newcomer may also displace the stalest signed one."""
        pool = [p for p in self.peers.values() if not p.signed] or ([*self.peers.values()] if signed else [])
        if not pool:
            return False
        del self.peers[min(pool, key=lambda p: p.last_seen).addr]
        self._peers_changed()
        return True

    def receive(self, now_wall: float = 0.0) -> list[tuple[Peer, object]]:
        """(peer, message) for every message waiting on the socket; bad frames are counted and dropped."""
        out = []
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                return out  # ICMP errors surface on the next recv on some platforms
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:  # pymavlink raises a few plain errors on garbage even when robust
                self.rx_dropped += 1
                self.mav.buf = bytearray()
                self.mav.buf_index = 0
                continue
            for m in msgs:
                if m.get_type() in ("BAD_DATA", "UNKNOWN") or m.get_msgId() < 0:
                    self.rx_dropped += 1
                    continue
                self.rx_packets += 1
                out.append((self._peer(addr, m, now_wall), m))
            if len(self.mav.buf) - self.mav.buf_index > 0:
                # A truncated frame (or junk announcing one) stays in the parser's buffer: drop it, datagrams never
                # continue, or the next datagram's frames would be swallowed into it.
                self.rx_dropped += 1
                self.mav.buf = bytearray()
                self.mav.buf_index = 0

    def close(self) -> None:
        self.sock.close()

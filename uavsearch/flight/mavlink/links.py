"""UDP links: one non-blocking socket per link, sending to a fixed remote port and answering whoever talked last.

Like PX4 SITL, the API link sends to 14540 (MAVSDK) and the GCS link to 14550 (QGroundControl, MAVProxy).
Frames are queued and packed into datagrams below a typical MTU; bad frames are counted and dropped, never
raised, so a malformed packet cannot take the vehicle down.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from .signing import enable_signing, frame_is_signed

AUTOPILOT_COMPID = 1
DATAGRAM_BYTES = 1400  # below a typical MTU; frames are never split across datagrams


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


class _Writer:
    def __init__(self, link: "Link"):
        self.link = link

    def write(self, buf: bytes) -> None:
        self.link.send_raw(bytes(buf))


class Link:
    """A socket, its pymavlink parser/packer (own sequence numbers and signing), counters and per-link state."""

    def __init__(self, cfg: LinkConfig, sysid: int):
        self.cfg = cfg
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.sock.bind(("127.0.0.1" if cfg.remote_host in ("127.0.0.1", "localhost") else "0.0.0.0", cfg.local_port))
        self.remote = (cfg.remote_host, cfg.remote_port)
        self.mav = mavlink.MAVLink(_Writer(self), srcSystem=sysid, srcComponent=AUTOPILOT_COMPID)
        self.mav.robust_parsing = True
        self._frame_signed = False
        if cfg.signing_key is not None:
            enable_signing(self.mav, cfg.signing_key, cfg.require_signed, lambda: self._frame_signed)
        self.intervals_us: dict = {}  # per-message stream intervals (streams.py fills them)
        self.next_due_us: dict = {}
        self.default_rates_hz: dict = {}
        self.rx_packets = 0
        self.rx_dropped = 0
        self.tx_packets = 0
        self._out = bytearray()
        self.upload = None  # a mission upload in progress from this link's client (mission.py)

    @property
    def local_port(self) -> int:
        return self.sock.getsockname()[1]

    def send_raw(self, buf: bytes) -> None:
        """Queue one frame; flush() packs queued frames into datagrams of at most DATAGRAM_BYTES (as PX4 does)."""
        if self._out and len(self._out) + len(buf) > DATAGRAM_BYTES:
            self.flush()
        self._out += buf
        self.tx_packets += 1

    def flush(self) -> None:
        if not self._out:
            return
        try:
            self.sock.sendto(bytes(self._out), self.remote)
        except OSError:
            pass  # nobody listening (ICMP port unreachable) or a full buffer: telemetry is best effort
        self._out.clear()

    def send(self, msg, compid: int = AUTOPILOT_COMPID) -> None:
        self.mav.srcComponent = compid
        self.mav.send(msg)

    def receive(self) -> list:
        """Every message waiting on the socket; bad frames are counted and dropped."""
        out = []
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                return out  # ICMP errors surface on the next recv on some platforms
            self._frame_signed = frame_is_signed(data)
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:  # pymavlink raises a few plain errors on garbage even when robust
                self.rx_dropped += 1
                self.mav.buf = bytearray()
                self.mav.buf_index = 0
                continue
            good = 0
            for m in msgs:
                if m.get_type() in ("BAD_DATA", "UNKNOWN") or m.get_msgId() < 0:
                    self.rx_dropped += 1
                    continue
                good += 1
                out.append(m)
            if good:
                self.remote = addr
                self.rx_packets += good
            elif not msgs and len(data) > 0 and self.mav.bytes_needed() > 0 and len(self.mav.buf) - self.mav.buf_index > 0:
                # A truncated frame stays in the parser's buffer: drop it, datagrams never continue.
                self.rx_dropped += 1
                self.mav.buf = bytearray()
                self.mav.buf_index = 0

    def close(self) -> None:
        self.sock.close()

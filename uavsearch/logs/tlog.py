"""MAVLink telemetry logs (.tlog): what pymavlink's mavlogdump, MAVProxy and QGroundControl read.

A tlog is a plain sequence of records: an 8-byte big-endian microsecond UNIX timestamp followed by
one raw MAVLink packet. The writer hooks into a pymavlink connection so that EVERY packet in both
directions is recorded (the receive callback sees all parsed packets, not only the ones a caller
asked for), and flushes often, so a process killed mid-flight leaves a log readable up to the end.
"""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

FLUSH_EVERY_S = 0.25


class TlogWriter:
    """Append-only tlog; `attach(conn)` records a pymavlink connection's traffic both ways."""

    def __init__(self, path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "ab")
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self.records = 0

    def write_packet(self, buf: bytes, t_s: float | None = None) -> None:
        if self._f is None or not buf:
            return
        usec = int((time.time() if t_s is None else t_s) * 1e6)
        with self._lock:
            self._f.write(struct.pack(">Q", usec) + bytes(buf))
            self.records += 1
            now = time.monotonic()
            if now - self._last_flush > FLUSH_EVERY_S:
                self._f.flush()
                self._last_flush = now

    def write_message(self, msg) -> None:
        self.write_packet(msg.get_msgbuf())

    def attach(self, conn) -> None:
        """Record everything `conn` (a pymavlink mavfile) receives and sends from now on."""
        conn.mav.set_callback(lambda m: self.write_message(m))
        conn.mav.set_send_callback(lambda m: self.write_message(m))

    def flush(self) -> None:
        with self._lock:
            if self._f is not None:
                self._f.flush()
                self._last_flush = time.monotonic()

    def close(self) -> None:
        with self._lock:
            if self._f is not None:
                self._f.close()
                self._f = None

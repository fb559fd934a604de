"""MAVLink telemetry logs (.tlog): what pymavlink's mavlogdump, MAVProxy and QGroundControl read.

A tlog is a plain sequence of records: an 8-byte big-endian microsecond UNIX timestamp followed by
one raw MAVLink packet. The writer hooks into a pymavlink connection so that EVERY packet in both
directions is recorded (the receive callback sees all parsed packets, not only the ones a caller
asked for), and flushes often, so a process killed mid-flight leaves a log readable up to the end.

Stamps follow the VEHICLE's clock (clock="sim", what `uavsearch fly` writes): the first stamp is the
wall time when the log started and every later one advances with the simulation time the vehicle
reports (the largest time_boot_ms received so far), so a flight simulated faster than real time, or
held still in lockstep, spans its simulated duration and mavflighttime.py / QGroundControl see the
real flight times. clock="wall" stamps the wall clock, as a ground station recording a real vehicle does.
"""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

FLUSH_EVERY_S = 0.25


class TlogWriter:
    """Append-only tlog; `attach(conn)` records a pymavlink connection's traffic both ways."""

    def __init__(self, path, clock: str = "wall"):
        if clock not in ("wall", "sim"):
            raise ValueError(f"tlog clock must be 'wall' or 'sim', not {clock!r}")
        self.clock = clock
        self._base_s: float | None = None  # unix time of simulation time 0 (clock="sim")
        self._sim_s = 0.0
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "ab")
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self.records = 0
        self.error: OSError | None = None  # why the log stopped growing (a full disk): packets are never lost
        # silently in a traceback inside pymavlink's receive callback; the flight goes on and says so

    def write_packet(self, buf: bytes, t_s: float | None = None) -> None:
        if self._f is None or not buf:
            return
        usec = int((self.now() if t_s is None else t_s) * 1e6)
        with self._lock:
            try:
                self._f.write(struct.pack(">Q", usec) + bytes(buf))
                self.records += 1
                now = time.monotonic()
                if now - self._last_flush > FLUSH_EVERY_S:
                    self._f.flush()
                    self._last_flush = now
            except OSError as e:
                self._stop(e)

    def now(self) -> float:
        """The stamp of a record written now, in unix seconds."""
        if self.clock == "wall" or self._base_s is None:
            return time.time()
        return self._base_s + self._sim_s

    def observe(self, msg) -> None:
        """Track the vehicle's clock from a received message's time_boot_ms (never backwards)."""
        t_ms = getattr(msg, "time_boot_ms", None)
        if self.clock != "sim" or t_ms is None:
            return
        sim_s = t_ms * 1e-3
        if self._base_s is None:
            self._base_s = time.time() - sim_s
        self._sim_s = max(self._sim_s, sim_s)

    def write_message(self, msg) -> None:
        self.write_packet(msg.get_msgbuf())

    def attach(self, conn, vehicle_sysid: int | None = None) -> None:
        """Record everything `conn` (a pymavlink mavfile) receives and sends from now on."""

        def received(m):
            if vehicle_sysid is None or m.get_srcSystem() == vehicle_sysid:
                self.observe(m)
            self.write_message(m)

        conn.mav.set_callback(received)
        conn.mav.set_send_callback(lambda m: self.write_message(m))

    def _stop(self, error: OSError) -> None:
        """Stop writing after a failed write (lock held): keep the error, drop the unwritable buffer."""
        self.error = error
        f, self._f = self._f, None
        try:
            f.close()
        except OSError:
            pass

    def flush(self) -> None:
        with self._lock:
            if self._f is not None:
                try:
                    self._f.flush()
                except OSError as e:
                    self._stop(e)
                self._last_flush = time.monotonic()

    def close(self) -> None:
        with self._lock:
            if self._f is not None:
                try:
                    self._f.close()
                except OSError as e:
                    self.error = e
                self._f = None

"""A ULog (.ulg) writer, by hand: PX4's self-describing log format, what Flight Review, PlotJuggler and pyulog read.

No library writes ULog from scratch (pyulog parses a log and can re-write one it parsed; nothing builds one from
nothing), so this module writes the format itself, following PX4's "ULog File Format" page and tested by reading
back with pyulog. It knows nothing of the vehicle: `logger.py` says what is logged.

A file is a 16-byte header (magic, version 1, start timestamp), then messages of `uint16 size, uint8 type, payload`:
the definitions (flag bits first, then info 'I', formats 'F' and initial parameters 'P'), then the data section
(subscriptions 'A', data 'D', logged text 'L', parameter changes 'P'). A topic's layout follows PX4's message
generator: fields sorted by the size of their type (largest first, stable; nested messages last), padding so a
nested message starts on 8 bytes and the struct ends on 8; a data message leaves out the trailing padding, as
PX4's logger does. Whole messages are written at a time, so a file cut short by a killed process ends at a message
boundary (and a reader stops at a torn last message anyway).
"""

from __future__ import annotations

import operator
import struct
import time
from pathlib import Path

MAGIC = b"ULog\x01\x12\x35"
VERSION = 1
FLUSH_EVERY_S = 0.25  # wall time between writes to the file: a killed vehicle loses at most this much
FLUSH_BYTES = 64 * 1024

# ULog type -> (struct code, size); msg-file type -> ULog type
_TYPES = {"int8_t": ("b", 1), "uint8_t": ("B", 1), "int16_t": ("h", 2), "uint16_t": ("H", 2), "int32_t": ("i", 4),
          "uint32_t": ("I", 4), "int64_t": ("q", 8), "uint64_t": ("Q", 8), "float": ("f", 4), "double": ("d", 8),
          "bool": ("?", 1), "char": ("c", 1)}
_MSG_TYPES = {"int8": "int8_t", "uint8": "uint8_t", "int16": "int16_t", "uint16": "uint16_t", "int32": "int32_t",
              "uint32": "uint32_t", "int64": "int64_t", "uint64": "uint64_t", "float32": "float", "float64": "double",
              "bool": "bool", "char": "char"}
ALIGN = 8  # PX4 aligns every struct to its 64-bit timestamp
_DATA_HEADER = struct.Struct("<HBH")  # a data message's size, type and msg_id


class MessageDef:
    """One uORB message laid out as PX4 lays it out, from its .msg field list ("float32[3] gyro_rad" lines).

    `nested` gives the MessageDefs of nested types by their snake_case name (position_setpoint)."""

    def __init__(self, name: str, msg_fields: str, nested: dict | None = None):
        self.name = name
        nested = nested or {}
        parsed = []
        for line in msg_fields.strip().splitlines():
            line = line.split("#")[0].strip()
            if not line or "=" in line:
                continue  # a blank line, a comment or a constant
            mtype, fname = line.split()
            base, _, count = mtype.partition("[")
            n = int(count.rstrip("]")) if count else 0
            if base in _MSG_TYPES:
                ctype = _MSG_TYPES[base]
                parsed.append((ctype, n, fname, None, _TYPES[ctype][1]))
            elif base in nested:
                parsed.append((base, n, fname, nested[base], 0))
            else:
                raise ValueError(f"{name}: unknown type {base!r} of field {fname}")
        parsed.sort(key=lambda f: -f[4])  # stable: equal sizes keep the .msg order; nested types (size 0) last
        self.fields = []  # (ULog type, array length or 0, name, nested MessageDef or None)
        self._at = {}  # field name -> (its Struct or nested MessageDef, byte offset, array length or 0)
        size, pad = 0, 0
        for ctype, n, fname, sub, _ in parsed:
            if sub is not None and size % ALIGN:
                gap = ALIGN - size % ALIGN
                self.fields.append(("uint8_t", gap, f"_padding{pad}", None))
                size, pad = size + gap, pad + 1
            self.fields.append((ctype, n, fname, sub))
            if sub is None:
                code, width = _TYPES[ctype]
                self._at[fname] = (struct.Struct(f"<{n}{code}" if n else f"<{code}"), size, n)
                size += width * max(n, 1)
            else:
                self._at[fname] = (sub, size, n)
                size += sub.size * max(n, 1)
        self.size_no_padding = size  # what a data message carries: PX4's logger leaves the trailing padding out
        if size % ALIGN:
            self.fields.append(("uint8_t", ALIGN - size % ALIGN, f"_padding{pad}", None))
            size += ALIGN - size % ALIGN
        self.size = size
        self._plans: dict = {}

    def format_text(self) -> str:
        """The 'F' message's text: `name:type field;...` with arrays as `type[n]`."""
        parts = [f"{sub.name if sub is not None else ctype}{f'[{n}]' if n else ''} {fname}"
                 for ctype, n, fname, sub in self.fields]
        return f"{self.name}:" + "".join(p + ";" for p in parts)

    def nested_defs(self) -> list["MessageDef"]:
        """Every nested MessageDef, innermost first, each once."""
        out = []
        for _, _, _, sub in self.fields:
            if sub is not None:
                for d in sub.nested_defs() + [sub]:
                    if d not in out:
                        out.append(d)
        return out

    def pack_into(self, buf: bytearray, offset: int, values: dict) -> None:
        """Write the fields `values` names at `offset` of `buf` (zeroed: fields left out stay zero)."""
        at = self._at
        for fname, v in values.items():
            how, off, n = at[fname]
            if type(how) is MessageDef:
                if n:
                    for i, item in enumerate(v):
                        how.pack_into(buf, offset + off + i * how.size, item)
                else:
                    how.pack_into(buf, offset + off, v)
            elif n:
                how.pack_into(buf, offset + off, *v)
            else:
                how.pack_into(buf, offset + off, v)

    def pack(self, values: dict) -> bytes:
        """A data sample (without the trailing padding): `values` maps field -> value (a sequence for an array, a
        dict for a nested message); a field left out is zero, as in PX4's zero-initialised structs.

        A logger fills the same fields every time, so each set of field names gets one Struct (zero pad bytes
        where the fields left out lie) and one C-level getter: a sample is packed in one call."""
        plan = self._plans.get(tuple(values))
        if plan is None:
            plan = self._plans[tuple(values)] = self._plan(tuple(values))
        if not plan:
            buf = bytearray(self.size_no_padding)
            self.pack_into(buf, 0, values)
            return bytes(buf)
        st, getter, arrays = plan
        row = getter(values)
        if arrays:
            row = list(row)
            for i in arrays:
                row[i:i + 1] = row[i]
        return st.pack(*row)

    def _plan(self, names: tuple):
        """(Struct, getter, positions of arrays) packing exactly these fields, or None (a nested one, or too many
        different sets of names to keep)."""
        if not names or len(self._plans) > 16 or any(type(self._at[n][0]) is MessageDef for n in names):
            return None
        order = sorted(names, key=lambda n: self._at[n][1])
        codes, pos, arrays = [], 0, []
        for i, name in enumerate(order):
            st, off, n = self._at[name]
            if off > pos:
                codes.append(f"{off - pos}x")
            codes.append(st.format.lstrip("<"))
            pos = off + st.size
            if n:
                arrays.append(i)
        if pos < self.size_no_padding:
            codes.append(f"{self.size_no_padding - pos}x")
        getter = operator.itemgetter(*order) if len(order) > 1 else (lambda d, k=order[0]: (d[k],))
        return struct.Struct("<" + "".join(codes)), getter, arrays[::-1]


def _info_payload(ctype: str, key: str, value) -> bytes:
    """An info or parameter message's payload: key length, "type key", value."""
    if ctype == "string":
        data = str(value).encode("utf-8", "replace")
        type_key = f"char[{len(data)}] {key}".encode()
    else:
        data = struct.pack("<" + _TYPES[ctype][0], value)
        type_key = f"{ctype} {key}".encode()
    if len(type_key) > 255:
        raise ValueError(f"ULog key too long: {key!r}")
    return bytes([len(type_key)]) + type_key + data


class ULogWriter:
    """Appends one ULog file: definitions first (`info`, `parameter`, `format`), then data (`subscribe`, `data`,
    `log`, `parameter` again for a change). Messages collect in memory and go to the file whole, every
    FLUSH_EVERY_S of wall time or FLUSH_BYTES; a failed write (a full disk) stops the log, keeps the error in
    `error`, and never raises into the vehicle's loop."""

    def __init__(self, path, start_timestamp_us: int = 0):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb", buffering=0)  # unbuffered: every write is whole messages
        self._buf = bytearray(MAGIC + bytes([VERSION]) + struct.pack("<Q", int(start_timestamp_us)))
        self.messages = 0
        # flag bits: no compat / incompat flags, no appended data
        self._message("B", bytes(8) + bytes(8) + bytes(3 * 8))
        self._in_definitions = True
        self._formats: set[str] = set()
        self._ids: dict[tuple[str, int], int] = {}
        self._last_flush = time.monotonic()
        self.error: OSError | None = None

    def _message(self, kind: str, payload: bytes) -> None:
        if len(payload) > 0xFFFF:
            raise ValueError(f"ULog message {kind!r} of {len(payload)} bytes is over 65535")
        self._buf += struct.pack("<HB", len(payload), ord(kind))
        self._buf += payload
        self.messages += 1

    # ---------------------------------------------------------------- definitions
    def info(self, key: str, value, ctype: str | None = None) -> None:
        """An 'I' message: `ctype` is a ULog type ("uint32_t"), or None for a string (int -> int32_t, float ->
        float when not a string). Info messages may also come later, in the data section."""
        if ctype is None:
            ctype = "string" if isinstance(value, str) else "int32_t" if isinstance(value, int) else "float"
        self._message("I", _info_payload(ctype, key, value))

    def parameter(self, name: str, value, is_int: bool) -> None:
        """A 'P' message: an initial value in the definitions, a change once data has begun."""
        self._message("P", _info_payload("int32_t" if is_int else "float", name, int(value) if is_int else
                                         float(value)))

    def format(self, mdef: MessageDef) -> None:
        """'F' messages of `mdef` and of its nested types (each once)."""
        if not self._in_definitions:
            raise RuntimeError("ULog formats belong in the definitions, before the first subscription")
        for d in mdef.nested_defs() + [mdef]:
            if d.name not in self._formats:
                self._formats.add(d.name)
                self._message("F", d.format_text().encode())

    # ---------------------------------------------------------------- data
    def subscribe(self, mdef: MessageDef, multi_id: int = 0) -> int:
        """An 'A' message: the msg_id that `data` messages of this topic instance carry."""
        if mdef.name not in self._formats:
            self.format(mdef)
        self._in_definitions = False
        msg_id = len(self._ids)
        self._ids[(mdef.name, multi_id)] = msg_id
        self._message("A", struct.pack("<BH", multi_id, msg_id) + mdef.name.encode())
        return msg_id

    def data(self, msg_id: int, payload: bytes) -> None:
        self._buf += _DATA_HEADER.pack(len(payload) + 2, 68, msg_id)  # 68: 'D'
        self._buf += payload
        self.messages += 1

    def log(self, severity: int, timestamp_us: int, text: str) -> None:
        """An 'L' message: a logged text, its level the ASCII digit of the MAVLink / syslog severity."""
        self._in_definitions = False
        level = ord("0") + min(max(int(severity), 0), 7)
        self._message("L", struct.pack("<BQ", level, int(timestamp_us)) + text.encode("utf-8", "replace"))

    # ---------------------------------------------------------------- the file
    def maybe_flush(self) -> None:
        if len(self._buf) >= FLUSH_BYTES or time.monotonic() - self._last_flush >= FLUSH_EVERY_S:
            self.flush()

    def flush(self) -> None:
        self._last_flush = time.monotonic()
        data = bytes(self._buf)
        self._buf.clear()
        if self._f is None or not data:
            return
        try:
            done = 0
            while done < len(data):  # a regular file takes it all; a short write goes on from where it stopped
                done += self._f.write(data[done:])
        except OSError as e:
            self.error = e
            self._close_file()

    def _close_file(self) -> None:
        f, self._f = self._f, None
        try:
            f.close()
        except OSError:
            pass

    @property
    def closed(self) -> bool:
        return self._f is None

    def close(self) -> None:
        if self._f is not None:
            self.flush()
            if self._f is not None:
                self._close_file()

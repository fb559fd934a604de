"""MAVLink 2 message signing per link, checked in the order the MAVLink spec gives.

A link with a key signs what it sends; by default it also drops unsigned input. The API link may accept
unsigned input instead (MAVSDK cannot sign), but a frame that IS signed must still carry the right signature.

Links with the same key share one SigningRecord (the newest timestamp per stream and the clock), as the
MAVLink C library keeps one record of stream timestamps for all its channels: a signed frame captured on one
link and replayed on another is a replay there too. Each link signs with its own link id.

pymavlink records a stream's timestamp BEFORE it checks the signature, so one forged frame with a
far-future timestamp would lock the real sender out. SigningMAVLink checks the signature first: a link's
per-stream timestamps (and its own clock) advance only on frames that verify. Each frame of a datagram is
judged on its own (a wrong-key frame after junk or after an unsigned frame is still a signed frame).
"""

from __future__ import annotations

import hashlib
import hmac
import time

from pymavlink.dialects.v20 import common as M

from ...errors import UavsearchError

SIGNING_EPOCH = 1420070400  # 2015-01-01 UTC
NEW_STREAM_SLACK = 6_000_000  # 60 s in the signing clock's 10 us units (the spec's window for a new stream)


def parse_signing_key(text: str) -> bytes:
    """32-byte key as 64 hex digits (what `--signing-key` takes)."""
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise UavsearchError("--signing-key must be 64 hexadecimal digits (a 32-byte key)") from None
    if len(key) != 32:
        raise UavsearchError(f"--signing-key must be 32 bytes (64 hex digits), got {len(key)} bytes")
    return key


class SigningRecord:
    """Per key: the newest accepted timestamp of each stream (link id, sysid, compid) and the newest timestamp seen."""

    def __init__(self):
        self.streams: dict = {}
        # MAVLink 2 signing timestamps count 10 us since 2015-01-01 on the wall clock: receivers drop
        # a new stream that starts more than a minute behind their own clock.
        self.clock = int((max(time.time(), SIGNING_EPOCH) - SIGNING_EPOCH) * 1e5)


class SigningMAVLink(M.MAVLink):
    """pymavlink's MAVLink with the spec's order of signature checks (see the module docstring)."""

    frame_signed = False  # whether the frame being decoded carries a signature (allow_unsigned_callback reads it)
    record: SigningRecord | None = None  # shared by the links with this key (enable_signing sets it)

    def decode(self, msgbuf: bytearray):
        self.frame_signed = (len(msgbuf) > 2 and msgbuf[0] == M.PROTOCOL_MARKER_V2
                             and bool(msgbuf[2] & M.MAVLINK_IFLAG_SIGNED))
        return super().decode(msgbuf)

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        sig = self.signing
        digest = hashlib.sha256(sig.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            return False  # a forgery: its timestamp must not count for anything
        tlow, thigh = self.mav_sign_unpacker.unpack(msgbuf[-12:-6])
        timestamp = tlow + (thigh << 32)
        stream = (msgbuf[-13], srcSystem, srcComponent)
        rec = self.record
        last = rec.streams.get(stream)
        if last is not None and timestamp <= last:
            return False  # a replay (on this link or another with the key), or out of order
        if last is None and timestamp + NEW_STREAM_SLACK < rec.clock:
            return False  # a new stream more than a minute behind our clock
        rec.streams[stream] = timestamp
        rec.clock = max(rec.clock, timestamp)
        sig.timestamp = max(sig.timestamp, timestamp)
        return True


def enable_signing(mav: SigningMAVLink, key: bytes, require_signed: bool, record: SigningRecord | None = None,
                   link_id: int = 0) -> None:
    """Sign everything `mav` sends with `link_id`; unless `require_signed`, accept unsigned frames (never badly
    signed ones). `record`: the timestamps shared with the other links that hold this key."""
    mav.record = record if record is not None else SigningRecord()
    mav.signing.secret_key = key
    mav.signing.link_id = link_id & 0xFF
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = mav.record.clock
    if not require_signed:
        mav.signing.allow_unsigned_callback = lambda m, _msgid: not m.frame_signed

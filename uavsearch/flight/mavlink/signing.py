"""MAVLink 2 message signing per link (pymavlink signs and checks; this sets it up as PX4 does).

A link with a key signs what it sends; by default it also drops unsigned input. The API link may accept
unsigned input instead (MAVSDK cannot sign), but a frame that IS signed must still carry the right signature.
"""

from __future__ import annotations

import time
from typing import Callable

from ...errors import UavsearchError

SIGNING_EPOCH = 1420070400  # 2015-01-01 UTC


def parse_signing_key(text: str) -> bytes:
    """32-byte key as 64 hex digits (what `--signing-key` takes)."""
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise UavsearchError("--signing-key must be 64 hexadecimal digits (a 32-byte key)") from None
    if len(key) != 32:
        raise UavsearchError(f"--signing-key must be 32 bytes (64 hex digits), got {len(key)} bytes")
    return key


def frame_is_signed(data: bytes) -> bool:
    """Whether a datagram starts with a MAVLink 2 frame whose incompat flags say 'signed'."""
    return len(data) > 2 and data[0] == 0xFD and bool(data[2] & 0x01)


def enable_signing(mav, key: bytes, require_signed: bool, last_frame_signed: Callable[[], bool]) -> None:
    """Sign everything `mav` sends; unless `require_signed`, accept unsigned frames (never badly signed ones)."""
    mav.signing.secret_key = key
    mav.signing.link_id = 0
    mav.signing.sign_outgoing = True
    # MAVLink 2 signing timestamps count 10 us since 2015-01-01 on the wall clock: receivers drop
    # a new stream that starts more than a minute behind their own clock.
    mav.signing.timestamp = int((max(time.time(), SIGNING_EPOCH) - SIGNING_EPOCH) * 1e5)
    if not require_signed:
        mav.signing.allow_unsigned_callback = lambda _mav, _msgid: not last_frame_signed()

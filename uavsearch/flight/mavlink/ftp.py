"""MAVLink FTP (FILE_TRANSFER_PROTOCOL), answered the way a vehicle without those files answers.

The vehicle serves no files. Ground stations ask anyway: MAVProxy first tries to download parameters as
`@PARAM/param.pck`, QGroundControl asks for component metadata. Without an answer each request times out
(seconds) before the client falls back to the plain protocols; a NAK makes it fall back at once, as PX4's
reply for a file it does not have does. Sessions reset and terminate with an ACK.
"""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as M

from .links import AUTOPILOT_COMPID, Peer

# Opcodes and error codes (MAVLink FTP).
OP_TERMINATE_SESSION, OP_RESET_SESSIONS, OP_LIST_DIRECTORY, OP_OPEN_FILE_RO = 1, 2, 3, 4
OP_CALC_FILE_CRC32 = 14
OP_ACK, OP_NAK = 128, 129
ERR_INVALID_SESSION, ERR_UNKNOWN_COMMAND, ERR_FILE_NOT_FOUND = 4, 7, 10
_NOT_FOUND_OPS = {OP_LIST_DIRECTORY, OP_OPEN_FILE_RO, OP_CALC_FILE_CRC32, 6, 11, 15}  # ... OpenFileWO, CreateDir ...
_SESSION_OPS = {5, 7, 8, 9, 10, 12, 13, 16}  # read, write, remove, truncate, rename, burst read: no open session
_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, padding, offset


class FtpProtocol:
    def __init__(self, ep):
        self.ep = ep
        self.messages = {"FILE_TRANSFER_PROTOCOL": self._on_ftp}

    def _on_ftp(self, peer: Peer, m) -> None:
        if not self.ep.for_me(m.target_system) or m.target_component not in (0, AUTOPILOT_COMPID):
            return
        payload = bytes(m.payload)
        if len(payload) < _HEADER.size:
            return
        seq, session, opcode, _size, _req, _burst, _pad, offset = _HEADER.unpack_from(payload)
        if opcode in (OP_TERMINATE_SESSION, OP_RESET_SESSIONS):
            reply, data = OP_ACK, b""
        elif opcode in _NOT_FOUND_OPS:
            reply, data = OP_NAK, bytes([ERR_FILE_NOT_FOUND])
        elif opcode in _SESSION_OPS:
            reply, data = OP_NAK, bytes([ERR_INVALID_SESSION])
        else:
            reply, data = OP_NAK, bytes([ERR_UNKNOWN_COMMAND])
        out = _HEADER.pack((seq + 1) & 0xFFFF, session, reply, len(data), opcode, 0, 0, offset) + data
        peer.send(M.MAVLink_file_transfer_protocol_message(0, m.get_srcSystem(), m.get_srcComponent(),
                                                           list(out.ljust(251, b"\0"))))

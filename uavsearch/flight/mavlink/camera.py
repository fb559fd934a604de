"""The camera component's protocol (compid 100): its heartbeat, information messages and image capture.

Images travel the MAVLink way: IMAGE_START_CAPTURE is ACKed first (clients wait for the ACK before they
listen for images), then each capture is broadcast as CAMERA_IMAGE_CAPTURED carrying the pose the vehicle
believed it had and the file:// URL of the PNG.
"""

from __future__ import annotations

import math
import shutil

from pymavlink.dialects.v20 import common as M

from ..camera import CAMERA_COMPID, MAX_PENDING, NO_SCENE, Camera, CaptureRecord, CaptureRejected
from ..commander import Result
from .links import Link, Peer
from .streams import message_id

CAMERA_COMMANDS = {
    M.MAV_CMD_IMAGE_START_CAPTURE,
    M.MAV_CMD_IMAGE_STOP_CAPTURE,
    M.MAV_CMD_REQUEST_CAMERA_INFORMATION,
    M.MAV_CMD_REQUEST_CAMERA_SETTINGS,
    M.MAV_CMD_REQUEST_STORAGE_INFORMATION,
    M.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS,
    M.MAV_CMD_SET_CAMERA_MODE,
}
_REQUESTS = {
    M.MAV_CMD_REQUEST_CAMERA_INFORMATION: M.MAVLINK_MSG_ID_CAMERA_INFORMATION,
    M.MAV_CMD_REQUEST_CAMERA_SETTINGS: M.MAVLINK_MSG_ID_CAMERA_SETTINGS,
    M.MAV_CMD_REQUEST_STORAGE_INFORMATION: M.MAVLINK_MSG_ID_STORAGE_INFORMATION,
    M.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS: M.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS,
}


def _disk_mib(path) -> tuple[float, float, float]:
    """(total, used, free) MiB of the disk holding `path` (zeros when it cannot be read)."""
    try:
        u = shutil.disk_usage(path)
    except OSError:
        return 0.0, 0.0, 0.0
    return u.total / 2**20, u.used / 2**20, u.free / 2**20


class CameraProtocol:
    """Serves the camera component's commands and messages for one Camera."""

    def __init__(self, ep, camera: Camera):
        self.ep = ep
        self.camera = camera

    def heartbeat(self, link: Link) -> None:
        link.send(link.mav.heartbeat_encode(M.MAV_TYPE_CAMERA, M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE),
                  CAMERA_COMPID)

    def broadcast_capture(self, rec: CaptureRecord) -> None:
        """CAMERA_IMAGE_CAPTURED to every destination; a failed write or render also says why (STATUSTEXT)."""
        self.ep.broadcast(self._capture_message(rec), CAMERA_COMPID)
        if rec.error and rec.error != NO_SCENE:
            self.ep.statustext(3, f"camera: capture {rec.index} failed: {rec.error}", CAMERA_COMPID)

    def send_notices(self) -> None:
        for text in self.camera.notices:
            self.ep.statustext(4, text, CAMERA_COMPID)
        self.camera.notices.clear()

    def command(self, peer: Peer, m, command: int, p: list) -> None:
        result = self._command(peer, m, command, p)
        if result is not None:
            self.ep.ack(peer, m, command, result, CAMERA_COMPID)

    def _command(self, peer: Peer, m, command: int, p: list) -> Result | None:
        """None when the command was already acknowledged."""
        c = self.camera
        if command == M.MAV_CMD_REQUEST_MESSAGE:
            mid = message_id(p[0])
            if mid is None:
                return Result.DENIED
            msg = self._message(mid)
            if msg is None:
                return Result.UNSUPPORTED
            self.ep.ack(peer, m, command, Result.ACCEPTED, CAMERA_COMPID)
            peer.send(msg, CAMERA_COMPID)
            return None
        if command == M.MAV_CMD_IMAGE_START_CAPTURE:
            if not c.available:
                return Result.FAILED
            try:  # bounded count and interval, checked before anything is promised
                interval, count = c.check_start(p[1], p[2])
            except CaptureRejected as e:
                self.ep.cmd.text(4, f"capture denied: {e}")
                return Result.DENIED
            if c.queue_full:  # refused, never accepted and then skipped: the client knows to try again
                self.ep.cmd.text(4, f"camera busy: {MAX_PENDING} photos rendering, try again")
                return Result.TEMPORARILY_REJECTED
            low = c.low_on_disk() if count != 1 else None
            if low is not None:
                self.ep.cmd.text(4, f"interval capture denied: {low}")
                return Result.DENIED
            # ACK now; the images follow as CAMERA_IMAGE_CAPTURED once rendered (Camera renders in its own
            # thread, the endpoint broadcasts what update() returns): clients wait for the ACK, then listen.
            self.ep.ack(peer, m, command, Result.ACCEPTED, CAMERA_COMPID)
            c.start(interval, count)
            return None
        if command == M.MAV_CMD_IMAGE_STOP_CAPTURE:
            c.stop()
            return Result.ACCEPTED
        if command == M.MAV_CMD_SET_CAMERA_MODE:
            return Result.ACCEPTED if p[1] == M.CAMERA_MODE_IMAGE else Result.DENIED
        req = _REQUESTS.get(command)
        if req is not None:
            self.ep.ack(peer, m, command, Result.ACCEPTED, CAMERA_COMPID)
            peer.send(self._message(req), CAMERA_COMPID)
            return None
        return Result.UNSUPPORTED

    def _message(self, mid: int):
        c = self.camera
        t = self.ep.telemetry.time_boot_ms()
        if mid == M.MAVLINK_MSG_ID_CAMERA_INFORMATION:
            vendor = list(b"uavsearch".ljust(32, b"\0"))
            model = list(f"nadir {c.intrinsics.width_px}x{c.intrinsics.height_px}".encode().ljust(32, b"\0"))[:32]
            sw, sh = c.sensor_size_mm
            return M.MAVLink_camera_information_message(
                t, vendor, model, 1, c.focal_length_mm, sw, sh, c.intrinsics.width_px, c.intrinsics.height_px, 0,
                M.CAMERA_CAP_FLAGS_CAPTURE_IMAGE, 0, b"", 0, 0,
            )
        if mid == M.MAVLINK_MSG_ID_CAMERA_SETTINGS:
            return M.MAVLink_camera_settings_message(t, M.CAMERA_MODE_IMAGE, math.nan, math.nan, 0)
        if mid == M.MAVLINK_MSG_ID_STORAGE_INFORMATION:  # the run directory's disk, in MiB
            total, used, free = _disk_mib(c.run_dir)
            return M.MAVLink_storage_information_message(t, 1, 1, M.STORAGE_STATUS_READY, total, used, free, 100.0,
                                                         100.0, 0, b"run", 0)
        if mid == M.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS:
            return M.MAVLink_camera_capture_status_message(
                t, 3 if c.capturing_interval else 0, 0, float(c.interval_s), 0, _disk_mib(c.run_dir)[2], c.image_count, 0
            )
        return None

    def _capture_message(self, rec: CaptureRecord):
        url = rec.file_url.encode()[:205] if rec.ok else b""
        return M.MAVLink_camera_image_captured_message(
            self.ep.telemetry.time_boot_ms(), int(rec.time_us), 0, int(round(rec.lat_deg * 1e7)),
            int(round(rec.lon_deg * 1e7)), int(round(rec.alt_amsl_m * 1000)), int(round(rec.alt_rel_home_m * 1000)),
            list(rec.q_wxyz), rec.index, 1 if rec.ok else 0, url,
        )

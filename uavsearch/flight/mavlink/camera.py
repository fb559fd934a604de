"""The camera component's protocol (compid 100): its heartbeat, information messages and image capture.

Images travel the MAVLink way: IMAGE_START_CAPTURE is ACKed first (clients wait for the ACK before they
listen for images), then each capture is broadcast as CAMERA_IMAGE_CAPTURED carrying the pose the vehicle
believed it had and the file:// URL of the PNG.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as M

from ..camera import CAMERA_COMPID, Camera, CaptureRecord
from ..commander import Result
from .links import Link

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


class CameraProtocol:
    """Serves the camera component's commands and messages for one Camera."""

    def __init__(self, ep, camera: Camera):
        self.ep = ep
        self.camera = camera

    def heartbeat(self, link: Link) -> None:
        link.send(link.mav.heartbeat_encode(M.MAV_TYPE_CAMERA, M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE),
                  CAMERA_COMPID)

    def broadcast_capture(self, rec: CaptureRecord) -> None:
        self.ep.broadcast(self._capture_message(rec), CAMERA_COMPID)

    def command(self, link: Link, m, command: int, p: list) -> None:
        result = self._command(link, m, command, p)
        if result is not None:
            self.ep.ack(link, m, command, result, CAMERA_COMPID)

    def _command(self, link: Link, m, command: int, p: list) -> Result | None:
        """None when the command was already acknowledged."""
        c = self.camera
        if command == M.MAV_CMD_REQUEST_MESSAGE:
            msg = self._message(int(p[0]) if math.isfinite(p[0]) else -1)
            if msg is None:
                return Result.UNSUPPORTED
            self.ep.ack(link, m, command, Result.ACCEPTED, CAMERA_COMPID)
            link.send(msg, CAMERA_COMPID)
            return None
        if command == M.MAV_CMD_IMAGE_START_CAPTURE:
            if not c.available:
                return Result.FAILED
            interval = p[1] if math.isfinite(p[1]) else 0.0
            count = int(p[2]) if math.isfinite(p[2]) else 1
            if interval < 0 or count < 0:
                return Result.DENIED
            # ACK first, then the capture(s): clients wait for the ACK before listening for images.
            self.ep.ack(link, m, command, Result.ACCEPTED, CAMERA_COMPID)
            link.flush()  # the ACK leaves before the render
            for rec in c.start(interval, count):
                self.broadcast_capture(rec)
            return None
        if command == M.MAV_CMD_IMAGE_STOP_CAPTURE:
            c.stop()
            return Result.ACCEPTED
        if command == M.MAV_CMD_SET_CAMERA_MODE:
            return Result.ACCEPTED if int(p[1]) == M.CAMERA_MODE_IMAGE else Result.DENIED
        req = _REQUESTS.get(command)
        if req is not None:
            self.ep.ack(link, m, command, Result.ACCEPTED, CAMERA_COMPID)
            link.send(self._message(req), CAMERA_COMPID)
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
        if mid == M.MAVLINK_MSG_ID_STORAGE_INFORMATION:
            return M.MAVLink_storage_information_message(t, 1, 1, M.STORAGE_STATUS_READY, 100000.0, 0.0, 100000.0, 100.0,
                                                         100.0, 0, b"run", 0)
        if mid == M.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS:
            return M.MAVLink_camera_capture_status_message(
                t, 3 if c.capturing_interval else 0, 0, float(c.interval_s), 0, 100000.0, c.image_count, 0
            )
        return None

    def _capture_message(self, rec: CaptureRecord):
        url = rec.file_url.encode()[:205] if rec.ok else b""
        return M.MAVLink_camera_image_captured_message(
            self.ep.telemetry.time_boot_ms(), int(rec.time_us), 0, int(round(rec.lat_deg * 1e7)),
            int(round(rec.lon_deg * 1e7)), int(round(rec.alt_amsl_m * 1000)), int(round(rec.alt_rel_home_m * 1000)),
            list(rec.q_wxyz), rec.index, 1 if rec.ok else 0, url,
        )

"""The camera of one System (component 100): the MAVLink camera protocol, as any ground station uses it.

IMAGE_START_CAPTURE -> CAMERA_IMAGE_CAPTURED, which carries the pose the camera reported and a file://
URL of the image; CAMERA_INFORMATION by REQUEST_MESSAGE.
"""

from __future__ import annotations

import urllib.parse
import urllib.request
from pathlib import Path

from .dialect import CAMERA_COMPID, M
from .errors import StepFailed

# A camera whose render queue is full answers TEMPORARILY_REJECTED (it never drops a shot silently): ask
# again this often, this long apart (wall clock: the camera renders on its own threads).
BUSY_RETRIES = 10
BUSY_WAIT_S = 0.2


def image_path(msg) -> Path:
    """The file a CAMERA_IMAGE_CAPTURED's file:// URL names; StepFailed for a URL this client cannot read."""
    url = msg.file_url if isinstance(msg.file_url, str) else bytes(msg.file_url).decode(errors="replace")
    url = url.rstrip("\x00")
    p = urllib.parse.urlparse(url)
    if p.scheme not in ("file", ""):
        raise StepFailed(f"camera image URL {url!r} is not a file:// URL this client can read")
    return Path(urllib.request.url2pathname(p.path))


class Camera:
    def __init__(self, system, compid: int = CAMERA_COMPID):
        self.system, self.compid = system, compid
        self._captured: list = []
        self.photos_asked = 0  # IMAGE_START_CAPTURE commands the camera accepted
        self.photos_received = 0  # CAMERA_IMAGE_CAPTURED answers with a good capture
        system.subscribe("CAMERA_IMAGE_CAPTURED", self._captured.append)

    def take_photo(self, sequence: int, timeout_s: float = 10.0):
        """One picture; its CAMERA_IMAGE_CAPTURED. StepFailed if refused, unanswered or a failed capture."""
        self._captured.clear()
        r = self.system.commands.long(M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, sequence, compid=self.compid)
        for _ in range(BUSY_RETRIES):  # the camera's render queue is full: it renders on, ask again shortly
            if r != M.MAV_RESULT_TEMPORARILY_REJECTED:
                break
            self.system.pump(BUSY_WAIT_S)
            r = self.system.commands.long(M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, sequence, compid=self.compid)
        if r != M.MAV_RESULT_ACCEPTED:
            raise StepFailed(f"camera refused IMAGE_START_CAPTURE (MAV_RESULT {r})")
        self.photos_asked += 1
        msg = self.system.wait_until(lambda: self._captured[-1] if self._captured else None, timeout_s,
                                     "CAMERA_IMAGE_CAPTURED", moving=False)
        if msg.capture_result != 1:
            texts = self.system.last_texts(1)
            raise StepFailed("the camera reported a failed capture" + (f" ({texts})" if texts else ""))
        self.photos_received += 1
        return msg

    def information(self):
        """The camera's CAMERA_INFORMATION (REQUEST_MESSAGE), or None."""
        s = self.system
        return s.request("CAMERA_INFORMATION", lambda: s.mav.command_long_send(
            s.sysid, self.compid, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_CAMERA_INFORMATION, 0, 0, 0, 0, 0, 0))


__all__ = ["Camera", "image_path"]

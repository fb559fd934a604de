"""Mission items as the autopilot stores them, and their feasibility checks.

Items keep MAVLink's MISSION_ITEM_INT layout (so a download returns exactly what was uploaded) and
reuse MAV_CMD / MAV_FRAME numbers; only the MAVLink endpoint turns them into and out of packets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..geometry import GeodeticOrigin, enu_to_ned

# MAV_CMD numbers the navigator executes (internal commands reuse MAVLink's numbering).
NAV_WAYPOINT = 16
NAV_LOITER_UNLIM = 17
NAV_LOITER_TIME = 19
NAV_RETURN_TO_LAUNCH = 20
NAV_LAND = 21
NAV_TAKEOFF = 22
DO_CHANGE_SPEED = 178
DO_SET_HOME = 179
DO_LAND_START = 189  # marks where the landing sequence starts (MAVProxy's `land` jumps there)
IMAGE_START_CAPTURE = 2000

NAV_COMMANDS = {NAV_WAYPOINT, NAV_LOITER_UNLIM, NAV_LOITER_TIME, NAV_RETURN_TO_LAUNCH, NAV_LAND, NAV_TAKEOFF}
DO_COMMANDS = {DO_CHANGE_SPEED, IMAGE_START_CAPTURE, DO_LAND_START}
SUPPORTED_COMMANDS = NAV_COMMANDS | DO_COMMANDS
POSITIONED_COMMANDS = {NAV_WAYPOINT, NAV_LOITER_UNLIM, NAV_LOITER_TIME, NAV_LAND, NAV_TAKEOFF}

# MAV_FRAME numbers.
FRAME_GLOBAL = 0  # AMSL altitude, x/y degrees (float items) or degE7 (int items)
FRAME_MISSION = 2
FRAME_GLOBAL_RELATIVE_ALT = 3
FRAME_GLOBAL_INT = 5
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
SUPPORTED_FRAMES = {FRAME_GLOBAL, FRAME_MISSION, FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_INT, FRAME_GLOBAL_RELATIVE_ALT_INT}
_RELATIVE_FRAMES = {FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_RELATIVE_ALT_INT}


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT: x/y are latitude/longitude in degE7 for global frames."""

    seq: int
    frame: int
    command: int
    current: int = 0
    autocontinue: int = 1
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = math.nan
    x: int = 0
    y: int = 0
    z: float = 0.0

    @property
    def lat_deg(self) -> float:
        return self.x * 1e-7

    @property
    def lon_deg(self) -> float:
        return self.y * 1e-7

    def position_ned(self, origin: GeodeticOrigin, home_ned: np.ndarray) -> np.ndarray | None:
        """Target in the local NED frame, or None for items without a position (lat = lon = 0 means here).

        Relative-altitude frames are above home; global frames are AMSL.
        """
        if self.command not in POSITIONED_COMMANDS or self.frame == FRAME_MISSION:
            return None
        if self.x == 0 and self.y == 0:
            return None
        if self.frame in _RELATIVE_FRAMES:
            alt_amsl = origin.alt_m - float(home_ned[2]) + self.z
        else:
            alt_amsl = self.z
        enu = origin.geodetic_to_enu([self.lat_deg, self.lon_deg, alt_amsl])
        return enu_to_ned(enu)


class MissionItemError(ValueError):
    """An item the autopilot cannot fly; carries the MAV_MISSION_RESULT to answer with."""

    def __init__(self, message: str, mission_result: int):
        super().__init__(message)
        self.mission_result = mission_result


# MAV_MISSION_RESULT numbers.
MISSION_ACCEPTED = 0
MISSION_ERROR = 1
MISSION_UNSUPPORTED_FRAME = 2
MISSION_UNSUPPORTED = 3
MISSION_NO_SPACE = 4
MISSION_INVALID = 5
MISSION_INVALID_SEQUENCE = 13
MISSION_DENIED = 14

MAX_ITEMS = 500  # the vehicle's mission capacity: a larger count is answered MAV_MISSION_NO_SPACE


def check_item(item: MissionItem) -> None:
    """Raise MissionItemError for a command or frame the navigator does not execute."""
    if item.command not in SUPPORTED_COMMANDS:
        raise MissionItemError(f"mission item {item.seq}: command {item.command} not supported", MISSION_UNSUPPORTED)
    if item.frame not in SUPPORTED_FRAMES:
        raise MissionItemError(f"mission item {item.seq}: frame {item.frame} not supported", MISSION_UNSUPPORTED_FRAME)
    if item.command in POSITIONED_COMMANDS and item.frame != FRAME_MISSION:
        if not (-90.0 <= item.lat_deg <= 90.0 and -180.0 <= item.lon_deg <= 180.0) or not math.isfinite(item.z):
            raise MissionItemError(f"mission item {item.seq}: position out of range", MISSION_INVALID)
    if item.command == NAV_LOITER_TIME and not (item.param1 >= 0.0):
        raise MissionItemError(f"mission item {item.seq}: negative loiter time", MISSION_INVALID)


class Mission:
    """The stored mission plus the index of the current item (MISSION_CURRENT's seq)."""

    def __init__(self):
        self.items: list[MissionItem] = []
        self.current_seq = 0
        self.reached_seq = -1
        self.finished = False

    def __len__(self) -> int:
        return len(self.items)

    def replace(self, items: list[MissionItem]) -> None:
        """Store a complete upload (already checked item by item); restarts at the first item."""
        self.items = [replace(it, seq=i) for i, it in enumerate(items)]
        self.current_seq = 0
        self.reached_seq = -1
        self.finished = False

    def clear(self) -> None:
        self.replace([])

    def set_current(self, seq: int) -> bool:
        if not 0 <= seq < len(self.items):
            return False
        self.current_seq = seq
        self.finished = False
        return True

    def land_start_index(self) -> int | None:
        """Where the landing sequence starts: the first DO_LAND_START marker, or None."""
        return next((i for i, it in enumerate(self.items) if it.command == DO_LAND_START), None)

    def positions_ned(self, origin: GeodeticOrigin, home_ned: np.ndarray) -> list[np.ndarray]:
        out = []
        for it in self.items:
            p = it.position_ned(origin, home_ned)
            if p is not None:
                out.append(p)
        return out

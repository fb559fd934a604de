"""QGroundControl `.plan` files: read (validated), turned into the autopilot's mission items, and written.

A `.plan` is what QGC's Plan view saves and opens (JSON, `fileType: "Plan"`, version 1): a mission of
SimpleItems (one MAV_CMD each: command, frame, seven params with NaN as null) and ComplexItems (a survey,
corridor or structure scan, which QGC saves together with the SimpleItems it generated), plus a
geofence and rally points. Reading validates that layout with pydantic and fails with one line naming
the field, e.g. `plan x.plan: mission.items.2.params: List should have at least 7 items`.

The vehicle flies the mission items (`uavsearch.flight.mission`); of the geofence it supports one
inclusion circle around home (as `GF_MAX_HOR_DIST`); polygons and rally points are read and reported,
not uploaded. Every flown search is written back as `flown.plan` so QGC opens it.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..errors import MissionError, format_validation_error
from ..flight.mavlink.wire_units import deg_to_e7
from ..flight.mission import (
    FRAME_GLOBAL_RELATIVE_ALT,
    FRAME_MISSION,
    IMAGE_START_CAPTURE,
    NAV_LAND,
    NAV_RETURN_TO_LAUNCH,
    NAV_TAKEOFF,
    NAV_WAYPOINT,
    SUPPORTED_COMMANDS,
    MissionItem,
)
from .bounded_read import PLAN_MAX_BYTES, parse_json, read_bounded_text

# MISSION_COUNT's count is a uint16: no plan of more items can be sent. A vehicle holds its own number at most
# (the simulated one: flight.mission.MAX_ITEMS) and answers a larger count with MAV_MISSION_NO_SPACE.
PROTOCOL_MAX_ITEMS = 65535


def check_item_count(n: int, source: str) -> None:
    if n > PROTOCOL_MAX_ITEMS:
        raise MissionError(f"plan {source}: {n} mission items; the MAVLink mission protocol carries at most "
                           f"{PROTOCOL_MAX_ITEMS}")

# QGC's numbers for what it writes: MAV_AUTOPILOT_PX4, MAV_TYPE_QUADROTOR, altitude relative to home.
FIRMWARE_PX4 = 12
VEHICLE_QUADROTOR = 2
ALT_MODE_RELATIVE = 1

_GLOBAL_FRAMES = {0, 3, 5, 6, 10, 11}  # x/y are latitude/longitude (degE7 on the wire)
_LOCAL_FRAMES = {1, 4, 7, 8, 9}  # x/y in metres (1e4 on the wire)


class _Open(BaseModel):
    """QGC adds fields over its versions (AltitudeMode, AMSLAltAboveTerrain, ...): keep, don't reject. QGC writes
    an unset parameter as null, never NaN or an infinity (1e999 in JSON): refused."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)


class SimpleItem(_Open):
    type: Literal["SimpleItem"]
    command: int = Field(ge=0, le=65535)
    frame: int = Field(ge=0, le=255)
    params: list[float | None] = Field(min_length=7, max_length=7)
    autoContinue: bool = True
    doJumpId: int | None = None


class ComplexItem(_Open):
    """A survey / corridor / structure scan; flown as the SimpleItems QGC generated and saved with it."""

    type: Literal["ComplexItem"]
    complexItemType: str

    def simple_items(self) -> list[SimpleItem]:
        extra = self.model_extra or {}
        transect = extra.get("TransectStyleComplexItem") or {}
        raw = transect.get("Items") if isinstance(transect, dict) else None
        if raw is None:
            raw = extra.get("Items")
        if not raw:
            raise ValueError(f"complex item '{self.complexItemType}' holds no generated items; "
                             "save the plan again with QGroundControl 4.x")
        return [SimpleItem.model_validate(r) for r in raw]


class PlanMission(_Open):
    version: Literal[2] = 2
    firmwareType: int = FIRMWARE_PX4
    vehicleType: int = VEHICLE_QUADROTOR
    cruiseSpeed: float | None = None
    hoverSpeed: float | None = None
    plannedHomePosition: list[float | None] = Field(min_length=3, max_length=3)
    items: list[SimpleItem | ComplexItem] = Field(min_length=1)


class FenceCircle(_Open):
    center: list[float] = Field(min_length=2, max_length=2)
    radius: float = Field(gt=0)


class FenceCircleItem(_Open):
    circle: FenceCircle
    inclusion: bool = True
    version: int = 1


class FencePolygonItem(_Open):
    polygon: list[list[float]] = Field(min_length=3)
    inclusion: bool = True
    version: int = 1


class GeoFence(_Open):
    version: Literal[2] = 2
    circles: list[FenceCircleItem] = []
    polygons: list[FencePolygonItem] = []


class RallyPoints(_Open):
    version: Literal[2] = 2
    points: list[list[float]] = []


class Plan(_Open):
    fileType: Literal["Plan"]
    version: Literal[1]
    groundStation: str = "QGroundControl"
    mission: PlanMission
    geoFence: GeoFence = GeoFence()
    rallyPoints: RallyPoints = RallyPoints()

    @property
    def home_lla(self) -> tuple[float, float, float] | None:
        lat, lon, alt = self.mission.plannedHomePosition
        if lat is None or lon is None:
            return None
        return float(lat), float(lon), float(alt or 0.0)

    def simple_items(self) -> list[SimpleItem]:
        out: list[SimpleItem] = []
        for it in self.mission.items:
            out.extend(it.simple_items() if isinstance(it, ComplexItem) else [it])
        return out


def _nan(v) -> float:
    return math.nan if v is None else float(v)


def _wire_xy(frame: int, v) -> int:
    if v is None or not math.isfinite(float(v)):
        return 0
    scale = 1e7 if frame in _GLOBAL_FRAMES else 1e4 if frame in _LOCAL_FRAMES else 1.0
    return int(round(float(v) * scale))


def _plan_xy(frame: int, v: int) -> float:
    scale = 1e7 if frame in _GLOBAL_FRAMES else 1e4 if frame in _LOCAL_FRAMES else 1.0
    return v / scale


def to_mission_item(seq: int, s: SimpleItem) -> MissionItem:
    p = s.params
    return MissionItem(seq=seq, frame=s.frame, command=s.command,
                       autocontinue=int(s.autoContinue), param1=_nan(p[0]), param2=_nan(p[1]),
                       param3=_nan(p[2]), param4=_nan(p[3]), x=_wire_xy(s.frame, p[4]), y=_wire_xy(s.frame, p[5]),
                       z=_nan(p[6]))


def mission_items(plan: Plan, source: str = "<plan>") -> list[MissionItem]:
    """The plan's items as the autopilot stores them; one line naming every command it cannot fly."""
    try:
        simple = plan.simple_items()
    except (ValueError, ValidationError) as e:
        raise MissionError(f"plan {source}: {str(e).splitlines()[0]}") from None
    check_item_count(len(simple), source)
    bad = sorted({s.command for s in simple if s.command not in SUPPORTED_COMMANDS})
    if bad:
        raise MissionError(f"plan {source}: the vehicle cannot fly MAV_CMD {bad} "
                           f"(it flies {sorted(SUPPORTED_COMMANDS)})")
    return [to_mission_item(i, s) for i, s in enumerate(simple)]


def plan_from_dict(data: Any, source: str = "<dict>") -> Plan:
    if not isinstance(data, dict):
        raise MissionError(f"plan {source}: not a QGroundControl plan (a JSON object), got {type(data).__name__}")
    items = data.get("mission", {}).get("items") if isinstance(data.get("mission"), dict) else None
    if isinstance(items, list):
        check_item_count(len(items), source)  # before validating 65,536 or more of them
    try:
        return Plan.model_validate(data)
    except ValidationError as e:
        raise MissionError(format_validation_error(e, source, kind="plan")) from None


WPL_HEADER = "QGC WPL 110"


def plan_from_wpl(text: str, source: str = "<wpl>") -> Plan:
    """A MAVProxy / QGC waypoint file (`QGC WPL 110`, tab-separated) as a plan. Its item 0 is the home
    position, not something to fly (the vehicle would descend to it before the take-off item): it becomes
    the plan's home and the items after it are renumbered from 0."""
    rows = [ln.split() for ln in text.splitlines()[1:] if ln.strip()]
    check_item_count(len(rows) - 1, source)  # row 0 is home
    items = []
    for n, r in enumerate(rows, start=2):
        if len(r) != 12:
            raise MissionError(f"waypoints {source} line {n}: {len(r)} fields, a QGC WPL 110 item has 12")
        try:
            seq, _cur, frame, command = (int(v) for v in r[:4])
            p1, p2, p3, p4, lat, lon, alt = (float(v) for v in r[4:11])
            auto = int(r[11])
        except ValueError:
            raise MissionError(f"waypoints {source} line {n}: not a number where QGC WPL 110 has one") from None
        if seq != n - 2:
            raise MissionError(f"waypoints {source} line {n}: item {seq} where item {n - 2} belongs")
        items.append(MissionItem(seq=seq, frame=frame, command=command, autocontinue=auto, param1=p1, param2=p2,
                                 param3=p3, param4=p4, x=_wire_xy(frame, lat), y=_wire_xy(frame, lon), z=alt))
    if len(items) < 2:
        raise MissionError(f"waypoints {source}: no mission items after the home position (item 0)")
    home = items[0]
    flown = [replace(it, seq=i) for i, it in enumerate(items[1:])]
    return plan_from_dict(plan_dict(flown, (home.x * 1e-7, home.y * 1e-7, home.z)), source)


def load_plan(path) -> Plan:
    """Read and validate a `.plan` file (or a `QGC WPL 110` waypoint file, whose item 0 is home)."""
    path = Path(path)
    text = read_bounded_text(path, "plan", PLAN_MAX_BYTES)
    if text.lstrip().startswith(WPL_HEADER):
        return plan_from_wpl(text.lstrip(), str(path))
    return plan_from_dict(parse_json(text, str(path)), str(path))


# --------------------------------------------------------------------------------------------------
# writing


def simple_item_dict(item: MissionItem, jump_id: int) -> dict:
    """One SimpleItem as QGC writes it (NaN as null; Altitude fields on items with a position)."""
    def num(v):
        return None if v is None or not math.isfinite(v) else float(v)

    params = [num(item.param1), num(item.param2), num(item.param3), num(item.param4),
              num(_plan_xy(item.frame, item.x)), num(_plan_xy(item.frame, item.y)), num(item.z)]
    d = {"autoContinue": bool(item.autocontinue), "command": int(item.command), "doJumpId": jump_id,
         "frame": int(item.frame), "params": params, "type": "SimpleItem"}
    if item.frame != FRAME_MISSION:
        d.update({"AMSLAltAboveTerrain": None, "Altitude": num(item.z),
                  "AltitudeMode": ALT_MODE_RELATIVE if item.frame in (3, 6) else 2})
    return d


def plan_dict(items: list[MissionItem], home_lla, cruise_speed_m_s: float = 5.0, hover_speed_m_s: float = 5.0,
              fence_radius_m: float | None = None, rally_points=()) -> dict:
    """A complete `.plan` document (QGC's layout, keys as QGC writes them)."""
    lat, lon, alt = (float(v) for v in home_lla)
    circles = []
    if fence_radius_m:
        circles.append({"circle": {"center": [lat, lon], "radius": float(fence_radius_m)}, "inclusion": True,
                        "version": 1})
    return {
        "fileType": "Plan",
        "geoFence": {"circles": circles, "polygons": [], "version": 2},
        "groundStation": "QGroundControl",
        "mission": {
            "cruiseSpeed": float(cruise_speed_m_s), "firmwareType": FIRMWARE_PX4, "globalPlanAltitudeMode":
            ALT_MODE_RELATIVE, "hoverSpeed": float(hover_speed_m_s),
            "items": [simple_item_dict(it, i + 1) for i, it in enumerate(items)],
            "plannedHomePosition": [lat, lon, alt], "vehicleType": VEHICLE_QUADROTOR, "version": 2,
        },
        "rallyPoints": {"points": [list(map(float, p)) for p in rally_points], "version": 2},
        "version": 1,
    }


def save_plan(path, items: list[MissionItem], home_lla, **kw) -> Path:
    path = Path(path)
    doc = plan_dict(items, home_lla, **kw)
    plan_from_dict(doc, str(path))  # what we write must read back
    path.write_text(json.dumps(doc, indent=4) + "\n")
    return path


def _global_item(seq: int, command: int, lat: float, lon: float, rel_alt_m: float, param1: float = 0.0) -> MissionItem:
    return MissionItem(seq=seq, frame=FRAME_GLOBAL_RELATIVE_ALT, command=command, param1=param1,
                       param4=math.nan, x=deg_to_e7(lat), y=deg_to_e7(lon), z=float(rel_alt_m))


def flown_search_items(home: dict, waypoints_enu, end_action: str = "land") -> list[MissionItem]:
    """The flown search as a mission: take off over the first view, fly to each view and take a photo
    there, then land where the search ended (or return). Flying it re-takes the same photos."""
    from ..geometry import GeodeticOrigin

    origin = GeodeticOrigin(float(home["lat_deg"]), float(home["lon_deg"]), float(home["alt_m"]))
    items: list[MissionItem] = []

    def add(item: MissionItem) -> None:
        items.append(replace(item, seq=len(items)))

    lla = [origin.enu_to_geodetic(p) for p in waypoints_enu]
    if not lla:
        return items
    alt0 = float(waypoints_enu[0][2])
    add(_global_item(0, NAV_TAKEOFF, lla[0][0], lla[0][1], alt0))
    for (lat, lon, _), p in zip(lla, waypoints_enu):
        add(_global_item(0, NAV_WAYPOINT, lat, lon, float(p[2])))
        # IMAGE_START_CAPTURE: all cameras, one image (interval 0, count 1).
        add(MissionItem(seq=0, frame=FRAME_MISSION, command=IMAGE_START_CAPTURE, param1=0.0, param2=0.0,
                        param3=1.0, param4=math.nan))
    if end_action == "rtl":
        add(MissionItem(seq=0, frame=FRAME_MISSION, command=NAV_RETURN_TO_LAUNCH))
    elif end_action == "land":
        lat, lon, _ = lla[-1]
        add(_global_item(0, NAV_LAND, lat, lon, 0.0))
    return items


def write_flown_plan(run_dir, out=None) -> Path | None:
    """`RUN_DIR/flown.plan` from a flight log: the views the search flew, in order; None with no views."""
    from ..logs.flight_log import read_flight_log

    run_dir = Path(run_dir)
    log = read_flight_log(run_dir)
    wps = [s.waypoint_enu for s in log.steps]
    if not wps:
        return None
    mission = log.header.get("mission") or {}
    flight = mission.get("flight") or {}
    home = log.header.get("home") or mission.get("home")
    items = flown_search_items(home, wps, flight.get("end_action", "land"))
    return save_plan(out or run_dir / "flown.plan", items, (home["lat_deg"], home["lon_deg"], home["alt_m"]))


__all__ = ["Plan", "flown_search_items", "load_plan", "mission_items", "plan_dict", "plan_from_dict", "save_plan",
           "write_flown_plan"]

"""`uavsearch mission upload`: send a QGroundControl `.plan` to a vehicle over MAVLink, and fly it.

The upload is the mission protocol any ground station speaks (MISSION_COUNT -> MISSION_REQUEST_INT ->
MISSION_ITEM_INT ... -> MISSION_ACK), through the same pymavlink client `uavsearch fly` uses, so what
works here works from QGC. With `start` the vehicle is armed and MISSION_START flies the plan; the call
returns when it has landed and disarmed, or the mission is complete in the air.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from pymavlink import mavutil

from ..errors import MissionError
from ..flight.mission import NAV_LAND, NAV_RETURN_TO_LAUNCH, MissionItem
from .plan_files import Plan, load_plan, mission_items

M = mavutil.mavlink
MISSION_STATE_COMPLETE = 5


@dataclass
class UploadReport:
    items: int
    notes: list[str] = field(default_factory=list)
    reached: list[int] = field(default_factory=list)
    flown: str = ""


def resolve_plan(path) -> tuple[Plan, str]:
    """A `.plan`, or a mission YAML whose `plan:` names one."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        from .missions import load_mission

        mission = load_mission(path)
        if mission.plan_path is None:
            raise MissionError(f"mission {path}: no 'plan:' field naming a QGroundControl .plan to upload")
        path = mission.plan_path
    return load_plan(path), str(path)


def _send_items(vehicle, items: list[MissionItem], timeout_s: float = 10.0) -> None:
    """The mission protocol's upload, answering the vehicle's requests until its MISSION_ACK."""
    conn = vehicle.conn
    conn.mav.mission_count_send(vehicle.target_system, 1, len(items), M.MAV_MISSION_TYPE_MISSION)
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        m = conn.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], blocking=True,
                            timeout=0.2)
        if m is None or m.get_srcSystem() != vehicle.target_system:
            continue
        if m.get_type() == "MISSION_ACK":
            if m.type != M.MAV_MISSION_ACCEPTED:
                name = M.enums["MAV_MISSION_RESULT"][m.type].name if m.type in M.enums["MAV_MISSION_RESULT"] \
                    else str(m.type)
                texts = "; ".join(vehicle._texts[-1:])
                raise MissionError(f"the vehicle refused the mission: {name}" + (f" ({texts})" if texts else ""))
            return
        if not 0 <= m.seq < len(items):
            continue
        it = items[m.seq]
        conn.mav.mission_item_int_send(vehicle.target_system, 1, it.seq, it.frame, it.command, int(it.seq == 0),
                                       it.autocontinue, it.param1, it.param2, it.param3, it.param4, it.x, it.y,
                                       it.z, M.MAV_MISSION_TYPE_MISSION)
        end = time.monotonic() + timeout_s
    raise MissionError(f"mission upload: no answer from the vehicle within {timeout_s:.0f} s")


def _set_param(vehicle, name: str, value: float, timeout_s: float = 3.0) -> bool:
    seen = []
    hook = (lambda _c, m: seen.append(m) if m.get_type() == "PARAM_VALUE" and m.param_id == name else None)
    vehicle.conn.message_hooks.append(hook)
    try:
        for _ in range(3):
            vehicle.conn.mav.param_set_send(vehicle.target_system, 1, name.encode(), float(value),
                                            M.MAV_PARAM_TYPE_REAL32)
            end = time.monotonic() + timeout_s
            while time.monotonic() < end and not seen:
                vehicle.pump(0.05)
            if seen:
                return abs(seen[-1].param_value - value) < 1e-3 * max(1.0, abs(value))
    finally:
        vehicle.conn.message_hooks.remove(hook)
    return False


def _fence_notes(vehicle, plan: Plan, apply: bool) -> list[str]:
    """Apply what the vehicle supports of the plan's geofence and rally points; say what it skipped."""
    notes = []
    fence = plan.geoFence
    inclusion = [c for c in fence.circles if c.inclusion]
    if inclusion:
        r = min(c.circle.radius for c in inclusion)
        if apply and _set_param(vehicle, "GF_MAX_HOR_DIST", r):
            notes.append(f"geofence: inclusion circle -> GF_MAX_HOR_DIST = {r:g} m (a radius around home)")
        elif apply:
            notes.append("geofence: the vehicle did not take GF_MAX_HOR_DIST")
    skipped = len(fence.circles) - len(inclusion) + len(fence.polygons)
    if skipped:
        notes.append(f"geofence: {skipped} polygon / exclusion shape(s) skipped (the vehicle fences a radius only)")
    if plan.rallyPoints.points:
        notes.append(f"rally points: {len(plan.rallyPoints.points)} skipped (the vehicle returns to home)")
    return notes


def upload_plan(path, connect: str = "udpin:127.0.0.1:14550", start: bool = False, timeout_s: float = 600.0,
                progress=print) -> UploadReport:
    """Upload the plan (and its fence radius); with `start`, arm, fly it, and wait for its end."""
    from .vehicle import FlightError, FlightSettings, MavlinkVehicle

    plan, source = resolve_plan(path)
    items = mission_items(plan, source)
    report = UploadReport(items=len(items))
    settings = FlightSettings(lockstep=False, wall_timeout_s=timeout_s)
    state = {"current": None, "mission_state": None}

    def hook(_c, m):
        t = m.get_type()
        if t == "MISSION_ITEM_REACHED":
            report.reached.append(int(m.seq))
            progress(f"reached item {m.seq}")
        elif t == "MISSION_CURRENT":
            state["current"], state["mission_state"] = int(m.seq), getattr(m, "mission_state", None)

    try:
        vehicle = MavlinkVehicle(connect, settings=settings, progress=progress)
    except FlightError as e:
        raise MissionError(str(e)) from None
    vehicle.conn.message_hooks.append(hook)
    try:
        vehicle.connect()
        report.notes = _fence_notes(vehicle, plan, apply=True)
        for n in report.notes:
            progress(n)
        _send_items(vehicle, items)
        progress(f"uploaded {len(items)} mission item(s) from {source}")
        if start:
            report.flown = _fly(vehicle, items, state, timeout_s, progress)
    except FlightError as e:
        raise MissionError(f"mission {source}: {e}") from None
    finally:
        vehicle.close()
    return report


def _fly(vehicle, items, state, timeout_s: float, progress) -> str:
    from .vehicle import FlightError

    end = time.monotonic() + 30.0
    while (r := vehicle.command_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)) != M.MAV_RESULT_ACCEPTED:
        if time.monotonic() > end:
            raise FlightError(f"arming refused ({'; '.join(vehicle._texts[-2:]) or f'MAV_RESULT {r}'})")
        vehicle.pump(0.2)
    vehicle._wait(lambda: vehicle.armed, 10.0, "arming", moving=False)
    r = vehicle.command_long(M.MAV_CMD_MISSION_START, 0, len(items) - 1)
    if r != M.MAV_RESULT_ACCEPTED:
        raise FlightError(f"mission start refused ({'; '.join(vehicle._texts[-2:]) or f'MAV_RESULT {r}'})")
    progress("mission started")
    t0 = vehicle.sim_time_s

    ends_on_ground = items[-1].command in (NAV_LAND, NAV_RETURN_TO_LAUNCH)

    def done():
        if not vehicle.armed:
            return "landed and disarmed"
        complete = state["mission_state"] == MISSION_STATE_COMPLETE
        return "complete (in the air)" if complete and not ends_on_ground else None

    how = vehicle._wait(done, timeout_s, "mission")
    dt = (vehicle.sim_time_s or 0.0) - (t0 or 0.0)
    progress(f"mission {how} after {dt:.1f} s of flight")
    return how


__all__ = ["UploadReport", "add_mission_parser", "resolve_plan", "upload_plan"]


def _cmd_mission_upload(args) -> int:
    r = upload_plan(args.plan, connect=args.connect, start=args.start, timeout_s=args.timeout,
                    progress=lambda line: print(line, flush=True))
    if args.start:
        print(f"flown: {r.flown}; {len(r.reached)} item(s) reached")
    return 0


def add_mission_parser(sub) -> None:
    """`uavsearch mission upload FILE.plan|MISSION.yaml [--connect URL] [--start]`."""
    p = sub.add_parser("mission", help="QGroundControl .plan missions: upload (and fly) one")
    msub = p.add_subparsers(dest="mission_cmd", required=True, metavar="{upload}")
    up = msub.add_parser("upload", help="upload a .plan (or a mission YAML whose 'plan:' names one) to a vehicle",
                         description="Mission items go up with the MAVLink mission protocol; an inclusion geofence "
                                     "circle becomes GF_MAX_HOR_DIST; polygons and rally points are reported, "
                                     "not uploaded. --start arms, flies the mission and waits for its end.")
    up.add_argument("plan", type=Path, metavar="FILE.plan|MISSION.yaml")
    up.add_argument("--connect", default="udpin:127.0.0.1:14550", metavar="URL",
                    help="the vehicle's link (default udpin:127.0.0.1:14550, the ground-station link of uavsearch sitl)")
    up.add_argument("--start", action="store_true", help="arm, start the mission, wait until landed or complete")
    up.add_argument("--timeout", type=float, default=600.0, metavar="S", help="wall-clock limit (default 600 s)")
    up.set_defaults(func=_cmd_mission_upload)

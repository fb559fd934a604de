"""`uavsearch mission upload`: send a QGroundControl `.plan` to a vehicle over MAVLink, and fly it.

The upload is the mission protocol any ground station speaks (MISSION_COUNT -> MISSION_REQUEST_INT ->
MISSION_ITEM_INT ... -> MISSION_ACK), through the same client `uavsearch fly` uses (its System's mission
and params plugins), so what works here works from QGC. With `start` the vehicle is armed and MISSION_START flies the plan; the call
returns when it has landed and disarmed, or the mission is complete in the air.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..errors import MissionError
from ..flight.mission import NAV_LAND, NAV_RETURN_TO_LAUNCH
from .dialect import M
from .plan_files import Plan, load_plan, mission_items


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


def _fence_notes(vehicle, plan: Plan, apply: bool) -> list[str]:
    """Apply what the vehicle supports of the plan's geofence and rally points; say what it skipped."""
    notes = []
    fence = plan.geoFence
    inclusion = [c for c in fence.circles if c.inclusion]
    if inclusion:
        r = min(c.circle.radius for c in inclusion)
        if apply and vehicle.system.params.set_float("GF_MAX_HOR_DIST", r):
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
                progress=print, system_id: int | None = None) -> UploadReport:
    """Upload the plan (and its fence radius) to `system_id` (None: the first autopilot); with `start`, arm,
    fly it, and wait for its end."""
    from .vehicle import FlightError, FlightSettings, MavlinkVehicle

    plan, source = resolve_plan(path)
    items = mission_items(plan, source)
    report = UploadReport(items=len(items))
    settings = FlightSettings(lockstep=False, wall_timeout_s=timeout_s)
    try:
        vehicle = MavlinkVehicle(connect, settings=settings, progress=progress, system_id=system_id)
    except FlightError as e:
        raise MissionError(str(e)) from None
    try:
        vehicle.connect()
        mission = vehicle.system.mission
        mission.on_reached(lambda seq: progress(f"reached item {seq}"))
        report.notes = _fence_notes(vehicle, plan, apply=True)
        for n in report.notes:
            progress(n)
        try:
            mission.upload(items)
        except MissionError as e:  # MAV_MISSION_NO_SPACE: more items than the vehicle holds
            raise MissionError(f"mission {source}: {e}; {len(items)} item(s) sent") from None
        progress(f"uploaded {len(items)} mission item(s) from {source}")
        if start:
            report.flown = _fly(vehicle, items, timeout_s, progress)
        report.reached = list(mission.reached)
    except FlightError as e:
        raise MissionError(f"mission {source}: {e}") from None
    finally:
        vehicle.close()
    return report


def _fly(vehicle, items, timeout_s: float, progress) -> str:
    """Arm, MISSION_START, and wait until landed and disarmed (or complete in the air)."""
    s = vehicle.system
    vehicle.arm(timeout_s=30.0)
    s.commands.require_long(M.MAV_CMD_MISSION_START, 0, len(items) - 1, what="mission start")
    progress("mission started")
    t0 = vehicle.sim_time_s
    ends_on_ground = items[-1].command in (NAV_LAND, NAV_RETURN_TO_LAUNCH)

    def done():
        if not vehicle.armed:
            return "landed and disarmed"
        return "complete (in the air)" if s.mission.complete and not ends_on_ground else None

    how = s.wait_until(done, timeout_s, "mission", say=progress)
    dt = (vehicle.sim_time_s or 0.0) - (t0 or 0.0)
    progress(f"mission {how} after {dt:.1f} s of flight")
    return how


__all__ = ["UploadReport", "add_mission_parser", "resolve_plan", "upload_plan"]


def _cmd_mission_upload(args) -> int:
    r = upload_plan(args.plan, connect=args.connect, start=args.start, timeout_s=args.timeout,
                    progress=lambda line: print(line, flush=True), system_id=args.system_id)
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
    up.add_argument("--system-id", type=int, default=None, metavar="N",
                    help="the vehicle with MAVLink system id N on the link (default: the first autopilot heard)")
    up.add_argument("--start", action="store_true", help="arm, start the mission, wait until landed or complete")
    up.add_argument("--timeout", type=float, default=600.0, metavar="S", help="wall-clock limit (default 600 s)")
    up.set_defaults(func=_cmd_mission_upload)

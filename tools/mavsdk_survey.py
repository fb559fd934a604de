"""A plain MAVSDK 4.x survey over `uavsearch sitl`, then `uavsearch replay` fuses its photos.

    uavsearch sitl --scene 3 --cells 5 --speed 20     # in one terminal
    python tools/mavsdk_survey.py --scene 3 --replay-out runs/survey_replay

The script flies a lawnmower (boustrophedon) survey over the 50 m x 50 m search area at 70 m with a
photo at every survey point (a MAVLink mission with TAKE_PHOTO items), returns to launch and lands.
Like a ground station it records the telemetry the vehicle sends to the GCS port into a .tlog, and counts
the CAMERA_IMAGE_CAPTURED it hears there: it reports photos received of photos asked (a photo the vehicle
could not take or write arrives with capture_result 0 and counts as failed). The flight can be replayed: `uavsearch replay survey.tlog --scene 3` re-renders each photo's view at the pose
in its CAMERA_IMAGE_CAPTURED and runs perception + fusion on them (no uavsearch code flies this survey).
"""

import argparse
import asyncio
import math
import sys
import threading
import time

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mission import MissionAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.mission import MissionItem, MissionPlan

M_PER_DEG_LAT = 111_200.0


def lawnmower(half_m: float, spacing_m: float) -> list[tuple[float, float]]:
    """(east, north) survey points, row by row from the south-west, alternating direction."""
    n = int(math.floor(2 * half_m / spacing_m + 1e-9)) + 1
    coords = [-half_m + i * spacing_m for i in range(n)]
    points = []
    for row, north in enumerate(coords):
        for east in (coords if row % 2 == 0 else coords[::-1]):
            points.append((east, north))
    return points


class Photos:
    """What the recorder heard of the camera: image indices received, and those that failed."""

    def __init__(self):
        self.ok: set[int] = set()
        self.failed: set[int] = set()

    def hear(self, m) -> None:
        if m.get_type() == "CAMERA_IMAGE_CAPTURED":
            (self.ok if m.capture_result == 1 else self.failed).add(m.image_index)

    @property
    def received(self) -> int:
        return len(self.ok | self.failed)


def record_tlog(path: str, port: int, stop: threading.Event, photos: Photos | None = None) -> None:
    """A passive ground station: every packet the vehicle sends to the GCS port goes into a .tlog."""
    import os

    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    from uavsearch.logs.tlog import TlogWriter

    tlog = TlogWriter(path)
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
    tlog.attach(conn)
    while not stop.is_set():
        m = conn.recv_match(blocking=True, timeout=0.2)
        if m is not None and photos is not None:
            photos.hear(m)
    conn.close()
    tlog.close()


async def survey(url: str, alt_m: float, half_m: float, spacing_m: float) -> int:
    """Fly it; the number of photos asked."""
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        await mavsdk.add_any_connection(url)
        drone = await mavsdk.first_autopilot(30.0)
        if drone is None:
            raise SystemExit(f"no autopilot on {url}: is `uavsearch sitl` running?")
        action, telemetry, mission = ActionAsync(drone), TelemetryAsync(drone), MissionAsync(drone)
        async for ok in telemetry.subscribe_health_all_ok():
            if ok:
                break
        home = await telemetry.home()
        m_per_deg_lon = M_PER_DEG_LAT * math.cos(math.radians(home.latitude_deg))
        points = lawnmower(half_m, spacing_m)
        items = [MissionItem(latitude_deg=home.latitude_deg + n / M_PER_DEG_LAT,
                             longitude_deg=home.longitude_deg + e / m_per_deg_lon,
                             relative_altitude_m=alt_m, speed_m_s=5.0, is_fly_through=False,
                             camera_action=MissionItem.CameraAction.TAKE_PHOTO)
                 for e, n in points]
        await mission.set_return_to_launch_after_mission(True)
        await mission.upload_mission(MissionPlan(items))
        print(f"uploaded a {len(items)}-photo lawnmower survey ({spacing_m:g} m spacing at {alt_m:g} m)", flush=True)
        await action.arm()
        await mission.start_mission()
        async for progress in mission.subscribe_mission_progress():
            print(f"  survey point {progress.current}/{progress.total}", flush=True)
            if progress.current == progress.total:
                break
        print("survey done, returning to launch", flush=True)
        async for armed in telemetry.subscribe_armed():
            if not armed:
                break
        print("landed and disarmed", flush=True)
        return len(items)
    finally:
        mavsdk.destroy()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--url", default="udpin://0.0.0.0:14540", help="MAVSDK connection URL (the sitl's API link)")
    ap.add_argument("--gcs-port", type=int, default=14550, help="the sitl's GCS link port, recorded into --tlog")
    ap.add_argument("--tlog", default="survey.tlog", help="telemetry log to write (default survey.tlog)")
    ap.add_argument("--alt", type=float, default=70.0, help="survey altitude above home, m (default 70)")
    ap.add_argument("--half", type=float, default=20.0, help="survey points span [-half, half] m (default 20)")
    ap.add_argument("--spacing", type=float, default=20.0, help="survey line spacing, m (default 20: 3 x 3 photos)")
    ap.add_argument("--scene", type=int, default=None, help="scene seed the sitl renders (for the replay)")
    ap.add_argument("--setting", type=int, default=2, help="its setting (for the replay, default 2)")
    ap.add_argument("--replay-out", default=None, help="after landing, run `uavsearch replay` into this folder")
    ap.add_argument("--mission", default=None, help="mission file whose perception / fusion the replay uses")
    ap.add_argument("--fusion", default=None, help="fusion method for the replay (default: the mission's)")
    ap.add_argument("--photo-wait", type=float, default=30.0,
                    help="after landing, wait up to this many seconds for photos still rendering (default 30)")
    args = ap.parse_args()
    stop = threading.Event()
    photos = Photos()
    rec = threading.Thread(target=record_tlog, args=(args.tlog, args.gcs_port, stop, photos), daemon=True)
    rec.start()
    asked = 0
    try:
        asked = asyncio.run(survey(args.url, args.alt, args.half, args.spacing))
        end = time.monotonic() + args.photo_wait
        while photos.received < asked and time.monotonic() < end:
            time.sleep(0.1)
    finally:
        stop.set()
        rec.join(timeout=5)
    print(f"photos received {len(photos.ok)} of {asked} asked"
          + (f" ({len(photos.failed)} more reported failed)" if photos.failed else ""), flush=True)
    print(f"telemetry log: {args.tlog}")
    if args.replay_out:
        if args.scene is None:
            raise SystemExit("--replay-out needs --scene SEED (the scene the sitl renders)")
        cmd = ["replay", args.tlog, "--scene", str(args.scene), "--setting", str(args.setting),
               "--out", args.replay_out]
        cmd += ["--mission", args.mission] if args.mission else []
        cmd += ["--fusion", args.fusion] if args.fusion else []
        print("$ uavsearch " + " ".join(cmd), flush=True)
        # In this process, not `python -m uavsearch`: from the folder that holds the clone, `-m` would import
        # the clone's folder (also named uavsearch) instead of the package.
        from uavsearch.cli import main as uavsearch_main

        return uavsearch_main(cmd)
    print(f"replay it: uavsearch replay {args.tlog} --scene SEED --out DIR")
    return 0 if len(photos.ok) == asked else 1


if __name__ == "__main__":
    sys.exit(main())

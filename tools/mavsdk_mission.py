"""MAVSDK 4.x example: upload a square survey mission with a photo at each corner, fly it, return home.

    uavsearch sitl --speed 10         # in one terminal
    python tools/mavsdk_mission.py [--url udpin://0.0.0.0:14540] [--side 10] [--alt 20]

Photos are rendered by the vehicle's camera (compid 100) at each corner; their file:// URLs arrive in
CAMERA_IMAGE_CAPTURED and are printed here.
"""

import argparse
import asyncio
import math

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.camera import CameraAsync
from mavsdk.asyncio.plugins.mission import MissionAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.mission import MissionItem, MissionPlan

M_PER_DEG_LAT = 111_200.0


async def print_photos(camera: CameraAsync) -> None:
    async for info in camera.subscribe_capture_info():
        print(f"  photo {info.index}: {info.file_url} at {info.position.relative_altitude_m:.1f} m")


async def run(url: str, side_m: float, alt_m: float) -> None:
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        await mavsdk.add_any_connection(url)
        drone = await mavsdk.first_autopilot(30.0)
        if drone is None:
            raise SystemExit(f"no autopilot on {url}: is `uavsearch sitl` running?")
        action, telemetry = ActionAsync(drone), TelemetryAsync(drone)
        mission, camera = MissionAsync(drone), CameraAsync(drone)
        async for ok in telemetry.subscribe_health_all_ok():
            if ok:
                break
        home = await telemetry.home()
        m_per_deg_lon = M_PER_DEG_LAT * math.cos(math.radians(home.latitude_deg))
        corners = [(0, 0), (side_m, 0), (side_m, side_m), (0, side_m)]
        items = [MissionItem(latitude_deg=home.latitude_deg + n / M_PER_DEG_LAT,
                             longitude_deg=home.longitude_deg + e / m_per_deg_lon,
                             relative_altitude_m=alt_m, speed_m_s=5.0, is_fly_through=False,
                             camera_action=MissionItem.CameraAction.TAKE_PHOTO)
                 for n, e in corners]
        await mission.set_return_to_launch_after_mission(True)
        await mission.upload_mission(MissionPlan(items))
        print(f"uploaded {len(items)} waypoints ({side_m:g} m square at {alt_m:g} m)")
        photos = asyncio.create_task(print_photos(camera))
        await action.arm()
        await mission.start_mission()
        async for progress in mission.subscribe_mission_progress():
            print(f"  mission item {progress.current}/{progress.total}")
            if progress.current == progress.total:
                break
        print("mission done, returning home")
        async for armed in telemetry.subscribe_armed():
            if not armed:
                break
        photos.cancel()
        print("landed at home and disarmed")
    finally:
        mavsdk.destroy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--url", default="udpin://0.0.0.0:14540", help="MAVSDK connection URL")
    ap.add_argument("--side", type=float, default=10.0, help="side of the square, m")
    ap.add_argument("--alt", type=float, default=20.0, help="altitude above home, m")
    args = ap.parse_args()
    asyncio.run(run(args.url, args.side, args.alt))


if __name__ == "__main__":
    main()

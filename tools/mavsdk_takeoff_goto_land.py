"""MAVSDK 4.x example: connect -> wait healthy -> arm -> takeoff -> goto 10 m north, 10 m up -> land.

    uavsearch sitl --speed 1          # in one terminal (or --speed 10 to watch it faster)
    python tools/mavsdk_takeoff_goto_land.py [--url udpin://0.0.0.0:14540]
"""

import argparse
import asyncio

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

M_PER_DEG_LAT = 111_200.0


async def run(url: str, north_m: float, up_m: float, print=print) -> None:
    """The whole flight on the vehicle at `url`; `print` says each stage (tools/mavsdk_team.py prefixes it)."""
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        await mavsdk.add_any_connection(url)
        drone = await mavsdk.first_autopilot(30.0)
        if drone is None:
            raise SystemExit(f"no autopilot on {url}: is `uavsearch sitl` running?")
        action, telemetry = ActionAsync(drone), TelemetryAsync(drone)
        print(f"system id {await drone.get_system_id()}: waiting for a healthy vehicle (sensors, GPS, home) ...")
        async for ok in telemetry.subscribe_health_all_ok():
            if ok:
                break
        home = await telemetry.home()
        print(f"home {home.latitude_deg:.7f}, {home.longitude_deg:.7f}, {home.absolute_altitude_m:.1f} m AMSL")
        await action.arm()
        await action.takeoff()  # climbs to MIS_TAKEOFF_ALT (action.set_takeoff_altitude changes it)
        async for pos in telemetry.subscribe_position():
            if pos.relative_altitude_m > await action.get_takeoff_altitude() - 0.3:
                break
        print(f"took off: {pos.relative_altitude_m:.1f} m")
        lat = home.latitude_deg + north_m / M_PER_DEG_LAT
        await action.goto_location(lat, home.longitude_deg, home.absolute_altitude_m + up_m, 0.0)
        async for pos in telemetry.subscribe_position():
            if abs(pos.latitude_deg - lat) * M_PER_DEG_LAT < 0.5 and abs(pos.relative_altitude_m - up_m) < 0.5:
                break
        print(f"arrived: {(pos.latitude_deg - home.latitude_deg) * M_PER_DEG_LAT:.1f} m north, {pos.relative_altitude_m:.1f} m up")
        await action.land()
        async for armed in telemetry.subscribe_armed():
            if not armed:
                break
        print("landed and disarmed")
    finally:
        mavsdk.destroy()  # always: a live Mavsdk at interpreter exit can abort the process


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--url", default="udpin://0.0.0.0:14540", help="MAVSDK connection URL")
    ap.add_argument("--north", type=float, default=10.0, help="goto offset north of home, m")
    ap.add_argument("--up", type=float, default=10.0, help="goto altitude above home, m")
    args = ap.parse_args()
    asyncio.run(run(args.url, args.north, args.up))


if __name__ == "__main__":
    main()

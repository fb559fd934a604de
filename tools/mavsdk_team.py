"""MAVSDK 4.x with a team: each vehicle of `uavsearch sitl --vehicles N` flown by its own MAVSDK client at once.

MAVSDK serves one vehicle per connection URL here, as PX4 SITL's multi-vehicle guide does it: vehicle I
(system id I + 1) sends its API link to UDP 14540 + I, so client I listens there. Every client runs
mavsdk_takeoff_goto_land.py's flight (arm, take off, goto, land) concurrently; vehicle I goes to
--north m north of its own home at --up + 5 I m (each its own altitude layer: the sitl refuses a goto
within SIM_SEP_DIST of another vehicle).

    uavsearch sitl --vehicles 3 --speed 1     # in one terminal
    python tools/mavsdk_team.py --vehicles 3  # ports 14540-14542
"""

import argparse
import asyncio
import sys
import time

from mavsdk_takeoff_goto_land import run


async def team(base_port: int, n: int, north_m: float, up_m: float) -> None:
    t0 = time.monotonic()

    def say(i: int):
        return lambda text: print(f"[vehicle {i + 1} :{base_port + i}  {time.monotonic() - t0:5.1f} s] {text}",
                                  flush=True)

    flights = [run(f"udpin://0.0.0.0:{base_port + i}", north_m, up_m + 5.0 * i, print=say(i)) for i in range(n)]
    await asyncio.gather(*flights)
    print(f"all {n} vehicles landed and disarmed in {time.monotonic() - t0:.1f} s wall")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vehicles", type=int, default=3, help="how many (default 3)")
    ap.add_argument("--port", type=int, default=14540, help="vehicle 1's API port; vehicle I's is PORT + I - 1")
    ap.add_argument("--north", type=float, default=10.0, help="goto offset north of each home, m")
    ap.add_argument("--up", type=float, default=10.0, help="vehicle 1's goto altitude above home, m")
    args = ap.parse_args()
    if not 1 <= args.vehicles <= 16:
        sys.exit("--vehicles must be 1..16")
    asyncio.run(team(args.port, args.vehicles, args.north, args.up))


if __name__ == "__main__":
    main()

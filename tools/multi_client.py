"""Many clients on ONE link of `uavsearch sitl`: who gets what, measured.

    python tools/multi_client.py [--clients 8] [--speed 10] [--seconds 10]

Starts `uavsearch sitl` (no camera scene) on free loopback ports and attaches, all at once, N pymavlink
clients (each its own UDP socket, sysid 200 + i, talking first to the API link's port as a script does)
and one MAVSDK client (`udpin://` on the API link's default port, as MAVSDK users connect). Each pymavlink
client asks for the full parameter list once and REQUEST_MESSAGE(AUTOPILOT_VERSION) every 0.5 s, sends a
heartbeat every second and counts what reaches its own socket; MAVSDK connects, finds the autopilot and
uploads a 4-waypoint mission meanwhile (read back with MISSION_REQUEST_LIST). Prints per client: commands asked, COMMAND_ACKs received for
itself and for others, heartbeats per wall second and parameters received; then the totals, MAVSDK's
connect time and upload result, and the machine's load.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

from pymavlink import mavutil

from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.testing.mavlink_client import PeerClient
from uavsearch.testing.mavsdk_session import mavsdk_session

M = mavutil.mavlink


def measure(clients: int, speed: str, seconds: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="multi_") as tmp:
        sitl = SitlProcess(Path(tmp), speed=speed, camera=False)
        try:
            api = sitl.link_address("api")
            peers = [PeerClient(api, sysid=200 + i) for i in range(clients)]
            mavsdk: dict = {}
            thread = threading.Thread(target=mavsdk_session, args=(sitl.api_port, mavsdk))
            thread.start()
            stats = {p.sysid: dict(asked=0, mine=0, others=0, hb=0, params={}, count=0) for p in peers}
            for p in peers:
                p.mav.param_request_list_send(1, 1)
            t0 = time.monotonic()
            next_ask = next_hb = t0
            while time.monotonic() - t0 < seconds:
                now = time.monotonic()
                if now >= next_ask and now - t0 < seconds - 1.0:  # the last second only listens
                    next_ask += 0.5
                    for p in peers:
                        p.mav.command_long_send(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0,
                                                M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
                        stats[p.sysid]["asked"] += 1
                if now >= next_hb:
                    next_hb += 1.0
                    for p in peers:
                        p.send_heartbeat()
                for p in peers:
                    s = stats[p.sysid]
                    for m in p.drain():
                        t = m.get_type()
                        if t == "COMMAND_ACK" and m.command == M.MAV_CMD_REQUEST_MESSAGE:
                            s["mine" if m.target_system == p.sysid else "others"] += 1
                        elif t == "HEARTBEAT" and m.get_srcComponent() == 1:
                            s["hb"] += 1
                        elif t == "PARAM_VALUE":
                            s["params"][m.param_index] = m.param_id
                            s["count"] = m.param_count
                time.sleep(0.002)
            wall = time.monotonic() - t0
            thread.join(60)
            peers[0].mav.mission_request_list_send(1, 1, 0)  # what the vehicle holds after MAVSDK's upload
            end = time.monotonic() + 3
            while time.monotonic() < end and "held" not in mavsdk:
                for m in peers[0].drain():
                    if m.get_type() == "MISSION_COUNT":
                        mavsdk["held"] = m.count
                time.sleep(0.01)
            for p in peers:
                p.close()
        finally:
            code, out = sitl.stop()
        return dict(stats=stats, wall=wall, mavsdk=mavsdk, exit_code=code, traceback="Traceback" in out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, default=8, help="pymavlink clients besides MAVSDK (default 8)")
    ap.add_argument("--speed", default="10", help="sitl --speed (default 10)")
    ap.add_argument("--seconds", type=float, default=10.0, help="wall seconds of traffic (default 10)")
    a = ap.parse_args(argv)
    load0 = os.getloadavg()
    r = measure(a.clients, a.speed, a.seconds)
    load1 = os.getloadavg()
    print(f"{a.clients} pymavlink clients + 1 MAVSDK client on the API link, sitl --speed {a.speed}, "
          f"{r['wall']:.1f} s wall")
    print("| client sysid | commands asked | ACKs to it | ACKs meant for others | heartbeats / wall s | params received |")
    print("|---|---|---|---|---|---|")
    asked = mine = others = 0
    full = 0
    for sysid, s in r["stats"].items():
        asked, mine, others = asked + s["asked"], mine + s["mine"], others + s["others"]
        full += bool(s["count"]) and len(s["params"]) == s["count"]
        print(f"| {sysid} | {s['asked']} | {s['mine']} | {s['others']} | {s['hb'] / r['wall']:.2f} | "
              f"{len(s['params'])} of {s['count']} |")
    md = r["mavsdk"]
    print(f"replies delivered to the asking client: {mine} of {asked} ({100.0 * mine / max(asked, 1):.1f} %); "
          f"ACKs at a client that did not ask: {others}")
    print(f"clients with the full parameter list: {full} of {a.clients}")
    print(f"MAVSDK: autopilot {'found' if md.get('found') else 'NOT found'} in {md.get('connect_s', float('nan')):.2f} s; "
          f"mission upload {md.get('upload', 'not tried')}"
          + (f" in {md['upload_s']:.3f} s" if "upload_s" in md else "")
          + f"; the vehicle then holds {md.get('held', '?')} mission items")
    print(f"vehicle exit code {r['exit_code']}{', printed a traceback' if r['traceback'] else ''}; load average "
          f"{load0[0]:.2f} before, {load1[0]:.2f} after ({os.cpu_count()} CPUs)")
    ok = mine == asked and others == 0 and full == a.clients and md.get("found") and md.get("held") == 4
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

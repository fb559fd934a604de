"""MAVProxy (1.8.75, as installed) flies the vehicle by PX4 mode names; pymavlink's set_mode(name) works.

MAVProxy runs as a real process on the vehicle's ground-station link, driven through its stdin (the same
lines a user types), with `--load-module=uavsearch.mavproxy_px4` for PX4 mode names (MAVProxy 1.8.75's own
`mode NAME` fails inside MAVProxy for every PX4 autopilot: see that module). A separate pymavlink observer
on the API link checks what the vehicle really did. Takeoff, mode changes by name, a mission loaded with
`wp load`, `wp list`, `wp set`, `rtl`, `land` (DO_LAND_START), `arm throttle` and `param` are exercised;
each wait is bounded.
"""

from __future__ import annotations

import re
import time

from uavsearch.flight.sitl_process import SitlProcess, free_udp_port
from uavsearch.testing.clean_env import clean_env
from uavsearch.testing.mavlink_client import Client
from uavsearch.testing.mavproxy_session import MavProxy, Observer, needs_mavproxy


HOME = (47.397742, 8.545594, 488.0)
MODES = {"TAKEOFF": (4, 2), "HOLD": (4, 3), "MISSION": (4, 4), "RTL": (4, 5), "LAND": (4, 6)}


def _wpl(path, alt_m: float = 10.0):
    """A QGC WPL 110 mission: takeoff, then a 12 m square's three corners (frame 3: relative altitude)."""
    lat, lon, _ = HOME
    dlat, dlon = 12 / 111_132.0, 12 / (111_320.0 * 0.6761)
    pts = [(22, lat, lon), (16, lat + dlat, lon), (16, lat + dlat, lon + dlon), (16, lat, lon + dlon)]
    rows = ["QGC WPL 110"] + [f"{i}\t{int(i == 0)}\t3\t{cmd}\t0\t0\t0\t0\t{a:.7f}\t{o:.7f}\t{alt_m}\t1"
                              for i, (cmd, a, o) in enumerate(pts)]
    path.write_text("\n".join(rows) + "\n")


@needs_mavproxy
def test_mavproxy_flies_takeoff_modes_mission_rtl_land_by_name(tmp_path):
    sitl = SitlProcess(tmp_path / "v", gcs_port=free_udp_port(), speed="4", camera=False, env=clean_env())
    mp = obs = None
    try:
        obs = Observer(sitl.api_port)
        mp = MavProxy(sitl.gcs_port, tmp_path)
        t0 = time.monotonic()
        mp.expect(r"online system 1", timeout_s=30, pump=obs.pump)
        print(f"online after {time.monotonic() - t0:.1f} s")
        mp.expect(r"Received \d+ parameters|Parameter download|parameters \(ftp", timeout_s=40, pump=obs.pump)
        print(f"parameters after {time.monotonic() - t0:.1f} s")
        # param show / set
        k = mp.send("param show MIS_TAKEOFF_ALT")
        mp.expect(r"MIS_TAKEOFF_ALT\s+[0-9.]+", k, pump=obs.pump)
        # PX4 reads NAV_TAKEOFF's altitude as AMSL, so MAVProxy's `takeoff 10` (10 m AMSL) is raised to
        # MIS_TAKEOFF_ALT above home, as on PX4 SITL: set that first.
        mp.send("param set MIS_TAKEOFF_ALT 10")
        for attempt in range(10):  # `param show` reads MAVProxy's copy, updated when the PARAM_VALUE arrives
            k = mp.send("param show MIS_TAKEOFF_ALT")
            line = mp.expect(r"MIS_TAKEOFF_ALT\s+[0-9.]+", k, pump=obs.pump)
            if re.search(r"MIS_TAKEOFF_ALT\s+10(\.0*)?$", line):
                break
            time.sleep(0.3)
        else:
            raise AssertionError(f"param set did not take: {line}")
        # a mission file, uploaded and listed back
        _wpl(tmp_path / "square.txt")
        k = mp.send(f"wp load {tmp_path / 'square.txt'}")
        mp.expect(r"Sent all 4 waypoints|Loaded 4 waypoints in", k, pump=obs.pump)
        k = mp.send("wp list")
        mp.expect(r"Saved 4 waypoints|Requesting 4 waypoints", k, pump=obs.pump)
        # arm, take off
        k = mp.send("arm throttle")
        obs.wait(lambda: obs.armed, "armed")
        k = mp.send("takeoff 10")
        obs.wait(lambda: obs.mode == MODES["TAKEOFF"], "TAKEOFF mode")
        obs.wait(lambda: obs.mode == MODES["HOLD"] and obs.rel_alt > 8.0, "takeoff to ~10 m, then Hold", 40)
        # mode changes by PX4 name
        for name, want in (("RTL", "RTL"), ("HOLD", "HOLD"), ("MISSION", "MISSION")):
            k = mp.send(f"mode {name}")
            obs.wait(lambda: obs.mode == MODES[want], f"mode {name} -> {want}")
        obs.wait(lambda: 1 in obs.reached, "mission item 1 reached", 40)
        k = mp.send("wp set 3")
        obs.wait(lambda: obs.current == 3, "wp set 3 -> MISSION_CURRENT 3")
        for name, want in (("LOITER", "HOLD"), ("AUTO", "MISSION")):
            k = mp.send(f"mode {name}")
            obs.wait(lambda: obs.mode == MODES[want], f"mode {name} -> {want}")
        k = mp.send("mode TAKEOFF")  # in the air, at the takeoff altitude already: accepted, done at once -> Hold
        mp.expect(r"DO_SET_MODE: ACCEPTED", k, pump=obs.pump)
        obs.wait(lambda: obs.mode == MODES["HOLD"], "takeoff mode done -> Hold", 30)
        k = mp.send("mode POSCTL")  # PX4 without RC/joystick refuses Position mode, and says why
        mp.expect(r"not available|DENIED", k, pump=obs.pump)
        k = mp.send("mode OFFBOARD")  # PX4 refuses Offboard without a setpoint stream
        mp.expect(r"[Oo]ffboard denied|DENIED", k, pump=obs.pump)
        k = mp.send("rtl")
        obs.wait(lambda: obs.mode == MODES["RTL"], "rtl -> RTL")
        k = mp.send("hold")
        obs.wait(lambda: obs.mode == MODES["HOLD"], "hold -> Hold")
        k = mp.send("land")  # MAV_CMD_DO_LAND_START: no landing sequence in the mission -> land here
        obs.wait(lambda: obs.mode == MODES["LAND"], "land -> LAND")
        assert "UNSUPPORTED" not in mp.output(k)
        obs.wait(lambda: not obs.armed, "touchdown and auto-disarm", 60)
        out = mp.output()
        print(out)
        assert "required argument is not a float" not in out and "Unknown" not in out, out
    finally:
        if mp is not None:
            mp.stop()
        if obs is not None:
            obs.c.close()
        sitl.stop()


def test_pymavlink_set_mode_by_name_always_sees_the_autopilot(tmp_path):
    """pymavlink routes set_mode by the autopilot type of the LAST heartbeat from the system, whatever component
    sent it. The camera's heartbeat (MAV_AUTOPILOT_INVALID) always travels just before the autopilot's in one
    datagram, so after any datagram the client sees PX4 and set_mode('LOITER') sends PX4's numbers."""
    from pymavlink import mavutil

    sitl = SitlProcess(tmp_path / "v", gcs_port=free_udp_port(), speed="1", camera=False, env=clean_env())
    try:
        c = Client(sitl.gcs_port)
        conn = c.connection.mavfile  # pymavlink's own mavfile, under the client
        conn.target_system, conn.target_component = c.sysid, 1
        seen_camera, end = 0, time.monotonic() + 4.0
        while time.monotonic() < end:
            m = conn.recv_match(blocking=True, timeout=0.5)
            if m is None:
                continue
            seen_camera += m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 100
            while conn.recv_match(blocking=False) is not None:  # the rest of what has arrived
                pass
            assert conn.field("HEARTBEAT", "autopilot") == mavutil.mavlink.MAV_AUTOPILOT_PX4
        assert seen_camera >= 2
        conn.set_mode("LOITER")  # pymavlink's name for PX4 Hold
        ack = c.recv("COMMAND_ACK", 5, cond=lambda a: a.command == mavutil.mavlink.MAV_CMD_DO_SET_MODE)
        assert ack is not None and ack.result == mavutil.mavlink.MAV_RESULT_ACCEPTED
    finally:
        sitl.stop()


def test_mavlink_ftp_requests_get_an_answer_at_once(tmp_path):
    """The vehicle serves no files; an FTP request is NAKed at once (MAVProxy's parameter download over FTP
    falls back to PARAM_REQUEST_LIST without waiting for a time-out)."""
    import struct

    sitl = SitlProcess(tmp_path / "v", gcs_port=free_udp_port(), speed="1", camera=False, env=clean_env())
    try:
        c = Client(sitl.gcs_port)
        path = b"@PARAM/param.pck"
        req = struct.pack("<HBBBBBBI", 7, 0, 4, len(path), 0, 0, 0, 0) + path  # OpenFileRO
        c.mav.file_transfer_protocol_send(0, 1, 1, list(req.ljust(251, b"\0")))
        m = c.recv("FILE_TRANSFER_PROTOCOL", 3)
        assert m is not None
        seq, _session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", bytes(m.payload))
        assert (seq, opcode, size, req_opcode, bytes(m.payload)[12]) == (8, 129, 1, 4, 10)  # NAK FileNotFound
    finally:
        sitl.stop()

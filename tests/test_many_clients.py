"""Many clients on one vehicle, as through mavlink-router: real `uavsearch sitl` processes, real UDP on 127.0.0.1.

Eight pymavlink clients (each its own socket, its own sysid) and a MAVSDK client share the API link: every
reply reaches the client that asked and nobody else, every client gets the streams, MAVSDK finds the
autopilot. A second client's mission upload is refused while another runs; a signed frame replayed on the
other link is a replay there too; an unsigned frame never takes a signed peer's place. Storage faults (a
full disk) make failed captures, never a stopped vehicle, and a photo that cannot be queued is refused.
"""

import contextlib
import math
import socket
import struct
import subprocess
import threading
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as v20

from uavsearch.testing.clean_env import clean_env
from uavsearch.testing.mavlink_client import Client, PeerClient
from uavsearch.testing.mavsdk_session import mavsdk_session
from uavsearch.flight.mavlink.links import MAX_PEERS, PEER_TIMEOUT_S, Link, LinkConfig
from uavsearch.flight.params import ParamStore
from uavsearch.flight.sitl_process import RESERVED_FLOOR, SitlProcess, ephemeral_ports, free_udp_port, free_udp_ports

M = mavutil.mavlink
KEY = bytes(range(32))
CLIENTS = 8


def _env(home) -> dict:
    """A vehicle's environment from scratch, its home and temporary files in the test's folder."""
    return clean_env(HOME=str(home), TMPDIR=str(home), LANG="C.UTF-8")


@pytest.fixture(scope="module")
def vehicle(tmp_path_factory):
    """A signing vehicle (the API link accepts unsigned input, as MAVSDK cannot sign), no camera scene."""
    tmp = tmp_path_factory.mktemp("many")
    p = SitlProcess(tmp / "run", "--signing-key", KEY.hex(), speed="4", camera=False, env=_env(tmp))
    yield p
    code, out = p.stop()
    assert code == 0 and "Traceback" not in out, out


def test_every_client_gets_its_own_replies_and_every_stream(vehicle):
    pytest.importorskip("mavsdk.asyncio")
    api = vehicle.link_address("api")
    clients = [PeerClient(api, sysid=200 + i) for i in range(CLIENTS)]
    mavsdk: dict = {}
    t = threading.Thread(target=mavsdk_session, args=(vehicle.api_port, mavsdk, False, 10.0))
    t.start()
    try:
        asks = 5
        got = {c.sysid: {"acks": [], "params": {}, "hb": 0, "count": None} for c in clients}
        for c in clients:
            c.mav.param_request_list_send(1, 1)
        end, next_ask, asked = time.monotonic() + 4.0, 0.0, 0
        while time.monotonic() < end:
            if asked < asks and time.monotonic() >= next_ask:  # all clients at once, five times
                for c in clients:
                    c.mav.command_long_send(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                            0, 0, 0, 0, 0, 0)
                    c.send_heartbeat()
                asked += 1
                next_ask = time.monotonic() + 0.3
            for c in clients:
                g = got[c.sysid]
                for m in c.drain():
                    if m.get_type() == "COMMAND_ACK":
                        g["acks"].append((m.target_system, m.command, m.result))
                    elif m.get_type() == "PARAM_VALUE":
                        g["params"][m.param_index] = m.param_id
                        g["count"] = m.param_count
                    elif m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1:
                        g["hb"] += 1
            time.sleep(0.005)
        t.join(30)
        for sysid, g in got.items():
            assert g["acks"] == [(sysid, M.MAV_CMD_REQUEST_MESSAGE, M.MAV_RESULT_ACCEPTED)] * asks, sysid
            assert g["count"] and sorted(g["params"]) == list(range(g["count"])), sysid
            assert g["hb"] >= 3, sysid  # 4 wall seconds at 4x real time: about 16
        assert mavsdk.get("found"), mavsdk
    finally:
        for c in clients:
            c.close()
        t.join(30)


def test_second_client_mission_upload_is_refused_and_the_first_completes(vehicle):
    api = vehicle.link_address("api")
    first, second = PeerClient(api, sysid=210), PeerClient(api, sysid=211)
    try:
        items = [M.MAVLink_mission_item_int_message(1, 1, i, 3, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, math.nan,
                                                    473977420 + 100 * i, 85455940, 10.0) for i in range(3)]
        first.mav.mission_count_send(1, 1, len(items), 0)
        req = first.wait(lambda m: m.get_type() == "MISSION_REQUEST_INT")
        assert req is not None and req.seq == 0 and req.target_system == 210
        first.mav.send(items[0])
        assert first.wait(lambda m: m.get_type() == "MISSION_REQUEST_INT" and m.seq == 1) is not None
        second.mav.mission_count_send(1, 1, 5, 0)  # meanwhile
        ack = second.wait(lambda m: m.get_type() == "MISSION_ACK")
        assert ack is not None and ack.type == M.MAV_MISSION_DENIED and ack.target_system == 211
        for it in items[1:]:
            first.mav.send(it)
        done = first.wait(lambda m: m.get_type() == "MISSION_ACK")
        assert done is not None and done.type == M.MAV_MISSION_ACCEPTED
        assert not [m for m in second.drain() if m.get_type().startswith("MISSION_REQUEST")]
    finally:
        first.close()
        second.close()


def test_signed_frame_replayed_on_the_other_link_is_dropped(vehicle):
    api, gcs = vehicle.link_address("api"), vehicle.link_address("gcs")
    owner = PeerClient(api, sysid=220, signing_key=KEY)
    try:
        msg = v20.MAVLink_command_long_message(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                             0, 0, 0, 0, 0, 0)
        owner.mav.send(msg)
        captured = bytes(msg.get_msgbuf())  # what anybody on the wire could copy
        assert captured[0] == 0xFD and captured[2] & 1  # a signed MAVLink 2 frame
        assert owner.wait(lambda m: m.get_type() == "COMMAND_ACK") is not None  # accepted where it was sent
        watcher = PeerClient(gcs, sysid=222, signing_key=KEY)  # the key holder on the GCS link sees what happens
        for _ in range(20):
            watcher.conn.port.sendto(captured, gcs)  # the captured frame, replayed from the GCS link's peer
        time.sleep(0.5)
        assert not [m for m in watcher.drain() if m.get_type() == "COMMAND_ACK"]
        watcher.mav.command_long_send(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                      0, 0, 0, 0, 0, 0)
        assert watcher.wait(lambda m: m.get_type() == "COMMAND_ACK") is not None  # the link itself works
        watcher.close()
    finally:
        owner.close()


def test_float_bounds_are_compared_at_float32(vehicle):
    gcs = Client(vehicle.gcs_port)  # the GCS link requires signing: sign as the key holder
    gcs.setup_signing(KEY)
    try:
        gcs.mav.param_set_send(1, 1, b"MC_ROLLRATE_P", 0.01, M.MAV_PARAM_TYPE_REAL32)  # 0.00999999977 on the wire
        v = gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "MC_ROLLRATE_P")
        assert v is not None and v.param_value == pytest.approx(0.01, rel=1e-6)
        gcs.mav.param_set_send(1, 1, b"MC_ROLLRATE_P", 0.15, M.MAV_PARAM_TYPE_REAL32)
        assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "MC_ROLLRATE_P") is not None
    finally:
        gcs.close()


def test_every_float_bound_survives_the_wire():
    from uavsearch.flight.commander import autopilot_params
    from uavsearch.flight.multicopter import MC_PARAMS
    from uavsearch.flight.sitl import SITL_PARAMS

    store = ParamStore(MC_PARAMS, autopilot_params(MC_PARAMS), SITL_PARAMS)
    checked = 0
    for name in store.names():
        d = store.definition(name)
        if d.type != "float" or d.readonly:
            continue
        for bound in (d.min, d.max):
            wire = struct.unpack("<f", struct.pack("<f", bound))[0]
            assert store.set(name, wire) == bound, name  # stored as the bound itself
            checked += 1
        store.set(name, d.default)
    assert checked > 50


def _udp(key: bytes | None = None, sysid: int = 250):
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    mav = v20.MAVLink(None, srcSystem=sysid, srcComponent=190)
    if key is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing = key, True
        mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
    return s, mav


def _heartbeat(mav) -> bytes:
    return bytes(v20.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3).pack(mav))


def test_peer_table_times_out_and_unsigned_frames_never_displace_a_signed_peer():
    link = Link(LinkConfig("api", 0, signing_key=KEY, require_signed=False), sysid=1)
    socks = []
    try:
        signed, smav = _udp(KEY)
        socks.append(signed)
        signed.sendto(_heartbeat(smav), ("127.0.0.1", link.local_port))
        time.sleep(0.05)
        link.receive(now_wall=100.0)
        for i in range(MAX_PEERS + 4):  # a flood of unsigned peers from other ports
            s, mav = _udp(sysid=100 + i)
            socks.append(s)
            s.sendto(_heartbeat(mav), ("127.0.0.1", link.local_port))
        time.sleep(0.05)
        got = link.receive(now_wall=101.0)
        assert len(got) == MAX_PEERS + 4  # every frame is still handled (and could be answered)
        assert len(link.peers) == MAX_PEERS
        assert signed.getsockname() in link.peers and link.peers[signed.getsockname()].signed
        link.expire(101.0 + PEER_TIMEOUT_S + 0.1)
        assert not link.peers  # silent peers are forgotten; streams then go to the default port only
    finally:
        link.close()
        for s in socks:
            s.close()


# ----------------------------------------------------------------------------------------------- storage


@contextlib.contextmanager
def _small_disk(path):
    """A 6 MB tmpfs at `path` when this machine lets us mount one; else None (the test says how it falls back)."""
    path.mkdir(parents=True, exist_ok=True)
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(path)], capture_output=True,
                        env=clean_env()).returncode == 0
    try:
        yield ok
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(path)], capture_output=True, env=clean_env())


def _fill(path) -> None:
    with open(path / "filler", "wb") as f:
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 65536)
                f.flush()


def test_full_disk_makes_failed_captures_and_the_vehicle_keeps_answering(tmp_path):
    """On a real full disk (a filled tmpfs); where mounting is not allowed, captures.jsonl and the images are
    links to /dev/full, a device whose every write fails with ENOSPC, and the free-space floor is raised above
    what the real disk has."""
    disk = tmp_path / "disk"
    with _small_disk(disk) as mounted:
        run = disk / "run"
        run.mkdir()
        if not mounted:
            (run / "images").mkdir()
            (run / "captures.jsonl").symlink_to("/dev/full")
            for i in range(8):
                (run / "images" / f"img_{i:04d}.png").symlink_to("/dev/full")
        floor = [] if mounted else ["--param", "SIM_CAM_FREE_MB=1e7"]
        sitl = SitlProcess(run, "--camera-size", "64x48", *floor, speed="2", gcs_port=0, env=_env(tmp_path))
        try:
            sitl.wait_file("scene.json")
            if mounted:
                _fill(disk)
            api = Client(sitl.api_port)
            try:
                ack = api.command(M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, target_component=100)
                assert ack.result == M.MAV_RESULT_ACCEPTED
                cap = api.recv("CAMERA_IMAGE_CAPTURED", timeout=30)
                assert cap is not None and cap.capture_result == 0 and cap.file_url == ""
                text = api.recv("STATUSTEXT", cond=lambda m: "capture 0 failed" in m.text, timeout=5)
                assert text is not None and "No space left" in text.text
                # The floor is above what this disk has: interval capture is refused.
                ack = api.command(M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0.1, 0, target_component=100)
                assert ack.result == M.MAV_RESULT_DENIED
                api.mav.param_request_read_send(1, 1, b"MPC_XY_P", -1)
                assert api.recv("PARAM_VALUE", cond=lambda m: m.param_id == "MPC_XY_P") is not None
                assert api.wait_heartbeat(5) is not None
            finally:
                api.close()
        finally:
            code, out = sitl.stop()
        assert sitl.proc.returncode is not None and "Traceback" not in out


def test_link_ports_are_never_ones_a_bind_to_port_0_can_take():
    """A vehicle sends to its client's port before the client binds it; meanwhile every bind to port 0 (each
    vehicle's own end of its links, on every test worker) draws from the kernel's ephemeral range. A link's
    port from there could go to another vehicle, whose answers would then reach this client."""
    low, high = ephemeral_ports()
    if low - RESERVED_FLOOR < 1000:
        pytest.skip(f"this kernel's ephemeral UDP ports start at {low}: no room below them")
    busy = 0
    for _ in range(50):
        port = free_udp_port()
        assert RESERVED_FLOOR <= port < low
        base = free_udp_ports(4)
        assert RESERVED_FLOOR <= base and base + 3 < low
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(5)]
        try:
            for sock, p in zip(socks, (port, base, base + 1, base + 2, base + 3)):
                try:
                    sock.bind(("127.0.0.1", p))  # free when handed out
                except OSError:
                    busy += 1  # another test worker drew the same port between the draw and this bind
        finally:
            for sock in socks:
                sock.close()
    assert busy <= 5, f"{busy} of 250 ports handed out were taken: the draw does not check that they are free"
    taken = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(20)]
    try:
        for sock in taken:
            sock.bind(("127.0.0.1", 0))
            assert low <= sock.getsockname()[1] <= high  # what the kernel hands out for port 0
    finally:
        for sock in taken:
            sock.close()


@pytest.fixture(scope="module")
def camera_vehicle(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cam")
    p = SitlProcess(tmp / "run", "--camera-size", "64x48", speed="2", gcs_port=0, env=_env(tmp))
    yield p
    code, out = p.stop()
    assert code == 0 and "Traceback" not in out, out


def test_a_photo_that_cannot_be_queued_is_refused_never_lost(camera_vehicle):
    api = Client(camera_vehicle.api_port)
    try:
        for _ in range(12):  # in one burst: the first renders wait for the scene's world to be built
            api.mav.command_long_send(1, 100, M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 0, 1, 0, 0, 0, 0)
        results = []
        while len(results) < 12:
            m = api.recv("COMMAND_ACK", timeout=10, cond=lambda m: m.command == M.MAV_CMD_IMAGE_START_CAPTURE)
            assert m is not None
            results.append(m.result)
        accepted = results.count(M.MAV_RESULT_ACCEPTED)
        assert set(results) <= {M.MAV_RESULT_ACCEPTED, M.MAV_RESULT_TEMPORARILY_REJECTED}
        assert M.MAV_RESULT_TEMPORARILY_REJECTED in results and accepted >= 1
        images = set()
        while True:
            m = api.recv("CAMERA_IMAGE_CAPTURED", timeout=20)
            if m is None:
                break
            images.add(m.image_index)
            if len(images) == accepted:
                break
        assert len(images) == accepted  # every accepted photo arrives
    finally:
        api.close()


def test_interval_capture_stops_below_the_free_space_floor(camera_vehicle):
    api = Client(camera_vehicle.api_port)
    try:
        ack = api.command(M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0.1, 0, target_component=100)
        assert ack.result == M.MAV_RESULT_ACCEPTED
        api.mav.param_set_send(1, 1, b"SIM_CAM_FREE_MB", 1e7, M.MAV_PARAM_TYPE_REAL32)  # above any disk here
        text = api.recv("STATUSTEXT", cond=lambda m: "interval capture stopped" in m.text, timeout=10)
        assert text is not None
        st_ack = api.command(M.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS, target_component=100)
        assert st_ack.result == M.MAV_RESULT_ACCEPTED
        status = api.recv("CAMERA_CAPTURE_STATUS")
        assert status.image_status == 0  # idle: the series stopped by itself
    finally:
        api.mav.param_set_send(1, 1, b"SIM_CAM_FREE_MB", 200.0, M.MAV_PARAM_TYPE_REAL32)
        api.command(M.MAV_CMD_IMAGE_STOP_CAPTURE, target_component=100)
        api.close()

"""The real `mavsdk` 4.x package flies a real `uavsearch sitl` process (JSBSim, UDP on 127.0.0.1, --speed max).

Two sessions, as a user would write them: connect -> health -> arm -> takeoff -> goto -> photo -> land,
and mission upload -> start -> progress to the end -> return to launch -> disarmed on the ground.
"""

import asyncio
import json
import math
from pathlib import Path

import pytest

from uavsearch.flight.sitl_process import SitlProcess

mavsdk_asyncio = pytest.importorskip("mavsdk.asyncio")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.camera import CameraAsync  # noqa: E402
from mavsdk.asyncio.plugins.mission import MissionAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync  # noqa: E402
from mavsdk.plugins.mission import MissionItem, MissionPlan  # noqa: E402
from uavsearch.testing.clean_env import clean_env

M_PER_DEG_LAT = 111_200.0  # close enough at 47 deg N for offsets of a few metres


async def _first(gen, cond, timeout_s: float):
    """The first item of an async stream that satisfies cond, or a clear failure."""

    async def scan():
        async for x in gen:
            if cond(x):
                return x

    return await asyncio.wait_for(scan(), timeout_s)


def _ned(pv) -> tuple[float, float, float]:
    return pv.position.north_m, pv.position.east_m, pv.position.down_m


async def _connect(port: int):
    md = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    await md.add_any_connection(f"udpin://127.0.0.1:{port}")
    system = await md.first_autopilot(10.0)
    assert system is not None, "no autopilot found"
    return md, system


def _run(coro):
    return asyncio.run(asyncio.wait_for(coro, 120))


def _sitl(tmp_path, camera: bool):
    p = SitlProcess(tmp_path, "--param", "MIS_TAKEOFF_ALT=5", "--param", "RTL_RETURN_ALT=8",
                    "--param", "RTL_DESCEND_ALT=5", camera=camera, env=clean_env())
    yield p
    code, out = p.stop()
    assert code == 0, out


@pytest.fixture
def sitl(tmp_path):
    yield from _sitl(tmp_path, camera=True)


@pytest.fixture
def sitl_no_scene(tmp_path):
    yield from _sitl(tmp_path, camera=False)  # the scene build (a few seconds) is not needed here


def test_mavsdk_takeoff_goto_photo_land(sitl, tmp_path):
    async def flight():
        md, system = await _connect(sitl.api_port)
        try:
            action, tel, cam = ActionAsync(system), TelemetryAsync(system), CameraAsync(system)
            assert await _first(tel.subscribe_health_all_ok(), bool, 20)
            assert await action.get_takeoff_altitude() == pytest.approx(5.0)
            await action.arm()
            await action.takeoff()
            await _first(tel.subscribe_in_air(), bool, 20)
            await _first(tel.subscribe_position(), lambda p: abs(p.relative_altitude_m - 5.0) < 0.3, 30)
            home = await tel.home()
            assert home.relative_altitude_m == pytest.approx(0.0, abs=0.1)
            assert (await tel.flight_mode()).name == "HOLD"

            north_m, up_m = 10.0, 8.0
            target_lat = home.latitude_deg + north_m / M_PER_DEG_LAT
            await action.goto_location(target_lat, home.longitude_deg, home.absolute_altitude_m + up_m, 0.0)
            await _first(
                tel.subscribe_position(),
                lambda p: abs(p.latitude_deg - target_lat) * M_PER_DEG_LAT < 0.5 and abs(p.relative_altitude_m - up_m) < 0.4,
                60,
            )

            cams = await _first(cam.subscribe_camera_list(), lambda cl: len(cl.cameras) > 0, 20)
            assert cams.cameras[0].component_id == 100
            captures = cam.subscribe_capture_info()
            await cam.take_photo(100)
            info = await _first(captures, lambda c: True, 20)
            assert info.is_success and info.index == 0
            # The message carries the ESTIMATED pose; the run dir's record has it beside the TRUE one.
            rec = json.loads((tmp_path / "captures.jsonl").read_text().splitlines()[0])
            assert info.position.latitude_deg == pytest.approx(rec["lat_deg"], abs=2e-7)
            assert info.position.absolute_altitude_m == pytest.approx(rec["alt_amsl_m"], abs=2e-3)
            true_n, true_up = rec["true_position_enu_m"][1], rec["true_position_enu_m"][2]
            est_n = (rec["lat_deg"] - home.latitude_deg) * M_PER_DEG_LAT
            assert 0.0 < abs(est_n - true_n) < 3.0 and abs(true_up - up_m) < 1.5  # close, but not the truth
            assert abs(info.position.relative_altitude_m - up_m) < 1.0  # the estimated pose at the shot
            png = Path(info.file_url.removeprefix("file://"))
            assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
            await cam.start_photo_interval(100, 1.0)  # every simulated second until stopped
            info = await _first(captures, lambda c: c.index == 2, 20)
            await cam.stop_photo_interval(100)
            assert info.is_success and Path(info.file_url.removeprefix("file://")).exists()

            await action.land()
            await _first(tel.subscribe_armed(), lambda armed: not armed, 60)
            assert not await tel.in_air()
            final = await tel.position()
            assert final.relative_altitude_m < 0.5
        finally:
            md.destroy()

    _run(flight())


def test_mavsdk_mission_progress_rtl(sitl_no_scene):
    async def flight():
        md, system = await _connect(sitl_no_scene.api_port)
        try:
            action, tel, mission = ActionAsync(system), TelemetryAsync(system), MissionAsync(system)
            assert await _first(tel.subscribe_health_all_ok(), bool, 20)
            home = await tel.home()
            legs = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0)]
            items = [
                MissionItem(
                    latitude_deg=home.latitude_deg + n / M_PER_DEG_LAT,
                    longitude_deg=home.longitude_deg + e / (M_PER_DEG_LAT * math.cos(math.radians(home.latitude_deg))),
                    relative_altitude_m=8.0,
                    speed_m_s=4.0,
                    is_fly_through=False,
                    camera_action=MissionItem.CameraAction.TAKE_PHOTO if i == 1 else MissionItem.CameraAction.NONE,
                )
                for i, (n, e) in enumerate(legs)
            ]
            await mission.set_return_to_launch_after_mission(False)
            await mission.upload_mission(MissionPlan(items))
            downloaded = await mission.download_mission()
            assert len(downloaded.mission_items) == 3
            assert downloaded.mission_items[1].latitude_deg == pytest.approx(items[1].latitude_deg, abs=1e-7)

            progress = mission.subscribe_mission_progress()
            await action.arm()
            await mission.start_mission()
            seen = []
            last = await _first(progress, lambda p: seen.append(p.current) or p.current == p.total, 90)
            assert last.total == 3 and seen == sorted(seen) and {0, 1, 2, 3} <= set(seen)
            assert await mission.is_mission_finished()
            pos = await tel.position()
            assert abs(pos.relative_altitude_m - 8.0) < 1.0

            await action.return_to_launch()
            await _first(tel.subscribe_flight_mode(), lambda m: m.name == "RETURN_TO_LAUNCH", 10)
            await _first(tel.subscribe_armed(), lambda armed: not armed, 90)
            final = await tel.position()
            assert abs(final.latitude_deg - home.latitude_deg) * M_PER_DEG_LAT < 1.5
            assert final.relative_altitude_m < 0.5
        finally:
            md.destroy()

    _run(flight())



def test_mavsdk_offboard_position_then_hold(sitl_no_scene):
    from mavsdk.asyncio.plugins.offboard import OffboardAsync
    from mavsdk.plugins.offboard import PositionNedYaw

    async def flight():
        md, system = await _connect(sitl_no_scene.api_port)
        try:
            action, tel, offboard = ActionAsync(system), TelemetryAsync(system), OffboardAsync(system)
            assert await _first(tel.subscribe_health_all_ok(), bool, 20)
            await action.arm()
            await offboard.set_position_ned(PositionNedYaw(0.0, 0.0, -5.0, 0.0))  # a setpoint before start
            await offboard.start()
            await _first(tel.subscribe_flight_mode(), lambda m: m.name == "OFFBOARD", 10)
            await offboard.set_position_ned(PositionNedYaw(5.0, 5.0, -5.0, 0.0))
            await _first(tel.subscribe_position_velocity_ned(), lambda pv: math.dist(_ned(pv), (5, 5, -5)) < 0.4, 30)
            await offboard.stop()  # MAVSDK switches to Hold
            await _first(tel.subscribe_flight_mode(), lambda m: m.name == "HOLD", 10)
            held = []  # Hold keeps the vehicle where offboard left it
            await _first(tel.subscribe_position_velocity_ned(), lambda pv: held.append(_ned(pv)) or len(held) >= 30, 20)
            assert max(math.dist(p, (5, 5, -5)) for p in held) < 0.8, held
            await action.land()
            await _first(tel.subscribe_armed(), lambda armed: not armed, 60)
        finally:
            md.destroy()

    _run(flight())

"""A MAVSDK ground station session the tests and tools/multi_client.py share: connect, time how long the
autopilot takes to appear, optionally upload a small mission."""

from __future__ import annotations

import asyncio
import time

M_PER_DEG_LAT = 111_200.0


def mavsdk_session(port: int, out: dict, upload: bool = True, timeout_s: float = 20.0) -> None:
    """Connect, find the autopilot (timed: out['found'], out['connect_s']) and, with `upload`, upload a
    4-item mission (out['upload'], out['upload_s']); what happened goes into `out`, nothing is raised."""
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.mission import MissionAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from mavsdk.plugins.mission import MissionItem, MissionPlan

    async def go():
        md = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            t0 = time.monotonic()
            await md.add_any_connection(f"udpin://127.0.0.1:{port}")
            system = await md.first_autopilot(timeout_s)
            out["connect_s"] = time.monotonic() - t0
            out["found"] = system is not None
            if system is None or not upload:
                return
            home = await asyncio.wait_for(TelemetryAsync(system).home(), 20)
            items = [MissionItem(latitude_deg=home.latitude_deg + n / M_PER_DEG_LAT,
                                 longitude_deg=home.longitude_deg + e / M_PER_DEG_LAT, relative_altitude_m=10.0,
                                 speed_m_s=5.0, is_fly_through=True)
                     for e, n in ((0, 10), (10, 10), (10, 0), (0, 0))]
            t1 = time.monotonic()
            try:
                await asyncio.wait_for(MissionAsync(system).upload_mission(MissionPlan(items)), 30)
                out["upload"] = f"ok ({len(items)} items)"
            except Exception as e:  # noqa: BLE001 - reported, not raised
                out["upload"] = f"failed: {type(e).__name__}: {e}"
            out["upload_s"] = time.monotonic() - t1
        finally:
            md.destroy()

    try:
        asyncio.run(go())
    except Exception as e:  # noqa: BLE001
        out.setdefault("upload", f"failed: {type(e).__name__}: {e}")


__all__ = ["mavsdk_session"]

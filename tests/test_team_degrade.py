"""A team degrades, it does not stop: three simulated vehicles (one `uavsearch sitl --vehicles 3` process, real UDP
on 127.0.0.1, lockstep) search one map; mid-search a second MAVLink client, on vehicle 2's own API port, does to
vehicle 2 what an operator or a failure would (LAND, a force-disarm, a GPS loss). The controller names the vehicle
and why in one line, the other two fly the mission to its end, and vehicle 2's end state is what it did."""

import re
import struct

import pytest
from pymavlink import mavutil

from uavsearch.fly.mission_controller import fly
from uavsearch.fly.missions import load_mission
from uavsearch.logs.flight_log import read_flight_log
from uavsearch.paths import MISSIONS_DIR
from uavsearch.search.team import VehicleOut

MISSION_TIME_S = 40.0
FAULT_AT_S = 6.0  # mission time (the vehicles' clock, from the controller's view lines) of the fault
FORCE_DISARM = 21196.0  # MAV_CMD_COMPONENT_ARM_DISARM param 2: disarm even in the air


def _api_port(run_dir, sysid: int) -> int:
    """Vehicle `sysid`'s API link source port, from the vehicle process's start lines (sitl.log)."""
    text = (run_dir / "sitl.log").read_text()
    after = text[text.index(f"vehicle {sysid} (instance"):]
    return int(re.search(r"API link .*? from 127\.0\.0\.1:(\d+)", after).group(1))


def _inject(run_dir, fault: str) -> None:
    """The fault, sent to system 2 by a client of its own on vehicle 2's API port."""
    link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{_api_port(run_dir, 2)}", source_system=251,
                                      source_component=190)
    m = link.mav
    try:
        for _ in range(3):  # UDP: a few copies (each is idempotent)
            if fault == "land":
                m.command_long_send(2, 1, mavutil.mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, float("nan"),
                                    float("nan"), float("nan"), float("nan"))
            elif fault == "disarm":
                m.command_long_send(2, 1, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, FORCE_DISARM,
                                    0, 0, 0, 0, 0)
            elif fault == "battery":  # a pack of the smallest capacity: what it drew so far empties it
                m.param_set_send(2, 1, b"BAT1_CAPACITY", 50.0, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
            else:  # GPS: int32 parameters travel bytewise in the float, as PX4 sends them
                value = struct.unpack("<f", struct.pack("<i", 1))[0]
                m.param_set_send(2, 1, b"SIM_GPS_BLOCK", value, mavutil.mavlink.MAV_PARAM_TYPE_INT32)
    finally:
        link.close()


@pytest.mark.parametrize("fault, words", [("land", "failsafe: LAND mode"), ("gps", "failsafe: LAND mode"),
                                          ("battery", "failsafe: "), ("disarm", "crashed: disarmed in the air")])
def test_team_flies_on_without_vehicle_2(tmp_path, fault, words):
    mission = load_mission(MISSIONS_DIR / "wide_team.yaml", check_registry=False)
    mission = mission.with_overrides(check_registry=False, **{"flight.speed": "max"}).with_team(
        vehicles=3, mission_time_s=MISSION_TIME_S)
    run, lines, sent = tmp_path / "run", [], []

    def progress(line: str) -> None:
        lines.append(line)
        t = re.search(r"mission time +([\d.]+) s", line)
        if not sent and line.startswith("view") and t and float(t.group(1)) >= FAULT_AT_S:
            sent.append(len([x for x in lines if x.startswith("view")]))
            _inject(run, fault)

    r = fly(mission, out=run, progress=progress, gcs_port=0)
    text = "\n".join(lines)
    assert sent, text[-3000:]
    assert r.status == "completed", text[-3000:]
    left = [x for x in lines if x.startswith("vehicle 2 leaves the search")]
    assert len(left) == 1 and words in left[0], text[-3000:]  # named once, with its reason
    log = read_flight_log(run)
    who = [s.vehicle for s in log.steps]
    n2 = who.count(2)
    assert 2 not in who[sent[0] + 2:]  # no view of vehicle 2 once it left (one may have been on its way)
    assert who[sent[0]:].count(1) >= 2 and who[sent[0]:].count(3) >= 2  # the others fly on
    assert len(who) > sent[0] + 4 and r.steps == len(who) and r.f1 is not None
    views = [s.lattice_idx for s in log.steps]
    assert len(views) == len(set(views))
    summary = log.summary
    assert summary["vehicles_finished"] == 2 and summary["views_per_vehicle"]["2"] == n2
    end2 = summary["vehicle_ends"]["2"]
    assert words in end2 and end2 != "landed"
    assert summary["vehicle_ends"]["1"] == "landed" and summary["vehicle_ends"]["3"] == "landed", text[-3000:]
    assert "vehicle 2: " + end2 in r.end
    # the last view's map is the team's map, vehicle 2's views in it
    assert summary["f1"] == pytest.approx(log.steps[-1].f1, abs=1e-6)


class _Losing:
    """A teleport team's views where vehicle `vehicle` cannot take its view number `at` (counted from 1) nor any
    later one: run_team's VehicleOut, as the flying team's source raises it."""

    per_vehicle = True

    def __init__(self, inner, vehicle: int, at: int):
        self.inner, self.vehicle, self.at, self.seen = inner, vehicle, at, 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def observe(self, idx, vehicle):
        if int(vehicle[0]) == self.vehicle:
            self.seen += 1
            if self.seen >= self.at:
                raise VehicleOut(f"vehicle {self.vehicle + 1}: gone")
        return self.inner.observe(idx)


def test_run_team_goes_on_without_a_lost_vehicle():
    """The episode engine's side: up to the loss the events are the fault-free team's; the lost vehicle never takes
    another view, the others spend the mission time, and its views stay in the map."""
    import dataclasses

    import numpy as np
    import torch

    from uavsearch.search.config import setting_config
    from uavsearch.search.evaluate.team import make_planner
    from uavsearch.search.fusion import FUSIONS
    from uavsearch.search.search_loop import CachedViews
    from uavsearch.search.team import run_team
    from uavsearch.search.wide_policies import footprints
    from uavsearch.testing.synthetic_views import synthetic_cache

    cfg = dataclasses.replace(setting_config("wide"), budget_T=73)
    c = synthetic_cache(1, k=10, seed=3, config=cfg)
    valid = footprints(cfg)[None].clone()
    cache = c._replace(valid=valid, person_px=(c.occupancy[:, None, :] & valid).int() * 5)

    def team(source):
        return run_team(source, FUSIONS["average"](), make_planner("team_entropy:0.8", cfg), 3, 80.0)

    whole = team(CachedViews(cache, np.arange(1), cfg))
    lost = team(_Losing(CachedViews(cache, np.arange(1), cfg), vehicle=1, at=2))
    ev = lost.vehicle[0]
    out = int((ev == 1).nonzero()[-1, 0])  # its last event: it left there, without a view
    assert not bool(lost.taken[0, out]) and out + 1 < len(ev)
    assert lost.taken[0, :out].tolist() == whole.taken[0, :out].tolist()
    assert lost.lattice_idx[0, :out].tolist() == whole.lattice_idx[0, :out].tolist()
    assert int(((ev == 1) & lost.taken[0]).sum()) == 1  # its start view only, and it stays in the map
    after = lost.taken[0, out + 1:]
    assert int(after.sum()) >= 4 and set(ev[out + 1:][after].tolist()) == {0, 2}  # the others fly on
    assert (lost.time_s[0, lost.taken[0]] <= 80.0 + 1e-4).all()
    views = lost.lattice_idx[0, lost.taken[0]].tolist()
    assert len(views) == len(set(views))
    assert int(lost.views()[0]) > out - 1  # more views than it had when it left
    assert torch.isfinite(lost.map_at(80.0)).all()

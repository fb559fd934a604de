"""`uavsearch fly` end to end: real processes (the controller and `uavsearch sitl`), real UDP, real JSBSim.

One SHORT mission (T = 2, --speed max) is flown once for the module; the tests then read what it left:
the console output, the flight log (search.jsonl, telemetry.tlog, images, summary.json) and a replay of
its tlog in the scene. The shipped models are used when they are in models/; otherwise a seeded untrained
perception net stands in (the flight and the log do not depend on the weights).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from pymavlink import mavutil

from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.testing.clean_env import clean_env
from uavsearch.paths import MODELS_DIR
from uavsearch.search.config import ACTIONS
from uavsearch.search.fusion import fuse
from uavsearch.search.metrics import map_accuracy, map_f1

M = mavutil.mavlink
T = 2


def _mission(tmp: Path) -> dict:
    m = {"name": "test_short", "scene": {"seed": 3, "setting": 2}, "search": {"budget_T": T}, "policy_seed": 0,
         "flight": {"speed": "max", "end_action": "land"}}
    if (MODELS_DIR / "perception.pt").is_file() and (MODELS_DIR / "search_s2_learned.pt").is_file():
        m.update(fusion="learned", policy="learned")
    else:
        import torch

        from uavsearch.search.perception import PerceptionNet, save_perception

        torch.manual_seed(0)
        save_perception(PerceptionNet(), tmp / "perception.pt")
        m.update(fusion="bayes", policy="coverage", perception=str(tmp / "perception.pt"))
    return m


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fly")
    mission = _mission(tmp)
    (tmp / "m.yaml").write_text(yaml.safe_dump(mission))
    run = tmp / "run"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(tmp / "m.yaml"), "--out", str(run),
                        "--gcs-port", "0"], capture_output=True, text=True, timeout=240, env=clean_env())
    return r, run, mission


def test_fly_prints_progress_map_and_metrics(flown):
    r, run, _ = flown
    assert r.returncode == 0, r.stdout + r.stderr
    out = r.stdout
    assert "starting uavsearch sitl" in out
    assert "step 1/2  at E" in out and "step 2/2  at E" in out and "cells found" in out
    assert "\nlanded\n" in out
    assert "found" in out and "truth" in out and out.count("\n. ") + out.count("\n# ") + out.count("\n! ") + \
        out.count("\nx ") == 10
    assert "completed: 2 view(s); Aacc" in out and "F1" in out and "sim time" in out and "wall time" in out
    assert "photos 2 of 2 received" in out
    assert str(run) in out
    assert "Traceback" not in r.stderr
    summary = json.loads((run / "summary.json").read_text())
    assert summary["photos_asked"] == 2 and summary["photos_received"] == 2


def test_the_comparison_run_beside_the_flight_is_the_one_run_after_it(flown):
    """The end-of-flight comparison starts once the vehicle has generated the scene and runs beside the flight
    (fly's on_scene): its rows equal those computed from the finished run folder alone, and the flight's own row
    closes the table."""
    from types import SimpleNamespace

    from uavsearch.fly.missions import mission_from_dict
    from uavsearch.fly.scene_baselines import COMPARISON_FILE, compare

    r, run, mission = flown
    assert r.returncode == 0, r.stdout + r.stderr
    beside = json.loads((run / COMPARISON_FILE).read_text())
    summary = json.loads((run / "summary.json").read_text())
    result = SimpleNamespace(run_dir=run, labels=summary["labels"], steps=summary["steps"], acc=summary["acc"],
                             f1=summary["f1"])
    after = json.loads(json.dumps(compare(mission_from_dict(mission, "m.yaml"), result)))
    assert [row["key"] for row in beside["rows"]] == ["first_view", "coverage", "greedy", "teleport_own", "flown"]
    assert beside["rows"][:-1] == after["rows"][:-1]  # the teleport rows, to the bit
    flown_row, again = beside["rows"][-1], after["rows"][-1]  # summary.json keeps 6 decimals of the flight's F1
    assert flown_row.pop("f1") == pytest.approx(again.pop("f1"), abs=1e-6) and flown_row == again
    assert {k: v for k, v in beside.items() if k not in ("rows", "wall_s")} == \
        {k: v for k, v in after.items() if k not in ("rows", "wall_s")}
    assert "hand-written rule" in r.stdout and "this flight" in r.stdout


def test_flight_log_records_every_step(flown):
    _, run, mission = flown
    lines = [json.loads(ln) for ln in (run / "search.jsonl").read_text().splitlines()]
    header, steps = lines[0], [ln for ln in lines if ln["type"] == "step"]
    assert header["type"] == "header" and len(steps) == T
    labels = np.array(header["labels"], dtype=bool)
    assert labels.sum() == 5
    assert steps[0]["waypoint_enu"] == [0.0, 0.0, 70.0]
    move = ACTIONS[steps[0]["action_name"]]
    assert steps[1]["waypoint_enu"] == [10.0 * move[0], 10.0 * move[1], 70.0]
    for s in steps:
        wp, rep = np.array(s["waypoint_enu"]), np.array(s["reported_position_enu"])
        true = np.array(s["true_pose"]["position_enu"])
        assert np.linalg.norm(rep - wp) < 1.0  # settled within the arrival radius (plus drift until the shot)
        assert np.linalg.norm(true - rep) < 3.0  # estimation error: metre-level GPS, not a different place
        assert (run / s["image"]).is_file()
        assert s["sim_time_s"] > 0 and len(s["p_occ"]) == 100 and len(s["fused"]) == 100
    # the log is self-consistent: the logged fused map is the fusion of the logged per-view outputs
    p = np.array([s["p_occ"] for s in steps])
    valid = np.array([s["valid"] for s in steps], dtype=bool)
    kw = {}
    if mission["fusion"] == "learned":
        kw["scores"] = np.array([s["scores"] for s in steps])
    np.testing.assert_allclose(fuse(mission["fusion"], p, valid, **kw), steps[-1]["fused"], atol=1e-5)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["end"] == "landed" and summary["steps"] == T
    assert summary["acc"] == pytest.approx(float(map_accuracy(np.array(steps[-1]["fused"]), labels)), abs=1e-6)
    assert summary["f1"] == pytest.approx(float(map_f1(np.array(steps[-1]["fused"]), labels)), abs=1e-6)
    assert summary["wall_s"] > 0 and summary["sim_time_s"] > 0


def test_tlog_has_the_whole_conversation(flown):
    _, run, _ = flown
    log = mavutil.mavlink_connection(str(run / "telemetry.tlog"), dialect="common")
    sent, got = [], []
    while True:
        m = log.recv_match()
        if m is None:
            break
        (sent if m.get_srcSystem() == 245 else got).append(m)
    cmds = [(m.get_type(), m.command) for m in sent if m.get_type() in ("COMMAND_LONG", "COMMAND_INT")]
    # one goto per view (a command the vehicle acknowledged late may have been re-sent, as MAVSDK does too)
    gotos = {(m.x, m.y) for m in sent if m.get_type() == "COMMAND_INT" and m.command == M.MAV_CMD_DO_REPOSITION}
    assert len(gotos) == T
    assert cmds.count(("COMMAND_LONG", M.MAV_CMD_IMAGE_START_CAPTURE)) == T
    assert ("COMMAND_LONG", M.MAV_CMD_COMPONENT_ARM_DISARM) in cmds and ("COMMAND_LONG", M.MAV_CMD_NAV_LAND) in cmds
    assert sum(m.get_type() == "CAMERA_IMAGE_CAPTURED" for m in got) == T
    ext = [m for m in got if m.get_type() == "EXTENDED_SYS_STATE"]
    assert ext[-1].landed_state == M.MAV_LANDED_STATE_ON_GROUND
    assert max(m.relative_alt for m in got if m.get_type() == "GLOBAL_POSITION_INT") > 69000


def test_replay_the_flight_and_its_tlog(flown, tmp_path):
    r, run, mission = flown
    out = tmp_path / "replay"
    rr = subprocess.run([sys.executable, "-m", "uavsearch", "replay", str(run), "--out", str(out)],
                        capture_output=True, text=True, timeout=120, env=clean_env())
    assert rr.returncode == 0, rr.stderr
    res = json.loads((out / "replay.json").read_text())
    summary = json.loads((run / "summary.json").read_text())
    assert res["views"] == T and res["acc"][-1] == pytest.approx(summary["acc"], abs=1e-6)
    for name in ("trajectory.png", "maps.png", "metrics.png", "replay.gif"):
        assert (out / name).stat().st_size > 1000
    # any tlog: re-render the camera at each CAMERA_IMAGE_CAPTURED in the scene and run perception + fusion
    mfile = run / "m.yaml"
    mfile.write_text(yaml.safe_dump(mission))
    out2 = tmp_path / "replay_tlog"
    rr = subprocess.run([sys.executable, "-m", "uavsearch", "replay", str(run / "telemetry.tlog"), "--scene", "3",
                         "--mission", str(mfile), "--out", str(out2)], capture_output=True, text=True, timeout=120,
                        env=clean_env())
    assert rr.returncode == 0, rr.stderr
    res2 = json.loads((out2 / "replay.json").read_text())
    assert res2["views"] == T and res2["labels"] == res["labels"]
    np.testing.assert_allclose(np.array(res2["positions_enu"])[:, :2], np.array(res["positions_enu"])[:, :2], atol=1.5)



def _without_wall_clock(run: Path) -> list[str]:
    """The flight log's records minus what depends on the wall clock or the run directory's name."""
    out = []
    for line in (run / "search.jsonl").read_text().splitlines():
        rec = {k: v for k, v in json.loads(line).items() if "wall" not in k and k != "started_utc"}
        out.append(json.dumps(rec, sort_keys=True).replace(str(run), "RUN"))
    return out


# a second flight beside a CPU hog (about 14 s); the flight --connect test shows the same determinism by default
@pytest.mark.slow
def test_the_same_mission_flies_the_same_flight_on_a_busy_machine(flown, tmp_path):
    """Lockstep: the seeds fix the flight, whatever else the machine is doing (here: a CPU hog)."""
    r, run, _ = flown
    assert r.returncode == 0, r.stdout + r.stderr
    run2 = tmp_path / "again"
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"], env=clean_env())
    try:
        r2 = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(run.parent / "m.yaml"),
                             "--out", str(run2), "--gcs-port", "0"], capture_output=True, text=True, timeout=240,
                            env=clean_env())
    finally:
        hog.kill()
        hog.wait()
    assert r2.returncode == 0, r2.stdout + r2.stderr
    assert _without_wall_clock(run2) == _without_wall_clock(run)
    images = sorted((run / "images").glob("*.png"))
    assert len(images) == T
    for img in images:
        assert (run2 / "images" / img.name).read_bytes() == img.read_bytes()


def test_connect_to_a_running_vehicle_flies_the_same_flight(flown, tmp_path):
    """--connect: a `uavsearch sitl --lockstep` started by someone else, same scene and seeds -> same flight,
    with the true poses read from the camera's captures.jsonl beside its images."""
    _, run, _ = flown
    sitl = SitlProcess(tmp_path / "vehicle", "--scene", "3", "--cells", "5", lockstep=True, env=clean_env())
    try:
        r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--connect", f"udpin:127.0.0.1:{sitl.api_port}",
                            "--mission", str(run.parent / "m.yaml"), "--out", str(tmp_path / "run")],
                           capture_output=True, text=True, timeout=240, env=clean_env())
    finally:
        sitl.stop()
    assert r.returncode == 0, r.stdout + r.stderr
    assert "starting uavsearch sitl" not in r.stdout and "not be reproducible" not in r.stdout
    steps = [ln for ln in _without_wall_clock(tmp_path / "run") if '"type": "step"' in ln]
    assert len(steps) == T and all('"true_pose": null' not in ln for ln in steps)
    assert steps == [ln for ln in _without_wall_clock(run) if '"type": "step"' in ln]

@pytest.mark.slow
def test_killed_mid_air_leaves_a_readable_log(tmp_path):
    """SIGKILL the controller after its first view: the log reads up to that step, and the vehicle process
    it started goes away with it (PR_SET_PDEATHSIG)."""
    import signal
    import time

    from uavsearch.logs.flight_log import read_flight_log
    from uavsearch.replay.replay import read_tlog

    mission = _mission(tmp_path)
    mission["search"]["budget_T"] = 5
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mission))
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "uavsearch", "fly", "--mission", str(tmp_path / "m.yaml"), "--out",
                             str(run), "--gcs-port", "0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env=clean_env())
    try:
        end = time.monotonic() + 180
        while time.monotonic() < end:
            p = run / "search.jsonl"
            if p.is_file() and '"type":"step"' in p.read_text():
                break
            time.sleep(0.1)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    log = read_flight_log(run)
    assert len(log.steps) >= 1 and log.steps[0].waypoint_enu == [0.0, 0.0, 70.0]
    assert log.summary["status"] == "running"  # provisional: never rewritten, so the flight was killed
    assert log.summary["kept"]["views"] in (len(log.steps) - 1, len(log.steps))  # (killed between the two writes)
    tr = read_tlog(run / "telemetry.tlog")
    assert len(tr.captures) >= 1 and tr.lla[:, 2].max() > 488.0 + 69.0
    time.sleep(2)
    sitl_log = (run / "sitl.log").read_text()
    out = subprocess.run(["pgrep", "-f", f"uavsearch.flight.sitl.*{run}"], capture_output=True, text=True,
                         env=clean_env())
    assert out.stdout.strip() == "", sitl_log


@pytest.mark.slow
def test_a_step_that_does_not_settle_fails_cleanly_and_lands(tmp_path):
    mission = _mission(tmp_path)
    mission["flight"]["step_timeout_s"] = 0.2  # no goto settles (0.5 m, 0.3 m/s for 0.5 s) this fast
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mission))
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(tmp_path / "m.yaml"), "--out", str(run),
                        "--gcs-port", "0"], capture_output=True, text=True, timeout=240, env=clean_env())
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert "step 1 failed: goto [0.0, 0.0, 70.0]: not done after 0.2 s of flight" in r.stdout
    assert "\nlanded\n" in r.stdout
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"].startswith("failed: goto") and summary["end"] == "landed" and summary["steps"] == 0


def test_flown_search_opens_as_a_plan(flown):
    """Every flight leaves flown.plan: take off, each view with a photo, then the end action, in QGC's format."""
    from uavsearch.fly.plan_files import load_plan, mission_items

    _, run, _ = flown
    steps = [json.loads(x) for x in (run / "search.jsonl").read_text().splitlines()[1:]]
    items = mission_items(load_plan(run / "flown.plan"))
    assert [i.command for i in items] == [22] + [16, 2000] * T + [21]
    home = json.loads((run / "mission.json").read_text())["home"]
    from uavsearch.geometry import GeodeticOrigin

    origin = GeodeticOrigin(home["lat_deg"], home["lon_deg"], home["alt_m"])
    for wp, step in zip([i for i in items if i.command == 16], steps):
        enu = origin.geodetic_to_enu([wp.lat_deg, wp.lon_deg, home["alt_m"] + wp.z])
        np.testing.assert_allclose(enu, step["waypoint_enu"], atol=0.02)


def test_flight_review_page_renders_in_chromium(flown, tmp_path):
    """`replay RUN --html` writes one self-contained page; headless Chromium renders it without console
    errors, and its plots hold what the telemetry log holds (read here independently with pymavlink)."""
    import os
    import shutil

    from headless_chromium import chromium_or_skip, close, open_page

    _, run, _ = flown
    page, shot = tmp_path / "review.html", tmp_path / "review.png"
    rr = subprocess.run([sys.executable, "-m", "uavsearch", "replay", str(run), "--html", str(page)],
                        capture_output=True, text=True, timeout=120, env=clean_env())
    assert rr.returncode == 0, rr.stderr
    # the log, independently
    home = json.loads((run / "mission.json").read_text())["home"]
    log = mavutil.mavlink_connection(str(run / "telemetry.tlog"), dialect="common")
    pos, att, texts, modes, truth = [], 0, [], [], 0
    while (m := log.recv_match()) is not None:
        if m.get_srcSystem() != 1:
            continue
        if m.get_type() == "GLOBAL_POSITION_INT":
            pos.append((m.time_boot_ms * 1e-3, m.alt * 1e-3 - home["alt_m"]))
        elif m.get_type() == "ATTITUDE":
            att += 1
        elif m.get_type() == "SIM_STATE":
            truth += 1
        elif m.get_type() == "STATUSTEXT":
            texts.append(m.text)
        elif m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1:
            modes.append(((m.custom_mode >> 16) & 0xFF, (m.custom_mode >> 24) & 0xFF))
    log.close()
    drv = chromium_or_skip()
    try:
        severe, plots = open_page(drv, page, shot)
        # self-contained: plotly.js inlined, images as data URIs, nothing loaded from elsewhere
        external = drv.execute_script("return document.querySelectorAll('script[src], link[href], img[src]').length")
        # a bare .tlog gets the same page without the per-view panels
        tlog_page = tmp_path / "tlog.html"
        rr = subprocess.run([sys.executable, "-m", "uavsearch", "replay", str(run / "telemetry.tlog"), "--html",
                             str(tlog_page)], capture_output=True, text=True, timeout=120, env=clean_env())
        assert rr.returncode == 0, rr.stderr
        tlog_severe, tlog_plots = open_page(drv, tlog_page, tmp_path / "tlog.png")
    finally:
        close(drv)
    assert external == 0
    assert tlog_severe == [] and len(tlog_plots) == 2
    assert {t["name"]: len(t["x"]) for t in tlog_plots[1]["traces"]}["altitude (estimate)"] == len(pos)
    if os.environ.get("UAVSEARCH_SCREENSHOT_DIR"):
        shutil.copy(shot, Path(os.environ["UAVSEARCH_SCREENSHOT_DIR"]) / "flight_review.png")
    assert severe == [], severe
    assert len(plots) == 4 and all(p["svg_paths"] > 0 for p in plots)
    series = {t["name"]: t for t in plots[1]["traces"]}
    alt = series["altitude (estimate)"]
    np.testing.assert_allclose(alt["x"], [p[0] for p in pos], atol=1e-6)
    np.testing.assert_allclose(alt["y"], [p[1] for p in pos], atol=0.02)  # ENU up vs AMSL - home over < 100 m
    assert len(series["roll"]["y"]) == att and len(series["N velocity"]["y"]) == len(pos)
    assert len(series["STATUSTEXT"]["x"]) == len(texts) > 0
    assert len(series["horizontal, estimate - truth"]["y"]) == truth > 0  # the client asked for SIM_STATE
    assert max(series["horizontal, estimate - truth"]["y"][10:]) < 3.0  # the EKF stays within metres of the truth
    assert {"TAKEOFF", "LAND"} <= set(plots[1]["annotations"]) and (4, 2) in modes and (4, 6) in modes
    steps = plots[2]
    assert steps["sliders"] == [T] and sum(t["type"] == "image" and t["source"] > 1000 for t in steps["traces"]) == T
    summary = json.loads((run / "summary.json").read_text())
    fused_last = [t for t in steps["traces"] if t["name"] == f"fused {T}"][0]["z"]
    np.testing.assert_allclose(np.array(fused_last).ravel(), summary["fused"], atol=1e-5)
    assert shot.stat().st_size > 50_000


def _vehicle_pid(run: Path) -> int | None:
    out = subprocess.run(["pgrep", "-f", f"uavsearch.flight.sitl.*{run}"], capture_output=True, text=True,
                         env=clean_env())
    pids = [int(p) for p in out.stdout.split()]
    return pids[0] if pids else None


def test_a_killed_vehicle_is_one_line_within_3_s(tmp_path):
    """kill -9 of the vehicle mid-mission: fly says so at once (how it died, the step, its log), exits non-zero."""
    import signal
    import time

    mission = _mission(tmp_path)
    mission["search"]["budget_T"] = 5
    mission["flight"]["speed"] = 3  # 3x real time: about 2 s of wall time between views, the kill lands mid-mission
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mission))
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "uavsearch", "fly", "--mission", str(tmp_path / "m.yaml"), "--out",
                             str(run), "--gcs-port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=clean_env())
    try:
        end = time.monotonic() + 180
        while time.monotonic() < end and not ((run / "search.jsonl").is_file()
                                              and '"type":"step"' in (run / "search.jsonl").read_text()):
            time.sleep(0.1)
        pid = _vehicle_pid(run)
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        out, err = proc.communicate(timeout=30)
        took = time.monotonic() - killed
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, out + err
    assert took < 3.0, f"{took:.1f} s"
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "vehicle lost at step 2 of 5" in err and "killed by SIGKILL" in err and str(run / "sitl.log") in err
    assert (run / "sitl.log").is_file() and (run / "search.jsonl").is_file()
    assert "not acknowledged" not in out + err


@pytest.fixture
def tiny_disk(tmp_path):
    """A 640 KiB tmpfs: room for the scene and two or three images of a flight, not for all of it."""
    where = tmp_path / "disk"
    where.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=640k", "tmpfs", str(where)], capture_output=True,
                       env=clean_env())
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    yield where
    # the vehicle process may still be closing its files: detach the mount now, it goes when they are closed
    subprocess.run(["umount", "-l", str(where)], capture_output=True, env=clean_env())


def test_a_full_disk_is_one_line_and_keeps_what_was_recorded(tmp_path, tiny_disk):
    mission = _mission(tmp_path)
    mission["search"]["budget_T"] = 5
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mission))
    run = tiny_disk / "run"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(tmp_path / "m.yaml"), "--out",
                        str(run), "--gcs-port", "0"], capture_output=True, text=True, timeout=300, env=clean_env())
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "no space left on device" in r.stderr and str(tiny_disk) in r.stderr
    assert "the camera reported a failed capture" not in r.stdout
    assert "\nlanded\n" in r.stdout
    from uavsearch.logs.flight_log import read_flight_log

    log = read_flight_log(run)
    assert log.header["mission"]["name"] == mission["name"]  # what it recorded is kept
    # the summary is kept (the reserve made room for it) and says what was kept
    assert log.summary["status"].startswith("failed: no space left on device"), log.summary["status"]
    kept = log.summary["kept"]
    assert kept["views"] == len(log.steps) and kept["tlog_bytes"] == (run / "telemetry.tlog").stat().st_size > 0
    assert kept["photos"] == sum(1 for p in run.glob("**/images/*.png") if p.stat().st_size > 0)
    assert not list(run.glob(".summary*")), list(run.glob(".summary*"))  # no reserve, no temporary file left


def test_a_torn_log_s_review_page_warns_in_one_line(flown, tmp_path):
    """`replay --html` on a damaged search.jsonl says so as plain replay does: one line, no Python warning."""
    import shutil

    _, run, _ = flown
    d = tmp_path / "torn"
    shutil.copytree(run, d)
    text = (d / "search.jsonl").read_text()
    (d / "search.jsonl").write_text(text[: len(text) - 40])  # killed while writing the last record
    r = subprocess.run([sys.executable, "-m", "uavsearch", "replay", str(d), "--html", str(tmp_path / "p.html")],
                       capture_output=True, text=True, timeout=300, env=clean_env())
    assert r.returncode == 0, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("uavsearch: warning: ") and "damaged at line" in lines[0], r.stderr
    assert "UserWarning" not in r.stderr and (tmp_path / "p.html").is_file()


def test_compare_flights_ignores_the_folder_a_run_lay_in(flown, tmp_path):
    """tools/compare_flights.py: the same flight in another folder (captures.jsonl records image paths and
    file:// URLs into its run folder) is the same; --compare-paths and a changed image are differences."""
    import shutil

    _, run, _ = flown
    copy = tmp_path / "elsewhere" / "run"
    shutil.copytree(run, copy)
    # as a flight into that folder records it: its own paths, as given and as file:// URLs
    caps = (copy / "captures.jsonl").read_text()
    assert str(run) in caps
    (copy / "captures.jsonl").write_text(caps.replace(str(run), str(copy)))

    def compare(*args):
        return subprocess.run([sys.executable, "tools/compare_flights.py", str(run), str(copy), *args],
                              capture_output=True, text=True, timeout=60, env=clean_env(),
                              cwd=Path(__file__).resolve().parents[1])

    r = compare()
    assert r.returncode == 0, r.stdout + r.stderr
    assert "run-folder paths ignored" in r.stdout
    r = compare("--compare-paths")
    assert r.returncode == 1 and "captures.jsonl       differs" in r.stdout, r.stdout + r.stderr
    img = sorted((copy / "images").glob("*.png"))[0]
    img.write_bytes(img.read_bytes()[:-1] + b"\0")
    r = compare()
    assert r.returncode == 1 and f"images/{img.name}  differs  image bytes" in r.stdout, r.stdout + r.stderr


def test_a_flown_run_exports_as_a_coco_dataset_whose_boxes_hold_its_people(flown, tmp_path):
    """`uavsearch dataset export --run`: the flight's own photos, each labelled from its true camera pose; every
    box holds its person's projection, and every labelled person on the grid stands in an occupied cell in view."""
    pytest.importorskip("pycocotools")
    import cv2
    from pycocotools.coco import COCO

    from uavsearch.geometry import CameraIntrinsics, CameraPose, project_points

    _, run, _ = flown
    out = tmp_path / "ds"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "dataset", "export", "--run", str(run), "--format", "coco",
                        "--out", str(out)], capture_output=True, text=True, timeout=240, env=clean_env())
    assert r.returncode == 0, r.stdout + r.stderr
    coco = COCO(str(out / "coco_annotations.json"))
    assert len(coco.imgs) == T
    people = 0
    for im in coco.imgs.values():
        name = Path(im["file_name"]).name
        assert np.array_equal(cv2.imread(str(out / im["file_name"])), cv2.imread(str(run / "images" / name)))
        cam = im["camera"]
        intr = CameraIntrinsics(im["width"], im["height"], cam["hfov_deg"])
        pose = CameraPose(np.array(cam["position_enu"]), np.array(cam["R_enu_from_cam"]))
        record = json.loads((out / "records" / f"{Path(name).stem}.json").read_text())
        where = {q["person_index"]: q["position_enu"] for q in record["people"]}
        for a in coco.loadAnns(coco.getAnnIds(imgIds=im["id"])):
            if a["cell"] >= 0:  # -1: a person beyond the search grid, in view all the same
                assert a["cell"] in im["occupied_cells"] and a["cell"] in im["cells_in_view"]
            (u, v), _ = project_points(np.array([*where[a["person_index"]], 0.9]), intr, pose)  # mid-body
            x, y, w, h = a["bbox"]
            assert x - 3 <= u <= x + w + 3 and y - 3 <= v <= y + h + 3, (u, v, a["bbox"])
            people += 1
    assert people > 0

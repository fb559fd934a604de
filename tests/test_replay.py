"""Replay of a run directory: re-fusion with another method re-scores the flight exactly as fusion.py
would; damaged logs replay up to the damage; bad inputs are one line."""

import json
import imageio.v2 as imageio
import numpy as np
import pytest

from uavsearch.errors import LogError
from uavsearch.logs.flight_log import FlightLogWriter
from uavsearch.logs.step_record import StepRecord
from uavsearch.replay.replay import replay_run_dir, write_replay
from uavsearch.fly.missions import load_mission
from uavsearch.search.fusion import fuse
from uavsearch.search.metrics import map_accuracy, map_f1

T = 3


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A flight log as `uavsearch fly` writes it, with known per-view numbers (no flight needed)."""
    d = tmp_path_factory.mktemp("run")
    mission = load_mission().with_overrides(**{"fusion": "bayes", "policy": "random"})
    spec = mission.scene_spec()
    labels = spec.occupancy_array().astype(bool)
    rng = np.random.default_rng(0)
    w = FlightLogWriter(d, tlog=False)
    w.header(mission=mission.model_dump(mode="json"), labels=labels.astype(int), grid={"n": 10, "cell_m": 5.0},
             fusion="bayes", agent="bayes fusion + random policy")
    p = np.clip(np.where(labels, 0.7, 0.2) + rng.normal(0, 0.2, (T, 100)), 0.01, 0.99)
    valid = rng.random((T, 100)) < 0.8
    area = rng.uniform(100, 300, (T, 100))
    scores = rng.normal(0, 1, (T, 100))
    p, area, scores = np.round(p, 6), np.round(area, 6), np.round(scores, 6)  # what the JSON log keeps
    import cv2

    for t in range(T):
        img = rng.integers(0, 255, (224, 224, 3), dtype=np.uint8)
        cv2.imwrite(str(d / "images" / f"img_{t:04d}.png"), img)
        pos = [10.0 * t, 0.0, 70.0]
        w.step(StepRecord(t=t, waypoint_enu=pos, reported_position_enu=pos, reported_rpy_rad=[0, 0, 0],
                          image=f"images/img_{t:04d}.png", p_occ=p[t], valid=valid[t], cell_area_px=area[t],
                          scores=scores[t], fused=fuse("bayes", p[: t + 1], valid[: t + 1]), sim_time_s=30.0 + t))
    w.close()
    return d, p, valid, area, scores, labels


@pytest.mark.parametrize("method", ["bayes", "average", "size", "learned", "oracle"])
def test_refusion_rescores_exactly(run_dir, method):
    d, p, valid, area, scores, labels = run_dir
    r = replay_run_dir(d, None if method == "bayes" else method)
    kw = {"size": {"area_px": area}, "learned": {"scores": scores}, "oracle": {"labels": labels}}.get(method, {})
    for t in range(T):
        expect = fuse(method, p[: t + 1], valid[: t + 1], **{k: (v[: t + 1] if k != "labels" else v) for k, v in kw.items()})
        np.testing.assert_allclose(r.maps[t], expect, atol=1e-9)
        assert r.acc[t] == pytest.approx(float(map_accuracy(expect, labels)))
        assert r.f1[t] == pytest.approx(float(map_f1(expect, labels)))
    if method == "oracle":
        assert r.acc[-1] >= r.acc[0]  # the bound never gets worse with more views


def test_replay_outputs_figures_and_one_video_frame_per_view(run_dir, tmp_path):
    d = run_dir[0]
    res = write_replay(replay_run_dir(d, "average"), tmp_path)
    for name in ("trajectory.png", "maps.png", "metrics.png"):
        assert imageio.imread(tmp_path / name).shape[0] > 200
    gif = imageio.mimread(tmp_path / "replay.gif")
    assert len(gif) == T
    assert json.loads((tmp_path / "replay.json").read_text())["acc"] == res["acc"]


def test_torn_log_replays_up_to_the_damage(run_dir, tmp_path):
    import shutil

    d = tmp_path / "torn"
    shutil.copytree(run_dir[0], d)
    text = (d / "search.jsonl").read_text()
    (d / "search.jsonl").write_text(text[: len(text) - 40])  # killed while writing the last step
    r = replay_run_dir(d)
    assert len(r.maps) == T - 1
    assert len(r.warnings) == 1 and "damaged at line 4" in r.warnings[0]  # the CLI prints it as one line


def test_learned_refusion_needs_scores(run_dir, tmp_path):
    import shutil

    d = tmp_path / "noscores"
    shutil.copytree(run_dir[0], d)
    lines = [json.loads(ln) for ln in (d / "search.jsonl").read_text().splitlines()]
    for ln in lines[1:]:
        ln["scores"] = None
    (d / "search.jsonl").write_text("".join(json.dumps(ln) + "\n" for ln in lines))
    with pytest.raises(LogError, match="confidence scores"):
        replay_run_dir(d, "learned")


def test_cli_bad_inputs_are_one_line(tmp_path, capsys):
    from uavsearch.cli import main

    junk = tmp_path / "junk.tlog"
    junk.write_bytes(b"\x00" * 64)
    cases = [([str(tmp_path / "nope")], "no such run directory"),
             ([str(tmp_path), "--fusion", "bayes"], "no search.jsonl"),
             ([str(junk), "--scene", "3"], "junk.tlog"),
             ([str(junk)], "needs --scene SEED")]
    for args, expect in cases:
        assert main(["replay", *args, "--out", str(tmp_path / "o")]) == 2
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("uavsearch: error: ") and expect in lines[0], lines


def test_mp4_video_through_opencv(run_dir, tmp_path):
    import cv2

    from uavsearch.replay.replay import write_video

    path = write_video(replay_run_dir(run_dir[0]), tmp_path, "mp4", seconds_per_view=0.2)
    cap, n = cv2.VideoCapture(str(path)), 0
    while cap.read()[0]:
        n += 1
    assert n == 2 * T  # 10 fps x 0.2 s per view



# --------------------------------------------------------------------------------------------------
# A team flight replays from what it recorded: no flags, the flight's own score; a contradicting flag is one line


@pytest.fixture(scope="module")
def team_run(tmp_path_factory):
    """One short flight of the wide team mission (three vehicles, 30 s of simulated flight)."""
    import subprocess
    import sys

    from uavsearch.paths import MISSIONS_DIR
    from uavsearch.testing.clean_env import clean_env

    run = tmp_path_factory.mktemp("team") / "run"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(MISSIONS_DIR / "wide_team.yaml"),
                        "--mission-time", "30", "--out", str(run), "--gcs-port", "0"],
                       capture_output=True, text=True, timeout=300, env=clean_env())
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return run, json.loads((run / "summary.json").read_text())


def test_a_team_flight_replays_with_no_flags(team_run, tmp_path, capsys):
    """The run folder (the flight's own maps: its learned aggregation reads cell features, which no log holds)
    and its own tlog (perception run again on the flight's images, the mission's learned aggregation fed their
    cell features) both score what the flight scored."""
    from uavsearch.cli import main

    run, summary = team_run
    assert summary["vehicles"] == 3 and summary["steps"] >= 3
    assert replay_run_dir(run).f1[-1] == pytest.approx(summary["f1"], abs=1e-6)
    assert main(["replay", str(run / "telemetry.tlog"), "--out", str(tmp_path / "o")]) == 0
    res = json.loads((tmp_path / "o" / "replay.json").read_text())
    from uavsearch.paths import MISSIONS_DIR

    assert res["fusion"] == load_mission(MISSIONS_DIR / "wide_team.yaml").fusion and res["views"] == summary["steps"]
    assert res["f1"][-1] == pytest.approx(summary["f1"], abs=1e-4)
    assert res["acc"][-1] == pytest.approx(summary["acc"], abs=1e-4)


def test_a_tlog_flown_elsewhere_replays_with_its_team_mission(team_run, tmp_path):
    """A bare .tlog with the wide team mission: its fusion spec (a learned aggregation, fed the cell features of
    perception run again) through the fusion registry, its family's scene."""
    import shutil

    from uavsearch.replay.replay import replay_tlog

    run, summary = team_run
    shutil.copy(run / "telemetry.tlog", tmp_path / "t.tlog")
    from uavsearch.paths import MISSIONS_DIR

    mission = load_mission(MISSIONS_DIR / "wide_team.yaml")
    d = replay_tlog(tmp_path / "t.tlog", mission.scene_spec(), mission, progress=False)
    assert d.fusion == mission.fusion and d.f1[-1] == pytest.approx(summary["f1"], abs=1e-4)


@pytest.mark.parametrize("flags, said", [
    (["--scene", "5"], "--scene 5"),
    (["--setting", "2"], "--setting 2"),
    (["--occupied-cells", "3"], "--occupied-cells 3"),
    (["--mission", "missions/default.yaml"], "fusion learned"),
])
def test_a_flag_that_contradicts_the_record_is_one_line(team_run, tmp_path, capsys, flags, said):
    from uavsearch.cli import main

    run, _ = team_run
    for src in (run, run / "telemetry.tlog"):
        for out in (["--out", str(tmp_path / "o")], ["--html", str(tmp_path / "p.html")]):
            assert main(["replay", str(src), *flags, *out]) == 2
            lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
            assert len(lines) == 1 and lines[0].startswith("uavsearch: error: replay: "), lines
            assert said in lines[0] and "scene 132000 of the wide family" in lines[0] and "3 vehicle(s)" in lines[0]
    assert not (tmp_path / "o").exists() and not (tmp_path / "p.html").exists()


def test_flags_that_agree_with_the_record_are_fine(team_run):
    from uavsearch.paths import MISSIONS_DIR
    from uavsearch.replay.replay import check_flags, flight_record

    run, summary = team_run
    rec = flight_record(run)
    mission_fusion = load_mission(MISSIONS_DIR / "wide_team.yaml").fusion  # the spec the flight recorded
    assert (rec.seed, rec.setting, rec.fusion, rec.vehicles) == (summary["scene_seed"], "wide", mission_fusion, 3)
    check_flags(rec, scene=rec.seed, setting="wide", occupied_cells=rec.occupied_cells,
                mission=str(MISSIONS_DIR / "wide_team.yaml"))
    check_flags(rec, fusion="average", mission=str(MISSIONS_DIR / "wide_team.yaml"))  # --fusion re-fuses on purpose


def test_a_run_folder_mixing_two_flights_is_one_line(team_run, tmp_path):
    import shutil

    from uavsearch.replay.replay import flight_record

    run, _ = team_run
    d = tmp_path / "mixed"
    shutil.copytree(run, d)
    s = json.loads((d / "summary.json").read_text())
    (d / "summary.json").write_text(json.dumps({**s, "scene_seed": 7}))
    with pytest.raises(LogError, match="mixes flights: scene 132000 in search.jsonl's header, .*7 in summary.json"):
        flight_record(d)

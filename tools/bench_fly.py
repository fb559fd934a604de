"""Wall time of flown search missions: `uavsearch fly` end to end, as a user runs it, stage by stage,
beside the time `import torch` takes in the same run (the floor of any command that runs perception).

    python tools/bench_fly.py [--mission missions/default.yaml] [--scenes 3 4 5] [--speed max] [--T 5]
                              [--out results/flight/fly_timing.md]

Each flight is `python -m uavsearch fly` in a fresh process. Stages (wall seconds, each from the end of
the one before): imports = process start until the mission controller runs (the controller's modules,
reading the mission); scene = waiting for the vehicle's scene.json (the vehicle process starts, while torch
and the checkpoints load in a thread); vehicle = waiting for the vehicle to be ready; arm = link up, health,
arming; models = waiting for the checkpoints after that (0 when they were ready first); take-off = the climb
to the search altitude; search = the T views (goto, settle, photo, perception, fusion, policy); landing =
down and disarmed; exit = the end-of-flight comparison's rest (it runs beside the flight), printing and
leaving. `sim` is
the vehicle's clock over the flight; `move sim` the vehicle's clock per move after the first view (goto,
settle, photo). CPU = the controller's own CPU seconds (the vehicle's are in its sitl.log). The load
average beside them says how shared the machine was. `--out` writes the same table as markdown (the file
docs/flying-measurements.md quotes).

`--all` flies the three shipped missions instead (missions/default.yaml, the paper's; wide.yaml; wide_team.yaml)
as they are, one flight each, and prints one row per mission: wall s, `import torch` s in the same run, their
ratio and the load (targets on a quiet machine: paper <= 2.5x import torch, wide <= 12 s, team <= 15 s).
"""

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.fly.missions import load_mission  # noqa: E402
from uavsearch.logs.flight_log import read_flight_log  # noqa: E402

STAGES = ("imports", "scene", "vehicle", "arm", "models", "take-off", "search", "landing", "exit")
_MARKS = ("scene_s", "vehicle_ready_s", "armed_s", "models_s", "took_off_s", "searched_s", "landed_s")


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def import_torch_s() -> tuple[float, float]:
    """(wall, CPU) of `python -c "import torch"` in a fresh process."""
    c0, t0 = _child_cpu(), time.monotonic()
    subprocess.run([sys.executable, "-c", "import torch"], check=True)
    return time.monotonic() - t0, _child_cpu() - c0


def fly_once(mission_file: Path, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    c0 = _child_cpu()
    start_unix = time.time()
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(mission_file), "--out", str(out),
                        "--gcs-port", "0"], capture_output=True, text=True, env=env)
    total = time.monotonic() - t0
    cpu = _child_cpu() - c0
    if r.returncode != 0:
        raise SystemExit(f"uavsearch fly failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    s = json.loads((out / "summary.json").read_text())
    ph = s["wall_phases_s"]
    fly_start = ph["start_unix"] - start_unix
    marks = [fly_start] + [fly_start + ph[k] for k in _MARKS] + [total]
    stages = dict(zip(STAGES, [marks[0]] + [b - a for a, b in zip(marks, marks[1:])]))
    moves = [st.flight_time_s for st in read_flight_log(out).steps[1:]]
    return dict(stages=stages, total=total, cpu=cpu, sim=s["sim_time_s"], status=s["status"], views=s["steps"],
                moves=moves)


ALL_MISSIONS = ("missions/default.yaml", "missions/wide.yaml", "missions/wide_team.yaml")


def fly_wall(mission_file: Path, out: Path) -> float:
    """Wall seconds of one `uavsearch fly --mission FILE` as a user runs it."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(mission_file), "--out", str(out),
                        "--gcs-port", "0"], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise SystemExit(f"uavsearch fly --mission {mission_file} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    return time.monotonic() - t0


def bench_all() -> int:
    """One row per shipped mission (module docstring)."""
    root = Path(__file__).resolve().parents[1]
    print("| mission | wall s | import torch s | ratio | load (1 min) |\n|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for i, name in enumerate(ALL_MISSIONS):
            torch_wall = import_torch_s()[0]
            wall = fly_wall(root / name, Path(tmp) / f"run{i}")
            print(f"| {name} | {wall:.2f} | {torch_wall:.2f} | {wall / torch_wall:.2f} | {os.getloadavg()[0]:.2f} |",
                  flush=True)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default=None, help="mission file (default missions/default.yaml)")
    ap.add_argument("--scenes", type=int, nargs="+", default=[3, 4, 5], help="scene seeds (default 3 4 5)")
    ap.add_argument("--speed", default="max", help="speed factor: max (default) or N")
    ap.add_argument("--T", type=int, default=None, help="override the mission's budget T")
    ap.add_argument("--fusion", default=None, help="override the mission's fusion")
    ap.add_argument("--policy", default=None, help="override the mission's policy")
    ap.add_argument("--free-running", action="store_true",
                    help="vehicle without lockstep (not reproducible; shows what lockstep costs)")
    ap.add_argument("--out", type=Path, default=None, help="also write the table as markdown to this file")
    ap.add_argument("--all", action="store_true", help="fly the three shipped missions, one row each (see above)")
    args = ap.parse_args()
    if args.all:
        return bench_all()
    if args.out is not None and not args.out.parent.is_dir():
        ap.error(f"no folder {args.out.parent} for --out")
    base = load_mission(args.mission).with_overrides(**{
        "flight.speed": args.speed if args.speed == "max" else float(args.speed), "search.budget_T": args.T,
        "fusion": args.fusion, "policy": args.policy, "flight.lockstep": False if args.free_running else None})
    load0 = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        torch_wall, torch_cpu = import_torch_s()
        for seed in tqdm(args.scenes, desc="flying", file=sys.stderr):
            m = base.with_overrides(**{"scene.seed": seed})
            path = Path(tmp) / f"mission{seed}.yaml"
            data = m.model_dump(mode="json")
            for key in ("checkpoint", "perception"):  # absolute: the file sits in a temporary folder
                if data.get(key):
                    data[key] = str(m.checkpoint_path if key == "checkpoint" else m.perception_path)
            path.write_text(yaml.safe_dump(data))
            rows.append(dict(scene=seed, **fly_once(path, Path(tmp) / f"run{seed}")))
        torch_wall2, _ = import_torch_s()
    torch_wall = (torch_wall + torch_wall2) / 2
    budget = f"T = {base.search.budget_T}" if base.family is None else f"{base.search_config().budget_s:g} s"
    out = [f"flown missions: {base.name}, {budget}, speed {base.flight.speed}, "
           f"{base.fusion} fusion + {base.policy} policy; load average {load0:.2f} at start, "
           f"{os.getloadavg()[0]:.2f} at end ({os.cpu_count()} CPUs)",
           f"limit: `import torch` in a fresh process {torch_wall:.2f} s wall (mean of one before and one after the "
           f"flights), {torch_cpu:.2f} s CPU"]
    hdr = f"{'scene':>5} " + " ".join(f"{s:>8}" for s in STAGES) + f" {'total s':>8} {'CPU s':>6} {'sim s':>6} " \
          f"{'move sim':>9} {'x torch':>7}"
    out += [hdr, "-" * len(hdr)]

    def moves(ms: list) -> str:
        return f"{min(ms):.1f}-{max(ms):.1f}" if ms else "-"

    for r in rows:
        out.append(f"{r['scene']:>5} " + " ".join(f"{r['stages'][s]:8.2f}" for s in STAGES) +
                   f" {r['total']:8.2f} {r['cpu']:6.2f} {r['sim']:6.1f} {moves(r['moves']):>9} "
                   f"{r['total'] / torch_wall:7.2f}")
    mean = {s: statistics.mean(r["stages"][s] for r in rows) for s in STAGES}
    tot = statistics.mean(r["total"] for r in rows)
    out.append(f"{'mean':>5} " + " ".join(f"{mean[s]:8.2f}" for s in STAGES) +
               f" {tot:8.2f} {statistics.mean(r['cpu'] for r in rows):6.2f} "
               f"{statistics.mean(r['sim'] for r in rows):6.1f} {moves([m for r in rows for m in r['moves']]):>9} "
               f"{tot / torch_wall:7.2f}")
    sims = [r["sim"] for r in rows]
    all_moves = [m for r in rows for m in r["moves"]]
    out += ["", f"whole mission {min(r['total'] for r in rows):.2f}-{max(r['total'] for r in rows):.2f} s wall, "
            f"mean {tot:.2f} s; stages (mean): " + ", ".join(f"{s} {mean[s]:.2f} s" for s in STAGES) +
            f"; simulated flight mean {statistics.mean(sims):.1f} s ({min(sims):.1f}-{max(sims):.1f})"
            + (f"; each move after the first view {moves(all_moves)} s of simulated time" if all_moves else "")]
    print("\n" + "\n".join(out))
    if args.out is not None:
        cmd = " ".join(["python tools/bench_fly.py", *sys.argv[1:]])
        args.out.write_text(f"# Flown missions, wall time by stage\n\nRegenerate: `{cmd}` "
                            f"({time.strftime('%Y-%m-%d', time.gmtime())}).\n\n```\n" + "\n".join(out) + "\n```\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

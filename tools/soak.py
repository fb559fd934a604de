"""Soak: N flown missions back to back in one process; wall time, RSS and leftovers per mission.

    python tools/soak.py [--missions 50] [--mission missions/default.yaml] [--speed max] [--T 5]

Each mission is `uavsearch fly` in process (vehicle process start, take-off, T views, landing) on the
next scene seed (cycling over --scenes). After each one: its wall time, the controller's RSS, its open
file descriptors and threads, the child processes still alive (a vehicle or render worker still there
10 s after its mission is a leftover), and whether it completed. At the end: the least-squares slope of
wall time and RSS per mission (flat means no leak), and what is still running.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.fly.missions import load_mission  # noqa: E402
from uavsearch.fly.mission_controller import fly  # noqa: E402


def _status(pid: int | str = "self") -> dict:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        k, _, v = line.partition(":")
        out[k] = v.strip()
    return out


def children(pid: int | None = None) -> list[int]:
    """Live child processes (every thread's children), zombies excluded."""
    pid = pid or os.getpid()
    kids = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            kids += [int(p) for p in (task / "children").read_text().split()]
        except OSError:
            pass
    return [k for k in kids if Path(f"/proc/{k}").exists() and _status(k).get("State", "Z")[0] != "Z"]


def sample(grace_s: float = 10.0) -> dict:
    """The controller after a mission. A vehicle finishes its shutdown on its own after `fly` returns: children
    still alive `grace_s` later are the leftovers (exit_s: how long the last one took to go)."""
    t0 = time.monotonic()
    while children() and time.monotonic() - t0 < grace_s:
        time.sleep(0.05)
    st = _status()
    return dict(rss_mib=int(st["VmRSS"].split()[0]) / 1024, threads=int(st["Threads"]),
                fds=len(os.listdir("/proc/self/fd")), children=children(), exit_s=time.monotonic() - t0)


def _slope(y) -> float:
    y = np.asarray(y, dtype=float)
    if len(y) < 2:
        return 0.0
    return float(np.polyfit(np.arange(len(y)), y, 1)[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--missions", type=int, default=50)
    ap.add_argument("--mission", default=None, help="mission file (default missions/default.yaml)")
    ap.add_argument("--scenes", type=int, nargs="+", default=list(range(3, 13)), help="scene seeds to cycle over")
    ap.add_argument("--speed", default="max")
    ap.add_argument("--T", type=int, default=None, help="override the budget T")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    a = ap.parse_args(argv)
    base = load_mission(a.mission).with_overrides(**{
        "flight.speed": a.speed if a.speed == "max" else float(a.speed), "search.budget_T": a.T})
    rows = []
    s0 = sample()
    print(f"start: RSS {s0['rss_mib']:.1f} MiB, {s0['fds']} fds, {s0['threads']} threads, children {s0['children']}")
    print("| # | scene | status | wall s | RSS MiB | fds | threads | children left (after s) |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="soak_") as tmp:
        for i in range(a.missions):
            seed = a.scenes[i % len(a.scenes)]
            m = base.with_overrides(**{"scene.seed": seed})
            t0 = time.monotonic()
            r = fly(m, out=Path(tmp) / f"m{i:03d}", progress=lambda s: None, gcs_port=0)
            wall = time.monotonic() - t0
            s = sample()
            row = dict(i=i, scene=seed, status=r.status.split(":")[0], wall_s=wall, f1=r.f1, **s)
            rows.append(row)
            print(f"| {i} | {seed} | {row['status']} | {wall:.1f} | {s['rss_mib']:.1f} | {s['fds']} | {s['threads']} | "
                  f"{len(s['children'])} ({s['exit_s']:.2f}) |", flush=True)
    walls = [r["wall_s"] for r in rows]
    rss = [r["rss_mib"] for r in rows]
    done = sum(r["status"] == "completed" for r in rows)
    half = max(1, len(rows) // 2)
    print(f"\n{len(rows)} missions, {done} completed; wall {np.mean(walls):.1f} s mean "
          f"(first half {np.mean(walls[:half]):.1f}, second half {np.mean(walls[half:] or walls):.1f}; "
          f"slope {_slope(walls):+.3f} s/mission)")
    print(f"RSS {rss[0]:.1f} -> {rss[-1]:.1f} MiB (slope {_slope(rss):+.3f} MiB/mission; after mission 5: "
          f"{_slope(rss[5:]) if len(rss) > 6 else 0.0:+.3f}); fds {rows[0]['fds']} -> {rows[-1]['fds']}; "
          f"threads {rows[0]['threads']} -> {rows[-1]['threads']}")
    left = children()
    print(f"leftovers: {len(left)} child process(es) alive at the end {left}")
    print(f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0 if done == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())

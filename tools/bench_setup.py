"""How long the README's first step takes: `make setup` (a new .venv) in a fresh clone of the committed HEAD.

    python tools/bench_setup.py [--out results/setup_time.md] [--python python3]

Clones HEAD into a temporary folder, runs `make setup` there as a new user's first `make run` does (pip
with no cache of its own, so every wheel is fetched and unpacked), and writes the wall time beside the
machine's load, CPU count, Python and commit to results/setup_time.md: the file the README and the
Makefile quote (tests/test_readme_numbers.py holds them to it).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "results" / "setup_time.md"


def minutes_seconds(seconds: float) -> str:
    """114.2 -> '1 min 54 s', 45 -> '0 min 45 s' (one form, the one the README quotes)."""
    m, s = divmod(round(seconds), 60)
    return f"{m} min {s} s"


def about(seconds: float) -> str:
    """The rounded figure for prose: to the half minute past a minute, to 10 s below it."""
    if seconds < 60:
        return f"about {max(10, round(seconds, -1)):.0f} s"
    half = round(seconds / 30) / 2
    return f"about {half:g} minute{'' if half == 1 else 's'}"


def _user_env() -> dict:
    """The caller's environment without an active virtualenv, so `make` finds the Python a new user has."""
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    venv = os.environ.get("VIRTUAL_ENV")
    if venv:
        env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                      if not p.startswith(venv))
    env["PIP_NO_CACHE_DIR"] = "1"
    return env


def measure(python: str, workdir: Path) -> dict:
    """Clone HEAD into workdir and time `make setup` there; the output lines go to workdir/setup.log."""
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, check=True).stdout.strip()
    clone = workdir / "uavsearch"
    subprocess.run(["git", "clone", "--quiet", "--depth", "1", f"file://{ROOT}", str(clone)], check=True)
    env = _user_env()
    version = subprocess.run([python, "-c", "import platform; print(platform.python_version())"],
                             capture_output=True, text=True, env=env, check=True).stdout.strip()
    load0 = os.getloadavg()[0]
    log = workdir / "setup.log"
    t0 = time.monotonic()
    with log.open("w") as f, tqdm(desc="make setup", unit=" line", file=sys.stderr) as bar:
        proc = subprocess.Popen(["make", "setup", f"PYTHON={python}"], cwd=clone, env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        for line in proc.stdout:
            f.write(line)
            bar.set_postfix_str(line.strip()[:60], refresh=False)
            bar.update()
        rc = proc.wait()
    wall = time.monotonic() - t0
    if rc != 0:
        raise SystemExit(f"bench_setup: make setup failed (exit {rc}); the last lines of {log}:\n"
                         + "".join(log.read_text().splitlines(keepends=True)[-20:]))
    return dict(commit=commit, python=version, wall_s=wall, load_before=load0, load_after=os.getloadavg()[0],
                cpus=os.cpu_count(), when=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))


def report(r: dict) -> str:
    return "\n".join([
        "# Setup time: `make setup` in a fresh clone",
        "",
        "Regenerate: `python tools/bench_setup.py` (clones HEAD into a temporary folder, makes a new `.venv` the",
        "README's way with `make setup`, pip without a cache, and times it). The load average says how shared the",
        "machine was: on a busy machine the same setup takes longer.",
        "",
        "| measured | commit | Python | CPUs | load average before / after | make setup, wall |",
        "|---|---|---|---|---|---|",
        f"| {r['when']} | {r['commit']} | {r['python']} | {r['cpus']} | {r['load_before']:.1f} / {r['load_after']:.1f} "
        f"| {minutes_seconds(r['wall_s'])} ({r['wall_s']:.0f} s) |",
        "",
        f"make setup took {minutes_seconds(r['wall_s'])} on {r['cpus']} CPUs (load average {r['load_before']:.1f} "
        f"before, {r['load_after']:.1f} after). Rounded, as the README and the Makefile quote it: "
        f"**{about(r['wall_s'])}**.",
        "",
    ])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="markdown file to write (default %(default)s)")
    ap.add_argument("--python", default="python3", help="the Python `make setup` builds the venv from")
    args = ap.parse_args(argv)
    if not args.out.parent.is_dir():
        print(f"bench_setup: no folder {args.out.parent} for --out", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="bench_setup_") as tmp:
        r = measure(args.python, Path(tmp))
    args.out.write_text(report(r))
    print(f"make setup: {minutes_seconds(r['wall_s'])} at load {r['load_before']:.1f} / {r['load_after']:.1f} "
          f"on {r['cpus']} CPUs -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

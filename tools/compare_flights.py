"""Did two flights fly the same? Compares two `uavsearch fly` run directories field by field.

Same mission, scene and seeds in lockstep must give the same flight: the same flight log, summary,
camera records, flown plan and image bytes. What may differ is wall-clock time (`wall_s`, `started_utc`,
`start_unix`, every `*_s` under a wall-time key) and where the run directory lay: a recorded path or file://
URL that leads into the run (captures.jsonl's image paths, as given or absolute) is compared from the run
directory down, so the same flight in two folders is the same (`--compare-paths` compares them as
recorded). The tlog and sitl.log are not compared (they stamp packets and lines with wall time).

    .venv/bin/python tools/compare_flights.py RUN_A RUN_B [--ignore mission_file] [--compare-paths]

Prints one row per file (same / differs, and the first fields that differ); exits 0 when every file
matches, 1 when one differs, 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path, PurePosixPath

JSON_FILES = ("search.jsonl", "summary.json", "captures.jsonl", "flown.plan", "mission.json", "scene.json")
WALL_KEYS = {"wall_s", "started_utc", "start_unix", "flight_wall_s"}
RUN_DIR = "<RUN_DIR>"


def _is_wall(path: tuple, ignore: frozenset = frozenset()) -> bool:
    """A wall-clock field: a named one, any field under a key that speaks of wall time, or one --ignore names."""
    keys = [k for k in path if isinstance(k, str)][1:]
    return bool(keys) and (keys[-1] in WALL_KEYS | ignore or any("wall" in k for k in keys))


def _in_run(value, run: Path | None):
    """A recorded path or file:// URL that leads into the run, from the run directory down; else the value.

    The run's folder is known only by what lies in it: the longest tail of the path that names a file or
    folder in `run` is kept, whatever stood before it (relative or absolute, this folder or the one flown in)."""
    if run is None or not isinstance(value, str) or "/" not in value:
        return value
    scheme = "file://" if value.startswith("file://") else ""
    parts = PurePosixPath(value[len(scheme):]).parts
    for i in range(1, len(parts)):
        if (run / Path(*parts[i:])).exists():
            return scheme + "/".join((RUN_DIR, *parts[i:]))
    return value


def _flatten(value, path: tuple, out: dict, run: Path | None, ignore: frozenset) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(v, path + (k,), out, run, ignore)
    elif isinstance(value, list) and value and all(isinstance(v, (dict, list)) for v in value):
        for i, v in enumerate(value):
            _flatten(v, path + (i,), out, run, ignore)
    elif not _is_wall(path, ignore):
        out[path] = json.dumps(_in_run(value, run), sort_keys=True)


def _records(path: Path) -> list:
    text = path.read_text()
    if path.suffix == ".jsonl":
        return [json.loads(line) for line in text.splitlines() if line.strip()]
    return [json.loads(text)]


def _fields(run: Path, name: str, ignore: frozenset, compare_paths: bool = False) -> dict:
    out: dict = {}
    for i, rec in enumerate(_records(run / name)):
        label = rec.get("type", "record") if isinstance(rec, dict) else "record"
        _flatten(rec, (f"{i}:{label}",), out, None if compare_paths else run, ignore)
    return out


def _name(path: tuple) -> str:
    return ".".join(str(p) for p in path)


def compare_file(a: Path, b: Path, name: str, ignore: frozenset = frozenset(),
                 compare_paths: bool = False) -> tuple[str, str]:
    """(status, detail) for one file of the two runs."""
    pa, pb = a / name, b / name
    if not pa.exists() and not pb.exists():
        return "absent", "in neither run"
    if not pa.exists() or not pb.exists():
        return "differs", f"only in {'B' if not pa.exists() else 'A'}"
    if name.startswith("images/"):
        return ("same", "") if pa.read_bytes() == pb.read_bytes() else ("differs", "image bytes")
    try:
        fa, fb = _fields(a, name, ignore, compare_paths), _fields(b, name, ignore, compare_paths)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        return "differs", f"not readable as JSON: {e}"
    diff = [k for k in sorted(set(fa) | set(fb), key=_name) if fa.get(k) != fb.get(k)]
    if not diff:
        return "same", ""
    shown = ", ".join(_name(k) for k in diff[:4]) + (f" (+{len(diff) - 4} more)" if len(diff) > 4 else "")
    return "differs", f"{len(diff)} field(s): {shown}"


def compare_runs(a: Path, b: Path, ignore=(), compare_paths: bool = False) -> list[tuple[str, str, str]]:
    images = sorted({p.relative_to(r).as_posix() for r in (a, b) for p in (r / "images").glob("*") if p.is_file()})
    return [(name, *compare_file(a, b, name, frozenset(ignore), compare_paths)) for name in (*JSON_FILES, *images)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_a", type=Path, metavar="RUN_A")
    ap.add_argument("run_b", type=Path, metavar="RUN_B")
    ap.add_argument("--ignore", action="append", default=[], metavar="KEY",
                    help="also ignore fields of this name (repeatable), e.g. mission_file for runs from two checkouts")
    ap.add_argument("--compare-paths", action="store_true",
                    help="compare recorded paths into the run directory as recorded (by default the folder the "
                         "run lay in is not a difference)")
    args = ap.parse_args(argv)
    for run in (args.run_a, args.run_b):
        if not (run / "search.jsonl").is_file():
            print(f"compare_flights: {run} is not a flight's run directory (no search.jsonl)", file=sys.stderr)
            return 2
    rows = compare_runs(args.run_a, args.run_b, args.ignore, args.compare_paths)
    width = max(len(r[0]) for r in rows)
    print(f"{'file':<{width}}  {'result':<7}  detail")
    for name, status, detail in rows:
        print(f"{name:<{width}}  {status:<7}  {detail}")
    bad = [r for r in rows if r[1] == "differs"]
    ignored = "wall-clock fields" + ("" if args.compare_paths else ", run-folder paths") \
        + "".join(f", {k}" for k in args.ignore)
    print(f"{len(rows) - len(bad)} of {len(rows)} file(s) the same ({ignored} ignored)"
          + ("" if not bad else f"; {len(bad)} differ"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

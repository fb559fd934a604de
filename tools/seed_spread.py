"""Spread of the paper's method over stage-2 TRAINING seeds, from one Table II (table2.csv) per seed.

    python tools/seed_spread.py results/training_seeds/seed0 results/training_seeds/seed1 ... --out FILE.md

Each folder is `uavsearch eval search --models-dir <runs of one training seed> --out <folder>`; the folder
name is the seed label. Writes a markdown table: per seed and setting the paper's method's Aacc / AF1,
the coverage route's AF1 (the strongest fixed baseline) and the share of the single-view -> oracle
fusion + policy AF1 gap it closes; then mean ± std over seeds (population std, as Table II's ± over
evaluation seeds). tools/reproduce.sh runs it.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from uavsearch.errors import UavsearchError
from uavsearch.paths import display_path
from uavsearch.search.evaluate.search import gap_closure
from uavsearch.world.settings import SETTINGS


def read_rows(folder: Path) -> list[dict]:
    path = folder / "table2.csv"
    if not path.is_file():
        raise UavsearchError(f"{path} not found (run `uavsearch eval search ... --out {folder}` first)")
    with path.open() as f:
        return [{k: (v if k in ("method", "key") else float(v)) for k, v in r.items()} for r in csv.DictReader(f)]


def spread_table(folders: list[Path]) -> str:
    settings = sorted(SETTINGS)
    per = {}  # seed label -> setting -> (aacc, af1, coverage af1, gap)
    for folder in folders:
        rows = read_rows(folder)
        by = {r["key"]: r for r in rows}
        per[folder.name] = {s: (by["learned_policy"][f"s{s}_aacc"], by["learned_policy"][f"s{s}_af1"],
                                by["learned_coverage"][f"s{s}_af1"], 100 * gap_closure(rows, s)) for s in settings}
    head = " | ".join(f"{SETTINGS[s]} cells Aacc % / AF1 (coverage AF1; gap closed)" for s in settings)
    lines = ["# The paper's method over stage-2 training seeds (Table II protocol per seed)", "",
             f"| training seed | {head} |", "|---|" + "---|" * len(settings)]
    for label, by_s in per.items():
        lines.append(f"| {label} | " + " | ".join(
            f"{a:.2f} / {f:.3f} ({c:.3f}; {g:.0f}%)" for a, f, c, g in (by_s[s] for s in settings)) + " |")
    cells = []
    for s in settings:
        v = np.array([per[k][s] for k in per])  # (seeds, 4)
        m, sd = v.mean(0), v.std(0)
        cells.append(f"{m[0]:.2f} ± {sd[0]:.2f} / {m[1]:.3f} ± {sd[1]:.3f} "
                     f"(gap {v[:, 3].min():.0f}-{v[:, 3].max():.0f}%)")
    lines.append("| mean ± std | " + " | ".join(cells) + " |")
    lines += ["", "From " + ", ".join(f"`{display_path(f / 'table2.csv')}`" for f in folders) + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+", type=Path, help="one Table II output folder per training seed")
    p.add_argument("--out", type=Path, required=True, help="markdown file to write")
    a = p.parse_args(argv)
    try:
        text = spread_table(a.folders)
    except UavsearchError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

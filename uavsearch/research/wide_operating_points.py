"""The wide net's 40 m targets at other decision thresholds: is a missed target the threshold's doing or the net's?

The perception targets of the wide family are judged at the fixed 0.5 threshold (recall of occupied cells showing
>= 8 person pixels >= 0.75 and <= 0.015 false alarms per cell-view, at 40 m). Moving the threshold trades one
for the other; this prints both for a range of logit shifts (a shift s fires where logit(p) + s > 0), for each
net given, at one altitude, on one part's view caches, and the best recall any shift reaches within the
false-alarm target. The calibrated fusion of the search Platt-scales logit(p), so such a shift leaves the search
as it is.

    python tools/wide_operating_points.py --part val --nets models/perception_wide.pt OTHER.pt \\
        --out results/perception_wide/operating_points.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..paths import display_path
from ..search.data.view_cache import get_view_cache
from ..search.evaluate.perception import at_altitude, perception_stats
from ..search.perception import load_perception, shipped_perception

SHIFTS = (-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0)
FA_TARGET = 0.015
RECALL_TARGET = 0.75


def operating_points(net_path: str, part: str, scenes: int | None, altitude_m: float) -> tuple[list[dict], str]:
    net, _ = load_perception(net_path)
    cache = at_altitude(get_view_cache(net, "wide", "large", part, limit=scenes, features=False, progress=False),
                        altitude_m)
    rows = []
    for s in SHIFTS:
        st = perception_stats([cache], threshold=float(1.0 / (1.0 + np.exp(s))))
        rows.append({"shift": s, "recall_8px": st["recall_8px"], "fa": st["fa_per_cell_view"], "ap": st["cell_ap"]})
    return rows, cache.perception_tag


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nets", nargs="+", default=[str(shipped_perception("wide"))])
    ap.add_argument("--part", default="val", choices=("train", "val", "test"))
    ap.add_argument("--scenes", type=int, default=50, help="the part's first N scenes")
    ap.add_argument("--altitude", type=float, default=40.0)
    ap.add_argument("--out", default=None, help="markdown table (also printed)")
    args = ap.parse_args()
    lines = [f"# The wide net's operating points at {args.altitude:g} m: {args.part} scenes (first {args.scenes})", "",
             "shift s: the net fires where logit(p) + s > 0 (0: the 0.5 threshold the targets are judged at). "
             f"Targets: recall at >= 8 visible person pixels >= {RECALL_TARGET}, false alarms per cell-view <= "
             f"{FA_TARGET}.", "", "| net | cell AP | " + " | ".join(f"s = {s:+g}" for s in SHIFTS) +
             f" | best recall with <= {FA_TARGET} false alarms |", "|---|---|" + "---|" * (len(SHIFTS) + 1)]
    for path in args.nets:
        rows, tag = operating_points(path, args.part, args.scenes, args.altitude)
        ok = [r["recall_8px"] for r in rows if r["fa"] <= FA_TARGET]
        cells = " | ".join(f"{r['recall_8px']:.3f} / {r['fa']:.4f}" for r in rows)
        best = f"{max(ok):.3f}" if ok else "none"
        lines.append(f"| {display_path(path)} ({tag}) | {rows[0]['ap']:.3f} | {cells} | {best} |")
    lines += ["", "Each cell: recall at >= 8 px / false alarms per cell-view."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Time the fusions view by view, as the search loop calls them: `update` T times on a batch of episodes of the
wide family's size (900 cells). The calibrated fusion is timed twice: its own update (same-scale counts kept in
its state, O(t N) per view) and the generic re-fusion of the whole history (Fusion.update, O(t^2 N) per view
for its counts). Synthetic inputs (two scales, 190 and 590 px); prints a table.

    python tools/bench_fusion.py                  # B = 100 episodes, T = 8 and 26 views
    python tools/bench_fusion.py --batch 50 --views 8,16,26 --repeats 5
"""

from __future__ import annotations

import argparse
import time

import torch

from uavsearch.search.fusion import AverageFusion, BayesFusion, CalibratedFusion, Fusion, FusionViews


class _Refusing(CalibratedFusion):
    """The calibrated fusion through the generic update: re-fuse everything each view."""

    update = Fusion.update


def _episode(fusion: Fusion, views: FusionViews, T: int) -> torch.Tensor:
    state, fused = None, None
    for t in range(T):
        state, fused = fusion.update(state, FusionViews(*(x[:, t:t + 1] for x in views[:3])))
    return fused


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=100, help="episodes per batch")
    ap.add_argument("--cells", type=int, default=900)
    ap.add_argument("--views", default="8,26", help="episode lengths T")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per row (the fastest is reported)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    coef = [1.15, -0.02, -2.69, 0.03]  # about what Table III fits on the wide family's training scenes
    fusions = {"average": AverageFusion(), "bayes": BayesFusion(0.3),
               "calibrated 0.75 (running state)": CalibratedFusion(coef, 0.011, 0.75),
               "calibrated 0.75 (re-fused history)": _Refusing(coef, 0.011, 0.75)}
    print(f"{args.batch} episodes x {args.cells} cells, {args.threads} thread(s); best of {args.repeats}\n")
    print("| fusion | T | ms per batch episode (all T updates) | ms per view |")
    print("|---|---|---|---|")
    for T in (int(v) for v in args.views.split(",")):
        shape = (args.batch, T, args.cells)
        views = FusionViews(torch.rand(shape, generator=gen), torch.rand(shape, generator=gen) < 0.3,
                            torch.where(torch.rand(shape, generator=gen) < 0.5, 190.0, 590.0))
        ref = None
        for name, fusion in fusions.items():
            best = float("inf")
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                out = _episode(fusion, views, T)
                best = min(best, time.perf_counter() - t0)
            if name.startswith("calibrated"):
                ref = out if ref is None else ref
                if not torch.equal(out, ref):
                    raise SystemExit("the running state and the re-fused history disagree")
            print(f"| {name} | {T} | {best * 1e3:.1f} | {best * 1e3 / T:.2f} |")


if __name__ == "__main__":
    main()

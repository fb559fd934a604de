"""What the flight benchmarks share: timing one call (wall and CPU) and printing rows (name, value, unit)."""

from __future__ import annotations

import math
import time


def timed(fn) -> tuple[float, float]:
    """(wall s, CPU s) of fn(); CPU beside wall because the machine may be shared: the CPU figure is the cost."""
    w0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0


def print_table(rows) -> None:
    """Rows (name, value, unit) or (name, value, unit, ratio): a ratio is printed as 'x.xx of <limit>'."""
    w = max(len(r[0]) for r in rows)
    print()
    for name, value, unit, *ratio in rows:
        val = "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:10.2f}"
        tail = f"   {ratio[0]:6.3f} {ratio[1]}" if ratio and ratio[0] is not None else ""
        print(f"{name:{w}}  {val} {unit:4}{tail}")

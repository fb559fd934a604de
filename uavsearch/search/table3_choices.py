"""What Table III chose on a family's validation scenes, read back from its committed files.

Table III (results/search_<family>/table3.csv and table3.md, written by evaluate/wide.py) chooses per budget the
fusion, the rule's variant and the best fixed route on validation scenes. The env's one-budget tasks and the
flight's comparison table reuse those choices; both read them here, from the files, so a regenerated table moves
them too and nothing holds a second copy.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import NamedTuple

from ..errors import UavsearchError
from ..paths import REPO_ROOT

RESULTS_DIR = REPO_ROOT / "results"
BUDGET_HEADS = {"8": "T = 8 views", "240": "240 s"}  # the env's budget keys -> the table's budget names


class Table3Choice(NamedTuple):
    """One family and budget of Table III."""

    fusion: str  # the fusion every row but the learned policy and the oracles fuses with
    rule: str  # the rule's variant (wide_policies.RULE_VARIANTS)
    best_fixed: str  # the best fixed route's key (evaluate/wide.py FIXED): may be a view set searched on training
    rule_val_af1: float  # the rule's mean AF1 on the validation scenes it was chosen on
    val_af1: dict  # every fixed route's validation AF1, by key
    source: str  # the table's markdown, relative to the repository


def table3_folder(family: str) -> Path:
    return RESULTS_DIR / f"search_{family.replace('-', '_')}"


def table3_choice(family: str, budget: str) -> Table3Choice:
    """Table III's choices for `family` and `budget` ("8", "240", or the table's "T = 8 views" / "240 s").
    A family without a committed Table III is a one-line UavsearchError."""
    budget = BUDGET_HEADS.get(str(budget).removesuffix("s"), str(budget))
    folder = table3_folder(family)
    try:
        with open(folder / "table3.csv", newline="") as f:
            rows = [r for r in csv.DictReader(f) if r["setting"] == family and r["budget"] == budget]
        text = (folder / "table3.md").read_text()
    except OSError as e:
        raise UavsearchError(f"no Table III of {family} in results/{folder.name}: {e.strerror}") from None
    section = {part.split("\n", 1)[0]: part for part in text.split("\n### ")}.get(f"{family}, {budget}", "")
    fusion = re.search(r"Fusion \*\*([^*]+)\*\*", section)
    rule = re.search(r"chosen on the validation scenes: \*\*([^*]+)\*\*", section)
    best = next((r["key"] for r in rows if r["best_fixed"] == "True"), None)
    if not rows or fusion is None or rule is None or best is None:
        raise UavsearchError(f"results/{folder.name}/table3.md has no complete section '{family}, {budget}'")
    rule_af1 = re.search(re.escape(rule.group(1)) + r" (\d\.\d+)[,)]", section[rule.end():])
    return Table3Choice(fusion.group(1), rule.group(1), best, float(rule_af1.group(1)) if rule_af1 else float("nan"),
                        {r["key"]: float(r["val_af1"]) for r in rows if r["val_af1"] not in ("", "nan")},
                        f"results/{folder.name}/table3.md")


__all__ = ["BUDGET_HEADS", "Table3Choice", "table3_choice", "table3_folder"]

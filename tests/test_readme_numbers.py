"""Every figure the README (and the docs pages listed here) quotes agrees with the committed file it comes from.

The convention: a quoted figure names its source beside it (a link or a path in the sentence, so a reader
can check it), and QUOTES ties the two for this test: the words the page says around the figure, `{}`
for each number, and the words of the source file that hold the same numbers. Numbers agree at the
page's precision (97.0 quotes 97.000; 15 quotes 15.04). Regenerating a source (tools/bench_setup.py,
tools/bench_fly.py, tools/wide_flights.py ...) without updating the page fails here, and so does editing
a figure on the page alone; the message names the number, the page and the file. A README figure with a
unit of time that no entry covers fails too: give it a source (and an entry) or drop it.
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NUMBER = r"(?<![\d.])([+\-−]?\d+(?:,\d{3})*(?:\.\d+)?)(?![\d])"


@dataclass(frozen=True)
class Quote:
    page: str  # the page that quotes, relative to the repository root
    says: str  # its words around the figure, {} for each number ({_} for a number not compared)
    source: str  # the committed file the figure comes from
    source_says: str | tuple[str, ...] = ""  # the file's words holding the same numbers (default: `says`)

    @property
    def source_templates(self) -> tuple[str, ...]:
        s = self.source_says or self.says
        return (s,) if isinstance(s, str) else s

    def __str__(self) -> str:
        return f"{self.page}: '{self.says}' <- {self.source}"


QUOTES = [
    # setup: measured by tools/bench_setup.py in a fresh clone
    Quote("README.md", "set up .venv (about {} minute", "results/setup_time.md", "**about {} minute"),
    Quote("README.md", "with a new virtual environment took {} min {} s on {} CPUs (load average {} before, {} after",
          "results/setup_time.md", "make setup took {} min {} s on {} CPUs (load average {} before, {} after"),
    Quote("Makefile", "(a fresh setup takes about {} minute", "results/setup_time.md", "**about {} minute"),
    Quote("Makefile", "dependencies (about {} minute", "results/setup_time.md", "**about {} minute"),
    # flying the default mission: tools/bench_fly.py
    Quote("README.md", "takes {} s of simulated flight", "results/flight/fly_timing.md", "simulated flight mean {} s"),
    # the wide missions: their mission files, and tools/wide_flights.py for the team's wall time
    Quote("README.md", "search a {} m city block (10 occupied cells in groups) for {} s of simulated flight, "
          "choosing each next viewpoint at {} m or {} m", "missions/wide.yaml",
          ("searches a {} m x", "mission_time_s: {}", "viewpoint ({} m or {} m)")),
    # the wide env: Table III's choices, read from the committed table (the T = 8 section comes first, so a
    # template's first match is T = 8's; the 240 s ones name that section's own words), and a scene's cost
    Quote("README.md", "(calibrated:{} at T = 8,", "results/search_wide/table3.md",
          "(AF1 gain per second)**. Fusion **calibrated:{}**"),
    Quote("README.md", "calibrated:{} at 240 s)", "results/search_wide/table3.md",
          "then 40 m lawnmower**. Fusion **calibrated:{}**"),
    Quote("README.md", "(about {} s to render and {} MB under cache/ each", "uavsearch/search/envs/search_env.py",
          ("WIDE_SCENE_S = {}", "WIDE_SCENE_MB = {}")),
    Quote("README.md", "(AF1 {} at T = 8,", "results/search_wide/table3.md",
          "**4 covering, resurvey below p 0.4** (4 covering {_}, 4 covering, per second {_}, 4 covering, resurvey "
          "below p 0.2 {_}, 4 covering, resurvey below p 0.2, per second {_}, 4 covering, resurvey below p 0.3 {_}, "
          "4 covering, resurvey below p 0.3, per second {_}, 4 covering, resurvey below p 0.4 {},"),
    Quote("README.md", "{} at 240 s; `python tools/env_table3.py`", "results/search_wide/table3.md",
          "per second {}). The learned policy: models/search_wide_240s_map.pt"),
    Quote("README.md", "vehicle over a {} m block", "missions/wide.yaml", "searches a {} m x"),
    Quote("README.md", "family for {} s of flight, sharing one fused map", "missions/wide_team.yaml",
          "mission_time_s: {}"),
    Quote("README.md", "lands all three (about {} s wall", "results/team_wide/flights.md",
          "(vehicle start, take-off, search, landing): mean {} s"),
    # training: the scene splits and the script that trained the shipped models
    Quote("README.md", "on the paper split's {} training scenes", "scenes/settings.yaml", "train: {}"),
    Quote("README.md", "the shipped ones ran {} iterations", "tools/reproduce.sh", "{} iterations,"),
    Quote("README.md", "iterations on {} (the large split", "scenes/settings.yaml", "needs more scenes train: {}"),
    # the gymnasium env's speed: tools/bench_env.py, as docs/learning.md records it
    Quote("README.md", "at {} envs its native vector env steps {} episode steps a second", "docs/learning.md",
          "{_} / {_} / {} envs | {_} / {_} / {} |"),
    # docs/flying-measurements.md: the flight-vs-teleport table (uavsearch eval search --vehicle mavlink) ...
    *[Quote("docs/flying-measurements.md", f"| {k} ({cells} cells) | {{_}}-{{_}} | {{}} / {{}} | {{}} / {{}} | {{}} | "
            "{}/10 | {} |", f"results/flight/flight_vs_teleport_s{k}.md",
            (f"setting {k} (paper split, {{_}}/{{_}} test scenes", "| teleport | {} | {} |",
             "| flight (MAVLink) | {} | {} |", "| difference | {_} | {} |", "Same route in both modes: {}/10",
             "Wall time per flown mission: {} s"))
      for k, cells in ((1, 2), (2, 5), (3, 10))],
    # ... and tools/bench_fly.py
    Quote("docs/flying-measurements.md", "took {}-{} s wall, mean {} s (imports {} s, scene {} s, vehicle {} s, arm {} s, "
          "models {} s, take-off {} s, search {} s, landing {} s, exit {} s)", "results/flight/fly_timing.md",
          ("whole mission {}-{} s wall, mean {} s", "imports {} s, scene {} s, vehicle {} s, arm {} s, models {} s, "
           "take-off {} s, search {} s, landing {} s, exit {} s")),
    Quote("docs/flying-measurements.md", "takes {}-{} s of simulated time", "results/flight/fly_timing.md",
          "each move after the first view {}-{} s"),
    Quote("docs/flying-measurements.md", "it is the flight's own ({} s for the default mission",
          "results/flight/fly_timing.md", "simulated flight mean {} s"),
]


def _pattern(template: str) -> re.Pattern:
    """{} a number compared, {_} a number passed over; spaces match any run of whitespace (line breaks too)."""
    skip = NUMBER.replace("([", "(?:[", 1)
    parts = [re.escape(p).replace(r"\ ", r"\s+").replace(r"\{_\}", skip) for p in template.split("{}")]
    return re.compile(NUMBER.join(parts))


def _numbers(text: str, templates: tuple[str, ...]) -> tuple[list[str], list[str]] | None:
    """(numbers, what the text says) of each template's first match, in order; None if one does not match."""
    nums, said = [], []
    for t in templates:
        m = _pattern(t).search(text)
        if m is None:
            return None
        nums += list(m.groups())
        said.append(" ".join(m.group(0).split()))
    return nums, said


def _value(s: str) -> float:
    return float(s.replace(",", "").replace("−", "-"))


def _agree(quoted: str, source: str) -> bool:
    decimals = len(quoted.split(".")[1]) if "." in quoted else 0
    return round(_value(source), decimals) == _value(quoted)


def _committed(path: str) -> bool:
    if not (ROOT / ".git").exists():
        return (ROOT / path).is_file()
    r = subprocess.run(["git", "ls-files", "--error-unmatch", path], cwd=ROOT, capture_output=True)
    return r.returncode == 0


@pytest.mark.parametrize("q", QUOTES, ids=lambda q: f"{q.page}:{q.says[:40]}")
def test_quoted_figure_agrees_with_its_file(q):
    page = (ROOT / q.page).read_text()
    if not ((ROOT / q.source).is_file() and _committed(q.source)):
        pytest.fail(f"{q}: {q.source} is not a committed file", pytrace=False)
    if q.source not in page:
        pytest.fail(f"{q.page} quotes '{q.says}' without naming its source {q.source}", pytrace=False)
    found = _numbers(page, (q.says,))
    if found is None:
        pytest.fail(f"{q.page} no longer says '{q.says}' (its figure comes from {q.source}): put the figure back as "
                    f"{q.source} has it, or change this entry in tests/test_readme_numbers.py", pytrace=False)
    source = _numbers((ROOT / q.source).read_text(), q.source_templates)
    if source is None:
        pytest.fail(f"{q.source} no longer holds '{' ... '.join(q.source_templates)}' (quoted by {q.page})",
                    pytrace=False)
    (quoted, said), (held, held_said) = found, source
    if len(quoted) != len(held):
        pytest.fail(f"{q}: {len(quoted)} number(s) quoted, {len(held)} in the source's words", pytrace=False)
    wrong = [f"{q.page} quotes {a} (number {i + 1} in '{said[0]}') but {q.source} says {b} ('{' ... '.join(held_said)}')"
             for i, (a, b) in enumerate(zip(quoted, held)) if not _agree(a, b)]
    if wrong:
        pytest.fail("\n".join(wrong), pytrace=False)


# a figure with a unit of time, or one in words, that a reader takes as measured
FIGURE = re.compile(r"(?<![\w.\-])~?\d+(?:\.\d+)?(?:\s*[-–]\s*\d+(?:\.\d+)?)?\s*(?:s|ms|min|minutes?|seconds?|hours?)\b"
                    r"|\babout\s+(?:a|an|one|two|three)\s+(?:minute|second|hour)s?\b|\btens\s+of\s+thousands\b")


def test_every_readme_figure_names_its_file():
    text = (ROOT / "README.md").read_text()
    covered = [m.span() for q in QUOTES if q.page == "README.md" for m in _pattern(q.says).finditer(text)]
    loose = [m for m in FIGURE.finditer(text) if not any(a < m.end() and m.start() < b for a, b in covered)]
    lines = [f"README.md line {text.count(chr(10), 0, m.start()) + 1}: '{m.group(0)}'" for m in loose]
    if lines:
        pytest.fail("figures the README quotes with no source file (name the committed file beside each and add it "
                    "to QUOTES in tests/test_readme_numbers.py, or drop the figure):\n  " + "\n  ".join(lines),
                    pytrace=False)

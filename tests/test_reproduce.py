"""The quoted results (README.md and the docs/ pages it links) are backed by committed files that
tools/reproduce.sh regenerates (no rendering)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest
from uavsearch.testing.clean_env import clean_env

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "tools" / "reproduce.sh"
# An absolute path: a slash that starts a token (not "m/s", not "Aacc / AF1") followed by a path segment.
ABSOLUTE = re.compile(r"(?:^|[\s`'\"(=:,])/[A-Za-z0-9_.-]+/")
# Lines that name a results file full mode writes but that is not committed yet say so in these words.
PENDING = "not committed yet"


def readme_results_paths() -> dict[str, bool]:
    """{results path named in README.md or docs/*.md: whether its line marks it as pending}."""
    paths: dict[str, bool] = {}
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    for line in (ln for page in pages for ln in page.read_text().splitlines()):
        for m in re.finditer(r"results/[A-Za-z0-9_./-]*[A-Za-z0-9_]", line):
            paths[m.group(0)] = paths.get(m.group(0), False) or PENDING in line
    return paths


def test_readme_results_files_exist():
    paths = readme_results_paths()
    assert "results/single_view/table1.md" in paths and "results/search/table2.md" in paths
    missing = [p for p, pending in paths.items() if not pending and not (ROOT / p).exists()]
    assert not missing, f"README.md / docs name results files that are not in the repository: {missing}"
    files = [p for p in paths if Path(p).suffix]
    assert len(files) >= 8, files


def test_results_files_hold_no_absolute_path():
    texts = [p for p in (ROOT / "results").rglob("*") if p.suffix in (".md", ".csv", ".json")]
    assert len(texts) >= 8
    bad = {str(p.relative_to(ROOT)): m.group(0).strip() for p in texts
           for m in [ABSOLUTE.search(p.read_text())] if m}
    assert not bad, f"absolute paths in results files: {bad}"


def test_absolute_path_pattern():
    assert ABSOLUTE.search("perception /work/main/models/perception.pt (tag x)")
    assert ABSOLUTE.search("checkpoint `/home/u/models/perception.pt`")
    assert not ABSOLUTE.search("perception models/perception.pt; 97.2 / 0.257 Aacc % / AF1, 0.3 m/s")


def run_script(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, timeout=60,
                          env={"PATH": "/usr/bin:/bin", "PY": sys.executable})


def test_help():
    r = run_script("--help")
    assert r.returncode == 0, r.stderr
    for word in ("--quick", "--ship", "--jobs", "--dry-run", "results/training_seeds", "estimate", "measured"):
        assert word in r.stdout


def test_quick_dry_run_lists_shipped_model_steps_only():
    r = run_script("--quick", "--dry-run")
    assert r.returncode == 0, r.stderr
    assert "[1/2] single_view" in r.stdout and "[2/2] search" in r.stdout
    assert "--out results/single_view" in r.stdout and "--out results/search" in r.stdout
    assert "train " not in r.stdout  # no training in --quick
    for step in ("train_perception", "view_caches", "train_policy", "search_large", "flight", "training_seeds"):
        assert f"skip: {step} (full mode only)" in r.stdout
    assert "skip: ship" in r.stdout
    assert not ABSOLUTE.search(r.stdout.replace(sys.executable, "PY"))


def test_full_dry_run_trains_into_runs_and_ships_only_when_asked():
    r = run_script("--dry-run", "--jobs", "2")
    assert r.returncode == 0, r.stderr
    trains = [ln for ln in r.stdout.splitlines() if " train policy " in ln]
    assert len(trains) == 45  # 5 fusions x 3 settings x training seeds 0-2
    assert all("--out runs/reproduce/seed" in ln and "--seed " in ln for ln in trains)
    assert "train perception --seed 1" in r.stdout and "--out runs/reproduce/perception.pt" in r.stdout
    assert "models/perception.pt &&" not in r.stdout and "skip: ship" in r.stdout
    shipped = run_script("--dry-run", "--ship")
    assert "cp runs/reproduce/perception.pt models/perception.pt &&" in shipped.stdout


@pytest.mark.parametrize("args", [("--bogus",), ("--jobs", "x"), ("--quick", "--ship"), ("--only", "nosuchstep")])
def test_bad_options_are_one_line_errors(args):
    r = run_script(*args, "--dry-run")
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and "reproduce.sh:" in r.stderr


def test_seed_spread_table(tmp_path):
    """tools/seed_spread.py on two committed Table IIs: per-folder rows and their mean, as in the CSVs."""
    out = tmp_path / "spread.md"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "seed_spread.py"), "results/search",
                        "results/search_large", "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                       timeout=120, env=clean_env())
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    import csv

    from uavsearch.search.evaluate.search import gap_closure

    first = {}
    for name in ("search", "search_large"):  # each folder's row, setting 1, as its CSV says
        with (ROOT / "results" / name / "table2.csv").open() as f:
            rows = [{k: (v if k in ("method", "key") else float(v)) for k, v in r.items()} for r in csv.DictReader(f)]
        by = {r["key"]: r for r in rows}
        first[name] = (by["learned_policy"]["s1_aacc"], by["learned_policy"]["s1_af1"])
        assert (f"| {name} | {first[name][0]:.2f} / {first[name][1]:.3f} ({by['learned_coverage']['s1_af1']:.3f}; "
                f"{100 * gap_closure(rows, 1):.0f}%)") in text
    af1 = [f for _, f in first.values()]
    assert f"| mean ± std | {sum(a for a, _ in first.values()) / 2:.2f} ± " in text
    assert f" / {sum(af1) / 2:.3f} ± {abs(af1[0] - af1[1]) / 2:.3f} (gap " in text
    assert not ABSOLUTE.search(text)


def test_display_path(tmp_path):
    from uavsearch.paths import MODELS_DIR, display_path

    assert display_path(MODELS_DIR / "perception.pt") == "models/perception.pt"
    assert display_path("models/perception.pt") == "models/perception.pt"
    assert display_path(tmp_path / "x" / "perception.pt") == "perception.pt"

"""The README's quick starts, run as written: every ```bash block under a `## Quick start` heading.

Each block runs in bash with -e (a failing command fails the block) from a scratch folder that links the
repository's tools/ and missions/, with this Python's `python` and `uavsearch` first on PATH, bounded in
time. Two things differ from a reader's terminal so that the test can run beside other flights on the same
machine: the well-known ports 14540 / 14550 become free ports (also `uavsearch sitl`'s defaults), and
`uavsearch sitl` binds free source ports; a block that fails stops what it started in the background.
A block preceded by `<!-- quickstart: slow -->` runs only with `-m slow`; its quick start keeps a fast block.
A zero exit is not enough: every `--out` must hold what its line's comment promises, readable.
"""

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from uavsearch.flight.sitl_process import free_udp_port
from uavsearch.paths import REPO_ROOT
from uavsearch.testing.clean_env import clean_env

README = REPO_ROOT / "README.md"
SLOW = "<!-- quickstart: slow -->"
TIMEOUT_S = 240  # per block: the first evaluation renders its view cache (about a minute on 2 busy cores)


def quickstart_blocks(text: str) -> list[tuple[str, int, str, bool]]:
    """(section title, block number, bash text, slow) for every bash block of every quick-start section."""
    blocks = []
    for section in re.split(r"(?m)^## ", text)[1:]:
        title, _, body = section.partition("\n")
        if not title.lower().startswith("quick start"):
            continue
        for i, m in enumerate(re.finditer(r"(?ms)^(<!-- quickstart: slow -->\n)?```bash\n(.*?)^```", body)):
            blocks.append((title.strip(), i + 1, m.group(2), bool(m.group(1))))
    return blocks


BLOCKS = quickstart_blocks(README.read_text())


def test_readme_has_three_quick_starts_each_with_a_fast_block():
    titles = {t for t, *_ in BLOCKS}
    assert len(titles) == 3, titles
    for t in titles:
        assert any(not slow for title, _, _, slow in BLOCKS if title == t), f"{t}: every block is slow"


def _params():
    for title, i, text, slow in BLOCKS:
        marks = [pytest.mark.slow] if slow else []
        yield pytest.param(text, id=f"{title.split(':', 1)[-1].strip().split()[0]}-{i}", marks=marks)


FILE_NAME = r"[\w.-]+\.(?:png|gif|mp4|md|csv|json|jsonl|tlog|pt|html|plan)"
# what a block without an --out says it prints
PRINTS = {"connect-1": r"system 1 in mode \S+, -?\d+\.\d m above home"}


def promised_outputs(block: str) -> list[tuple[str, list[str]]]:
    """(--out path, the file names its line's comment promises in it) for every command line of a block."""
    out = []
    for line in block.splitlines():
        command, _, comment = line.partition("#")
        m = re.search(r"--out\s+(\S+)", command)
        if m:
            out.append((m.group(1), re.findall(FILE_NAME, comment)))
    return out


def test_promised_outputs_are_read_from_the_commands_and_their_comments():
    block = "uavsearch replay runs/a --out runs/b   # trajectory.png, maps.png (and more)\nuavsearch x --out c.pt\n"
    assert promised_outputs(block) == [("runs/b", ["trajectory.png", "maps.png"]), ("c.pt", [])]
    fly = next(b for t, _, b, _ in BLOCKS if t.endswith("fly a search"))
    assert [p for p, _ in promised_outputs(fly)] == ["runs/wide", "runs/wide_replay", "runs/scene7", "runs/scene7.png"]
    assert set(PRINTS) <= {p.id for p in _params()}


def check_output(path: Path) -> None:
    """What a block wrote is there and reads as what it is (a flight log, a picture, a table, a model)."""
    assert path.exists(), f"{path} was not written"
    if path.is_dir():
        assert any(path.iterdir()), f"{path} is empty"
        if (path / "search.jsonl").is_file():  # a flight log: a completed flight with its images and telemetry
            from uavsearch.logs.flight_log import read_flight_log

            log = read_flight_log(path)
            assert log.steps and log.summary["status"] == "completed", path
            assert len(list((path / "images").glob("*.png"))) == len(log.steps)
            assert (path / "telemetry.tlog").stat().st_size > 0
        return
    assert path.stat().st_size > 0, f"{path} is empty"
    kind = path.suffix
    if kind in (".png", ".gif"):
        import imageio.v2 as imageio

        assert imageio.imread(path).shape[0] > 100, path
    elif kind in (".json", ".plan"):
        json.loads(path.read_text())
    elif kind == ".csv":
        assert len(path.read_text().splitlines()) >= 2, path
    elif kind == ".pt":
        from uavsearch.search.policy import load_search_model

        load_search_model(path)


@pytest.mark.parametrize("block", list(_params()))
def test_quickstart_block_runs_as_written(block, tmp_path, request):
    for name in ("tools", "missions", "models"):
        (tmp_path / name).symlink_to(REPO_ROOT / name)
    api, gcs = free_udp_port(), free_udp_port()
    script = block.replace("14540", str(api)).replace("14550", str(gcs))
    script = re.sub(r"\buavsearch sitl\b", f"uavsearch sitl --api-port {api} --gcs-port {gcs} --api-local-port 0 "
                    "--gcs-local-port 0", script)
    # a block that fails leaves nothing running in the background
    script = "trap 'rc=$?; kill $(jobs -p) 2>/dev/null || true; exit $rc' EXIT\n" + script
    bin_dir = Path(sys.executable).parent
    env = clean_env(PYTHONPATH=str(REPO_ROOT))  # no UAVSEARCH_RUNS: runs/ of the scratch folder, as in a clone
    if not (bin_dir / "uavsearch").exists():  # a Python without the console script: the same entry point
        (tmp_path / "bin").mkdir()
        (tmp_path / "bin" / "uavsearch").write_text(f"#!/bin/sh\nexec {sys.executable} -m uavsearch \"$@\"\n")
        (tmp_path / "bin" / "uavsearch").chmod(0o755)
        env["PATH"] = f"{tmp_path / 'bin'}{os.pathsep}{env['PATH']}"
    proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", script], cwd=tmp_path, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=TIMEOUT_S)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # whatever the block left running in the background
        except ProcessLookupError:
            pass
        proc.wait()
    assert proc.returncode == 0, f"$ {script}\n{out}"
    assert "Traceback" not in out, out
    assert "udpin:127.0.0.1:0 " not in out  # messages name the real port
    # and it did what the README says: each --out holds what the line's comment names, and reads
    for where, names in promised_outputs(block):
        check_output(tmp_path / where)
        for name in names:
            check_output(tmp_path / where / name)
    expect = PRINTS.get(request.node.callspec.id)
    assert expect is None or re.search(expect, out), out

"""`uavsearch fly` as a real process: SIGTERM mid-flight lands like Ctrl-C and writes summary.json; a second
SIGTERM abandons the landing and ends at once. The handler is the command's, restored after it; importing the
package sets none."""

import json
import signal
import subprocess
import sys
import time

from uavsearch.errors import Terminated, sigterm_as_interrupt
from uavsearch.paths import MISSIONS_DIR
from uavsearch.testing.clean_env import clean_env

PAPER = MISSIONS_DIR / "default.yaml"


def _fly(run, *args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "uavsearch", "fly", "--mission", str(PAPER), "--out", str(run),
                             "--gcs-port", "0", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=clean_env())


def _read_until(proc, out: list, word: str, deadline: float) -> None:
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        out.append(line)
        if not line or word in line:
            return


def test_sigterm_mid_flight_lands_and_writes_the_summary(tmp_path):
    run = tmp_path / "run"
    proc = _fly(run, "--speed", "max")
    out = []
    try:
        _read_until(proc, out, "step 1/", time.monotonic() + 240)
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=120)
        out.append(rest)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(out)
    assert "Traceback" not in text and "interrupted (SIGTERM): ending the mission" in text, text
    assert proc.returncode == 1, text  # a flight that did not complete, as after Ctrl-C
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["end"] == "landed", summary
    assert 1 <= summary["steps"] < 5


def test_a_second_sigterm_abandons_the_landing_at_once(tmp_path):
    run = tmp_path / "run"
    proc = _fly(run, "--speed", "max")
    out = []
    try:
        deadline = time.monotonic() + 240
        _read_until(proc, out, "step 1/", deadline)
        proc.send_signal(signal.SIGTERM)
        _read_until(proc, out, "landing", deadline)  # the landing has begun
        proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        rest, _ = proc.communicate(timeout=60)
        took = time.monotonic() - t0
        out.append(rest)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(out)
    assert "Traceback" not in text and "end action abandoned: SIGTERM again during the land" in text, text
    assert took < 10, f"{took:.1f} s after the second SIGTERM"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["end"].startswith("end action abandoned"), summary


def test_the_handler_is_the_commands_and_comes_back_after_it():
    before = signal.getsignal(signal.SIGTERM)
    r = subprocess.run([sys.executable, "-c", "import signal, uavsearch.cli, uavsearch.fly.mission_controller; "
                        "print(signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)"],
                       capture_output=True, text=True, timeout=120, env=clean_env())
    assert r.stdout.strip() == "True", r.stdout + r.stderr  # importing sets nothing
    with sigterm_as_interrupt():
        assert signal.getsignal(signal.SIGTERM) is not before
        try:
            signal.raise_signal(signal.SIGTERM)
        except Terminated as e:
            assert isinstance(e, KeyboardInterrupt) and str(e) == "SIGTERM"
        else:
            raise AssertionError("SIGTERM did not raise")
    assert signal.getsignal(signal.SIGTERM) is before

"""The lockstep runner: determinism on simulation time, and one-line errors for bad command lines."""

import math

import numpy as np
import pytest

from uavsearch.flight.commander import VehicleCommand
from uavsearch.flight.sitl import Sitl, SitlConfig, main


def _fly(seed: int, tmp_path) -> np.ndarray:
    """Arm, take off, reposition and sample the TRUE position on a fixed simulation-time grid (no links)."""
    cfg = SitlConfig(seed=seed, scene_seed=None, speed=math.inf, api_port=0, gcs_port=0, run_dir=tmp_path / f"s{seed}",
                     params={"MIS_TAKEOFF_ALT": 5.0})
    sitl = Sitl(cfg)
    try:
        sitl.run(2.0)
        c = sitl.commander
        assert c.handle_command(VehicleCommand(400, 1.0)) == 0
        assert c.handle_command(VehicleCommand(22)) == 0
        track = []
        for i in range(24):
            if i == 8:
                lla = cfg.home.enu_to_geodetic([3.0, 6.0, 0.0])
                assert c.handle_command(VehicleCommand(192, -1, 1, 0, math.nan, lla[0], lla[1], cfg.home.alt_m + 6.0)) == 0
            sitl.run(0.5)
            track.append(sitl.vehicle.true_state.position_enu_m.copy())
        return np.array(track)
    finally:
        sitl.close()


def test_same_seed_same_flight_other_seed_other_noise(tmp_path):
    a = _fly(7, tmp_path)
    b = _fly(7, tmp_path)
    c = _fly(8, tmp_path)
    np.testing.assert_array_equal(a, b)  # bit-identical: wall-clock pacing never enters the trajectory
    assert not np.array_equal(a, c)
    assert np.allclose(a[-1], [3.0, 6.0, 6.0], atol=1.0)  # and it went where it was sent


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--speed", "fast"], "speed"),
        (["--home", "91,0"], "--home"),
        (["--signing-key", "abc"], "signing-key"),
        (["--param", "NOPE_PARAM=1", "--no-camera-scene"], "unknown parameter NOPE_PARAM"),
        (["--param", "GF_ACTION=99", "--no-camera-scene"], "GF_ACTION"),
    ],
)
def test_bad_command_lines_fail_in_one_line(argv, words, capsys, tmp_path):
    """Exit status 2 and one line naming the problem, whether argparse (SystemExit) or the runner refuses it."""
    try:
        code = main(argv + ["--out", str(tmp_path), "--api-port", "0", "--gcs-port", "0"])
    except SystemExit as e:
        code = e.code
    assert code == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err

"""Mission files: the shipped ones validate; every kind of bad file is one line naming the field."""

import pytest

from uavsearch.errors import MissionError
from uavsearch.fly.missions import DEFAULT_MISSION, load_mission, mission_from_dict
from uavsearch.paths import MISSIONS_DIR
from uavsearch.testing.clean_env import clean_env


def test_default_mission_is_paper_setting_2():
    m = load_mission()
    assert m.source == str(DEFAULT_MISSION)
    assert (m.scene.setting, m.scene.k) == (2, 5)
    c = m.search_config()
    assert (c.altitude_m, c.step_m, c.budget_T) == (70.0, 10.0, 5)
    assert c.actions == ("MoveAhead", "MoveRight", "MoveLeft", "MoveBack")
    assert (m.fusion, m.policy) == ("learned", "learned")
    assert m.checkpoint_path.name == "search_s2_learned.pt"
    assert m.flight_settings().arrive_radius_m == 0.5 and m.flight_settings().settle_speed_m_s == 0.3


@pytest.mark.parametrize("path", sorted(MISSIONS_DIR.glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_mission_validates(path):
    m = load_mission(path)
    assert m.search_config().budget_T >= 1
    assert m.flight.end_action in ("land", "rtl", "none")


def test_overrides_revalidate():
    m = load_mission().with_overrides(**{"scene.seed": 9, "flight.speed": 4.0})
    assert m.scene.seed == 9 and m.speed_factor == 4.0
    with pytest.raises(MissionError, match="flight.speed"):
        load_mission().with_overrides(**{"flight.speed": -1})


BAD = [
    ({"search": {"budget_T": 0}}, "search.budget_T", "greater than or equal to 1"),
    ({"search": {"altitude_m": "high"}}, "search.altitude_m", "valid number"),
    ({"search": {"actions": ["MoveUp"]}}, "search.actions", "unknown action"),
    ({"fusion": "median"}, "fusion", "'learned'"),
    ({"policy": "magic"}, "policy", "'learned'"),
    ({"flight": {"speed": "fast"}}, "flight.speed", ""),
    ({"flight": {"end_action": "crash"}}, "flight.end_action", "'land'"),
    ({"home": {"lat_deg": 123}}, "home.lat_deg", "less than or equal to 90"),
    ({"scene": {"seed": 1, "setting": 7}}, "scene.setting", "the paper's settings are 1, 2, 3"),
    ({"scene": {"seed": 1, "setting": 2, "occupied_cells": 4}}, "setting OR occupied_cells", ""),
    ({"budget_T": 5}, "budget_T", "unknown field"),
    ({"search": {"budgetT": 5}}, "search.budgetT", "unknown field"),
]


@pytest.mark.parametrize("data,field,problem", BAD, ids=[b[1] for b in BAD])
def test_bad_mission_is_one_line_naming_the_field(data, field, problem):
    with pytest.raises(MissionError) as e:
        mission_from_dict(data, "x.yaml")
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith("mission x.yaml: ")
    assert field in msg and problem in msg


def test_bad_files(tmp_path):
    cases = {"syntax.yaml": "search: {budget_T: 5\n", "list.yaml": "- 1\n- 2\n", "empty.yaml": ""}
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(MissionError, match="not valid YAML at line"):
        load_mission(tmp_path / "syntax.yaml")
    with pytest.raises(MissionError, match="YAML mapping"):
        load_mission(tmp_path / "list.yaml")
    assert load_mission(tmp_path / "empty.yaml").search.budget_T == 5  # every field has a default
    with pytest.raises(MissionError, match="cannot read"):
        load_mission(tmp_path / "missing.yaml")


def test_cli_bad_mission_prints_one_line_and_exits_2(tmp_path, capsys):
    from uavsearch.cli import main

    bad = tmp_path / "bad.yaml"
    bad.write_text("search:\n  budget_T: -3\n")
    assert main(["fly", "--mission", str(bad)]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert lines == [f"uavsearch: error: mission {bad}: search.budget_T: Input should be greater than or equal to 1 (got -3)"]


def test_read_without_the_registry_imports_no_torch_and_checks_names_later(tmp_path):
    """`uavsearch fly` reads its mission before torch is imported (its vehicle starts meanwhile); the names
    are checked against the agent registry afterwards, with the same one-line error."""
    import subprocess
    import sys

    code = ("import sys; from uavsearch.fly.missions import load_mission; "
            "from uavsearch.fly.mission_controller import fly; "
            "m = load_mission(check_registry=False).with_overrides(check_registry=False, **{'scene.seed': 4}); "
            "print(m.scene.seed, 'torch' in sys.modules, 'scipy' in sys.modules, 'gymnasium' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=clean_env()).stdout.split()
    assert out == ["4", "False", "False", "False"]
    # a family's search config (its flight speeds are the autopilot's parameter defaults) leaves the vehicle's
    # estimator and scipy to the vehicle process
    code = ("import sys; from uavsearch.fly.missions import load_mission; "
            "m = load_mission(sys.argv[1], check_registry=False); c = m.search_config(); "
            "print(c.lattice.num_positions, 'uavsearch.flight.estimator' in sys.modules, 'scipy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(MISSIONS_DIR / "wide.yaml")], capture_output=True, text=True,
                         check=True, env=clean_env()).stdout.split()
    assert out == ["73", "False", "False"]
    (tmp_path / "m.yaml").write_text("fusion: nope\n")
    m = load_mission(tmp_path / "m.yaml", check_registry=False)
    with pytest.raises(MissionError, match=r"^mission .*m\.yaml: fusion: unknown fusion method 'nope'"):
        m.check_registry()
    with pytest.raises(MissionError, match="unknown fusion method 'nope'"):
        load_mission(tmp_path / "m.yaml")


def test_altitude_layers_reach_the_search_config():
    from uavsearch.fly.missions import mission_from_dict

    m = mission_from_dict({"search": {"altitudes_m": [70, 40], "allow_untrained": True,
                                      "actions": ["MoveAhead", "MoveRight", "MoveLeft", "MoveBack", "Descend", "Climb"]}},
                          "m.yaml", check_registry=False)
    c = m.search_config()
    assert c.layers_m == (70.0, 40.0) and c.lattice.num_positions == 50
    bad = mission_from_dict({"search": {"altitudes_m": [40, 70], "allow_untrained": True}}, "m.yaml",
                            check_registry=False)
    with pytest.raises(MissionError, match="first lattice altitude"):
        bad.search_config()

"""Mission and plan files that try to hurt: each is refused in one line, never a traceback, a hang, a run folder
outside the runs root or a NaN that reaches the vehicle. Generated documents (hypothesis) get a valid mission or
one MissionError line from the validator."""

import json
import math
import os
import subprocess
import sys
import threading

import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from uavsearch.errors import MissionError, UavsearchError
from uavsearch.flight.mission import MAX_ITEMS
from uavsearch.flight.sitl_process import SitlProcess, free_udp_port
from uavsearch.fly.bounded_read import MAX_DEPTH, MISSION_MAX_BYTES
from uavsearch.fly.missions import DEFAULT_MISSION, Mission, load_mission, mission_from_dict
from uavsearch.fly.plan_files import load_plan
from uavsearch.testing.clean_env import clean_env

PROPERTY = settings(max_examples=200, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _one_line(e: BaseException) -> str:
    msg = str(e)
    assert len(msg.splitlines()) == 1, msg
    return msg


def _cli(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "uavsearch", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=clean_env())


def _refused_in_one_line(r, *words):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("uavsearch: error: "), r.stderr
    assert "Traceback" not in r.stderr and all(w in lines[0] for w in words), lines[0]


# -- hostile files ------------------------------------------------------------------------------------


def test_hostile_mission_files_are_one_line_from_fly_and_mission_upload(tmp_path):
    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 50_000 + "]" * 50_000 + "\n")
    latin1 = tmp_path / "latin1.yaml"
    latin1.write_bytes("name: caf\u00e9\n".encode("latin-1"))
    for path, words in ((deep, ["nested deeper than"]), (latin1, ["not UTF-8", "0xe9"]),
                        ("/dev/zero", ["not a regular file"])):
        _refused_in_one_line(_cli("fly", "--mission", path), str(path), *words)
        _refused_in_one_line(_cli("mission", "upload", path), str(path), *words)


@pytest.mark.parametrize("text,words", [
    ("a: " + "{b: " * 40 + "1" + "}" * 40 + "\n", ["nested deeper than"]),
    ("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, "
                                                           f"*{p}, *{p}]\n" for p, c in zip("abcdefgh", "bcdefghi")),
     ["more than 100000 values"]),  # ten to the ninth values through aliases
    ("when: 2001-13-45\n", ["not valid YAML"]),
    ("seed: " + "9" * 5000 + "\n", ["not valid YAML"]),
    ("name: !!python/object:os.system x\n", ["not valid YAML"]),
    ("{[1]: 2}\n", ["not valid YAML"]),
    ("home:\n  alt_m: .nan\n", ["home.alt_m", "finite"]),
    ("name: x/../../../tmp/escaped\n", ["name: a name, not a path"]),
])
def test_hostile_mission_text_is_one_line(tmp_path, text, words):
    path = tmp_path / "m.yaml"
    path.write_text(text)
    with pytest.raises(MissionError) as e:
        load_mission(path, check_registry=False)
    msg = _one_line(e.value)
    assert msg.startswith(f"mission {path}: ") and all(w in msg for w in words), msg


def test_a_fifo_an_oversize_file_and_a_folder_are_refused_without_reading_them(tmp_path):
    fifo = tmp_path / "m.yaml"
    os.mkfifo(fifo)
    got = []
    t = threading.Thread(target=lambda: got.append(_attempt(load_mission, fifo)), daemon=True)
    t.start()
    t.join(10)
    assert got and "not a regular file" in got[0]  # no writer ever opens the FIFO: reading it would block
    big = tmp_path / "big.yaml"
    big.write_bytes(b"#" * (MISSION_MAX_BYTES + 1))
    assert "larger than 1 MiB" in _attempt(load_mission, big)
    assert "not a regular file" in _attempt(load_plan, tmp_path)
    assert "cannot read" in _attempt(load_plan, tmp_path / "missing.plan")


def _attempt(load, path) -> str:
    try:
        load(path)
    except MissionError as e:
        return _one_line(e)
    raise AssertionError(f"{path} was accepted")


def _plan(n_items: int) -> dict:
    item = {"type": "SimpleItem", "command": 16, "frame": 3, "params": [0, 0, 0, 0, 47.4, 8.5, 10],
            "autoContinue": True}
    return {"fileType": "Plan", "version": 1,
            "mission": {"version": 2, "plannedHomePosition": [47.4, 8.5, 488.0], "items": [item] * n_items}}


def test_a_plan_past_the_mission_protocol_s_count_is_one_line(tmp_path):
    big = tmp_path / "big.plan"
    big.write_text(json.dumps(_plan(70_000), separators=(",", ":")))
    _refused_in_one_line(_cli("mission", "upload", big), "70000 mission items", "at most 65535")
    wpl = tmp_path / "big.waypoints"
    wpl.write_text("QGC WPL 110\n" + "".join(f"{i}\t0\t3\t16\t0\t0\t0\t0\t47.4\t8.5\t10\t1\n" for i in range(70_001)))
    assert "70000 mission items" in _attempt(load_plan, wpl)
    deep = tmp_path / "deep.plan"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    assert "nested deeper than" in _attempt(load_plan, deep)
    nan = tmp_path / "nan.plan"
    nan.write_text(json.dumps(_plan(2)).replace("488.0", "NaN"))
    assert "NaN is not a number" in _attempt(load_plan, nan)
    nan.write_text(json.dumps(_plan(2)).replace("488.0", "1e999"))
    assert "mission.plannedHomePosition.2: Input should be a finite number" in _attempt(load_plan, nan)


def test_a_plan_past_the_vehicle_s_capacity_is_refused_by_the_vehicle_in_one_line(tmp_path):
    """The vehicle answers a MISSION_COUNT it cannot hold with MAV_MISSION_NO_SPACE; `mission upload` says so."""
    path = tmp_path / "over.plan"
    path.write_text(json.dumps(_plan(MAX_ITEMS + 1)))
    sitl = SitlProcess(tmp_path / "v", gcs_port=free_udp_port(), speed="max", camera=False, env=clean_env())
    try:
        r = _cli("mission", "upload", path, "--connect", f"udpin:127.0.0.1:{sitl.gcs_port}", timeout=120)
    finally:
        sitl.stop()
    _refused_in_one_line(r, "MAV_MISSION_NO_SPACE", f"{MAX_ITEMS + 1} item(s) sent")


# -- every float field, and the run folder -----------------------------------------------------------


def _float_fields(model=Mission, prefix=""):
    """Dotted paths of every float field of the mission schema (nested sections included)."""
    for name, f in model.model_fields.items():
        ann = f.annotation
        args = getattr(ann, "__args__", ()) or (ann,)
        sections = [a for a in args if isinstance(a, type) and issubclass(a, Mission.__mro__[1])]
        if sections:
            yield from _float_fields(sections[0], f"{prefix}{name}.")
        elif float in args or ann is float or "float" in str(ann):
            yield f"{prefix}{name}"


FLOAT_FIELDS = sorted(set(_float_fields()))


def _nested(path: str, value) -> dict:
    *parents, leaf = path.split(".")
    d = {leaf: [value] if path == "search.altitudes_m" else value}
    for p in reversed(parents):
        d = {p: d}
    return d


def test_the_schema_s_float_fields_are_found():
    assert {"home.alt_m", "home.lat_deg", "flight.speed", "flight.settle_time_s", "search.step_m",
            "camera.hfov_deg", "team.mission_time_s", "search.altitudes_m"} <= set(FLOAT_FIELDS)


@pytest.mark.parametrize("field", FLOAT_FIELDS)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
def test_nan_and_infinities_are_refused_in_every_float_field(field, value):
    with pytest.raises(MissionError) as e:
        mission_from_dict(_nested(field, value), "x.yaml", check_registry=False)
    assert _one_line(e.value).startswith(f"mission x.yaml: {field}")


@pytest.mark.parametrize("name", ["x/../../../tmp/escaped", "/tmp/escaped", "..", "a\\b", "a\nb", "a\x00b", "", "."])
def test_a_mission_name_is_a_name_not_a_path(name):
    with pytest.raises(MissionError, match="name: a name, not a path"):
        mission_from_dict({"name": name}, "x.yaml", check_registry=False)


# -- generated documents ------------------------------------------------------------------------------

SCALARS = (st.none() | st.booleans() | st.integers(-10**20, 10**20) | st.floats() | st.text(max_size=20)
           | st.sampled_from(["max", "land", "wide", "learned", "greedy", "MoveAhead", ".nan", "-.inf", "1e999"]))
KEYS = st.text(max_size=12) | st.sampled_from(["name", "home", "alt_m", "speed", "seed", "setting", "team", "search"])
YAMLABLE = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(KEYS, inner, max_size=4),
                        max_leaves=20)
VALID = Mission().model_dump(mode="json")
PATHS = sorted({f"{k}.{sub}" if isinstance(v, dict) else k for k, v in VALID.items()
                for sub in (v if isinstance(v, dict) else [None])} - {"source"}) + ["team.vehicles", "team.max_views"]


@st.composite
def near_valid(draw):
    """The default mission with a few fields replaced by generated values (or dropped, or an unknown key)."""
    doc = json.loads(json.dumps(VALID))
    for _ in range(draw(st.integers(1, 3))):
        *parents, leaf = draw(st.sampled_from(PATHS + ["unknown", "home.unknown"])).split(".")
        d = doc
        for p in parents:
            if not isinstance(d.get(p), dict):
                d[p] = {}
            d = d[p]
        if draw(st.booleans()) and leaf in d:
            del d[leaf]
        else:
            d[leaf] = draw(YAMLABLE)
    return doc


def _check_answer(doc, source="gen.yaml"):
    """A valid mission (finite floats, a run folder inside the runs root) or one MissionError line."""
    from uavsearch.fly.mission_controller import default_run_dir
    from uavsearch.paths import RUNS_DIR

    try:
        m = mission_from_dict(doc, source, check_registry=False)
    except UavsearchError as e:
        _one_line(e)
        return
    stack = [m.model_dump(mode="python")]
    while stack:
        v = stack.pop()
        if isinstance(v, dict):
            stack.extend(v.values())
        elif isinstance(v, (list, tuple)):
            stack.extend(v)
        elif isinstance(v, float):
            assert math.isfinite(v), doc
    assert default_run_dir(m).resolve().parent == RUNS_DIR.resolve()


@PROPERTY
@given(st.one_of(YAMLABLE, near_valid()))
@example({"a\nb": 1})
@example({"home": {"alt_m\u2028": 1}})
@example({"scene": {"seed": 1, "setting": "2\n"}})
def test_generated_documents_get_a_mission_or_one_line(doc):
    _check_answer(doc)


@PROPERTY
@given(st.one_of(near_valid(), YAMLABLE, st.binary(max_size=200)))
def test_generated_files_get_a_mission_or_one_line(tmp_path_factory, data):
    path = tmp_path_factory.getbasetemp() / "generated.yaml"
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        path.write_text(yaml.safe_dump(data, allow_unicode=True))
    try:
        load_mission(path, check_registry=False)
    except UavsearchError as e:
        assert _one_line(e).startswith(f"mission {path}: ")


@PROPERTY
@given(st.text(max_size=60))
def test_a_valid_name_keeps_its_run_folder_in_the_runs_root(name):
    _check_answer({"name": name})


def test_the_shipped_default_mission_is_within_every_bound():
    assert len(DEFAULT_MISSION.read_bytes()) < MISSION_MAX_BYTES and MAX_DEPTH >= 8
    assert load_mission(DEFAULT_MISSION, check_registry=False).name == "default"

"""Scene families declare their task: a variant added to a settings file by declaration alone ("2-dusk": setting 2
rendered darker) searches with setting 2's task and models, in teleport and in flight, and both draw it darker.

The flight is one short `uavsearch fly` (T = 1: take off, one view, land; --speed max) of real processes over real
UDP; the vehicle process reads the same settings file through UAVSEARCH_SCENE_SETTINGS.
"""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from uavsearch.errors import SceneError
from uavsearch.geometry import camera_pose_from_vehicle
from uavsearch.search.config import setting_config
from uavsearch.testing.clean_env import clean_env
from uavsearch.world import settings
from uavsearch.world.render import SceneRenderer

DUSK = {"ambient": 0.3, "diffuse": 0.2}
SEED = 3  # a paper-split scene of setting 2


def _settings_with(tmp: Path, **families) -> Path:
    cfg = yaml.safe_load(settings.SETTINGS_FILE.read_text())
    cfg["families"].update(families)
    path = tmp / "settings.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def dusk_file(tmp_path_factory):
    path = _settings_with(tmp_path_factory.mktemp("families"), **{"2-dusk": {"variant_of": 2, "task": {"render": DUSK}}})
    with settings.settings_file(path):
        yield path


def _brightness(rgb) -> float:
    return float(np.asarray(rgb, dtype=np.float64).mean())


def test_a_variant_searches_its_base_task_with_its_own_render_options(dusk_file):
    dusk, two = settings.setting_params("2-dusk"), settings.setting_params("2")
    assert dusk.variant_of == "2" and dusk.task.render.ambient == DUSK["ambient"]
    assert dusk.task.model_dump(exclude={"render"}) == two.task.model_dump(exclude={"render"})
    assert dusk.task.mission == "moves" and dusk.task.fusion == "learned" and dusk.task.policies == "search_s2"
    assert settings.scene_seeds("2-dusk", "paper", "test") == settings.scene_seeds(2, "paper", "test")
    assert settings.generate_setting_scene("2-dusk", SEED) == settings.generate_setting_scene(2, SEED)
    assert setting_config("2-dusk") == dataclasses.replace(setting_config(2), render=dusk.task.render)
    assert settings.parse_settings("2-dusk", families=True) == ["2-dusk"] and settings.SETTINGS == {1: 2, 2: 5, 3: 10}
    assert not any("2-dusk" in name for name in settings.all_seed_sets())  # setting 2's scenes, listed once

    from uavsearch.fly.missions import Mission
    from uavsearch.search.agents import checkpoint_path

    m = Mission(name="dusk", scene={"seed": SEED, "setting": "2-dusk"})
    assert m.family is None and m.scene.k == 5 and m.checkpoint_path == checkpoint_path(2, "learned")
    assert m.search_config().render == dusk.task.render and m.scene_spec() == settings.generate_setting_scene(2, SEED)


def test_the_shipped_file_is_back_after_a_temporary_one(dusk_file):
    assert "2-dusk" in settings.SCENE_FAMILIES
    with settings.settings_file(settings.SCENES_DIR / "settings.yaml"):
        assert "2-dusk" not in settings.SCENE_FAMILIES
        with pytest.raises(SceneError, match="unknown setting '2-dusk'"):
            settings.setting_params("2-dusk")
    assert "2-dusk" in settings.SCENE_FAMILIES


@pytest.mark.parametrize("family, match", [
    ({"variant_of": "nope"}, "variant_of 'nope' is not another family"),
    ({"variant_of": 2, "task": {"render": {"glow": 1.0}}}, "render: .*glow"),
    ({"variant_of": 2, "task": {"base": "night"}}, "unknown base 'night'"),
    ({"k": 5, "slot": 9, "task": {"base": "paper"}}, "policies"),  # the paper's task names no policies of its own
])
def test_a_bad_declaration_is_a_one_line_error_and_changes_nothing(tmp_path, family, match):
    path = _settings_with(tmp_path, bad=family)
    before = dict(settings.SCENE_FAMILIES)
    with pytest.raises(SceneError, match=match) as e:
        with settings.settings_file(path):
            pass
    assert "\n" not in str(e.value) and settings.SCENE_FAMILIES == before


def test_a_named_wide_variant_stays_a_team_mission(tmp_path):
    path = _settings_with(tmp_path, **{"wide-dusk": {"variant_of": "wide", "task": {"render": DUSK}}})
    from uavsearch.fly.missions import Mission

    with settings.settings_file(path):
        assert settings.setting_params("wide-dusk").task.mission == "team"
        m = Mission(name="w", scene={"seed": 1, "setting": "wide-dusk"}, fusion="bayes", policy="rule", team={})
        assert m.family == "wide-dusk" and m.search_config().render == settings.setting_params("wide-dusk").task.render
        assert setting_config("wide-dusk") == dataclasses.replace(setting_config("wide"), render=setting_config("wide-dusk").render)


def _env_images(setting) -> list[np.ndarray]:
    from uavsearch.search.envs.search_env import ActiveSearchEnv, default_fusion

    assert default_fusion(setting) == "learned"  # setting 2's learned confidence fusion, from its checkpoint
    env = ActiveSearchEnv(setting=setting, obs="image", views="live", progress=False)
    assert env.config == setting_config(setting)
    try:
        obs, info = env.reset(seed=0, options={"scene_seed": SEED})
        images = [obs["image"]]
        obs, *_ = env.step(0)
        images.append(obs["image"])
    finally:
        env.close()
    return images


def test_teleport_draws_the_variant_darker_on_its_base_task(dusk_file):
    dusk, two = _env_images("2-dusk"), _env_images(2)
    for d, t in zip(dusk, two):
        assert d.shape == t.shape and _brightness(d) < 0.75 * _brightness(t)


def test_flight_draws_what_teleport_draws(dusk_file, tmp_path):
    """The flown camera renders with the family's render options: the image the vehicle wrote is the teleport
    renderer's at the vehicle's true pose, byte for byte, and darker than setting 2's there."""
    mission = {"name": "dusk", "scene": {"seed": SEED, "setting": "2-dusk"}, "search": {"budget_T": 1},
               "policy_seed": 0, "flight": {"speed": "max", "end_action": "land"}}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mission))
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(tmp_path / "m.yaml"), "--out",
                        str(run), "--gcs-port", "0"], capture_output=True, text=True, timeout=240,
                       env=clean_env(**{settings.SETTINGS_ENV: str(dusk_file)}))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "(2-dusk)" in (run / "sitl.log").read_text()  # the vehicle was told the family
    shot = json.loads((run / "captures.jsonl").read_text().splitlines()[0])
    flown = cv2.imread(shot["path"])[..., ::-1]
    pose = camera_pose_from_vehicle(np.asarray(shot["true_position_enu_m"]), *shot["true_rpy_rad"], gimbal_stabilised=True)
    spec = settings.generate_setting_scene("2-dusk", SEED)
    drawn = {}
    for name in ("2-dusk", 2):
        config = setting_config(name)
        with SceneRenderer(spec, config.intrinsics, config.render) as renderer:
            drawn[name] = np.asarray(renderer.render(pose).rgb)
    assert np.array_equal(flown, drawn["2-dusk"])
    assert _brightness(flown) < 0.75 * _brightness(drawn[2])

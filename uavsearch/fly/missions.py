"""Mission files (missions/*.yaml): everything one flown search needs, validated with pydantic.

A mission names the scene (a seed with a setting or K, or a saved spec), the search task (altitude, step,
budget T, action set), the method (fusion + policy + checkpoints), how to fly (speed factor, home,
arrival thresholds, end action) and the seeds. Unknown keys are errors (a typo must not silently fall
back to a default). A bad file gives ONE line naming the field and the problem:

    mission missions/x.yaml: search.budget_T: Input should be greater than or equal to 1 (got 0)
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from ..errors import MissionError, UavsearchError, format_validation_error
from ..geometry import CameraIntrinsics, GeodeticOrigin
from ..paths import MISSIONS_DIR, REPO_ROOT, display_path
from ..search.config import ACTIONS, SearchConfig
from ..world.scene import generate_scene, load_scene
from ..world.settings import SETTINGS, setting_key, setting_params
from .bounded_read import check_shape, parse_yaml, read_bounded_text
from .vehicle import FlightSettings

if TYPE_CHECKING:
    from ..search.agents import LoadedAgent
    from ..search.fusion import Fusion
    from ..search.team import TeamPlanner

DEFAULT_MISSION = MISSIONS_DIR / "default.yaml"
FLY_MISSION = MISSIONS_DIR / "wide.yaml"  # what `uavsearch fly` flies when no mission is named
# A scene family's mission flown by the learned wide-area policy (search/map_policy.py) instead of a team planner,
# with the fusion its checkpoint was trained and saved with.
WIDE_POLICY = "map"
FROM_CHECKPOINT = "checkpoint"
# The agent registry (search/agents.py) imports torch (1-4 s). Validating with the context {REGISTRY: False}
# leaves the fusion / policy names unchecked, so `uavsearch fly` can start its vehicle first and check
# them (Mission.check_registry) while the vehicle starts.
REGISTRY = "check_registry"


def _registry():
    from ..search import agents  # lazy: torch, see REGISTRY

    return agents


def _checks_registry(info: ValidationInfo) -> bool:
    return not (info.context and info.context.get(REGISTRY) is False)


# What a checkpoint that records no search config was trained on (the shipped models: every view rendered
# with SearchConfig's defaults, 70 m and 10 m steps). A checkpoint trained since records its own.
TRAINED_FOR = {"altitude_m": 70.0, "step_m": 10.0}


def trained_for(checkpoint: Path) -> dict:
    """{altitude_m, step_m} the policy checkpoint was trained on: its recorded search config, or TRAINED_FOR
    for one older than the record (or one that cannot be read: loading it later says why)."""
    from ..search.config import config_from_dict
    from ..search.policy import load_search_model  # lazy: torch, see REGISTRY

    try:
        *_, extra = load_search_model(checkpoint)
    except Exception:  # noqa: BLE001 - the agent's own load reports a bad checkpoint in one line
        return dict(TRAINED_FOR)
    rec = extra.get("search_config") if isinstance(extra, dict) else None
    if rec is None:
        return dict(TRAINED_FOR)
    c = config_from_dict(rec)
    return {"altitude_m": c.altitude_m, "step_m": c.step_m}


def untrained_settings(search, trained: dict | None = None) -> list[str]:
    """The search settings that differ from what the models were trained on, as 'altitude_m 40 (trained 70)'."""
    trained = trained or TRAINED_FOR
    return [f"{k} {getattr(search, k):g} (trained {v:g})" for k, v in trained.items()
            if not math.isclose(float(getattr(search, k)), v, rel_tol=0, abs_tol=1e-6)]


class _Strict(BaseModel):
    # NaN and infinities are refused in every float field: a NaN home altitude or speed passes every bound
    # check (each comparison is false) and only fails inside the vehicle.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SceneRef(_Strict):
    """Which world: a generated scene (seed + setting or occupied_cells) or a saved spec file."""

    seed: int | None = Field(3, ge=0)
    setting: int | str | None = 2  # the paper's 1 | 2 | 3, or a scene family ("wide": a team's wide-area search)
    occupied_cells: int | None = Field(None, ge=0, le=100)
    spec: str | None = None  # path to a scene JSON (uavsearch scene save), relative to the mission file

    @field_validator("setting")
    @classmethod
    def _setting(cls, v):
        if v is None:
            return v
        if isinstance(v, int) and not isinstance(v, bool) and v not in SETTINGS:
            raise ValueError(f"setting {v}: the paper's settings are {', '.join(map(str, SETTINGS))}")
        try:
            return setting_key(v)  # 2 for "2": the declared name
        except UavsearchError as e:
            raise ValueError(str(e)) from None

    @property
    def family(self) -> str | None:
        """The scene family a team's lattice mission searches ("wide"); None where the family's task is the
        paper's kind (one vehicle's moves: settings 1-3 and their variants) or no setting is named."""
        if self.setting is None or setting_params(self.setting).task.mission != "team":
            return None
        return str(self.setting)

    @property
    def k(self) -> int:
        if self.occupied_cells is not None:
            return int(self.occupied_cells)
        return setting_params(self.setting if self.setting is not None else 2).k


class SearchSection(_Strict):
    altitude_m: float = Field(70.0, gt=0, le=120)
    step_m: float = Field(10.0, gt=0)
    budget_T: int = Field(5, ge=1, le=25)
    actions: tuple[str, ...] = ("MoveAhead", "MoveRight", "MoveLeft", "MoveBack")
    # the lattice's altitude layers, the first = altitude_m ([] = one layer); Climb / Descend move between them
    altitudes_m: tuple[float, ...] = ()
    # Fly although the altitude or step differs from what the shipped models were trained on (their
    # perception has never seen such views: the result says little about the method).
    allow_untrained: bool = False

    @field_validator("altitudes_m")
    @classmethod
    def _altitudes(cls, v):
        if any(not 0 < a <= 120 for a in v):
            raise ValueError("every altitude must lie in (0, 120] m")
        return tuple(v)

    @field_validator("actions")
    @classmethod
    def _known(cls, v):
        bad = [a for a in v if a not in ACTIONS]
        if bad:
            raise ValueError(f"unknown action(s) {bad}; valid: {sorted(ACTIONS)}")
        if not v:
            raise ValueError("at least one action")
        return tuple(v)


# The camera the shipped models were trained with: every training and evaluation view set is rendered with
# SearchConfig's default intrinsics (its manifest records them, search/data/dataset.py) and no training command
# takes an option to change them.
TRAINED_CAMERA = CameraIntrinsics()


class CameraSection(_Strict):
    """The simulated nadir pinhole camera: what the vehicle renders and what the search projects the grid with."""

    hfov_deg: float = Field(TRAINED_CAMERA.hfov_deg, gt=1, lt=170)
    width_px: int = Field(TRAINED_CAMERA.width_px, ge=16, le=4096)
    height_px: int = Field(TRAINED_CAMERA.height_px, ge=16, le=4096)

    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(width_px=self.width_px, height_px=self.height_px, hfov_deg=self.hfov_deg)

    def untrained(self) -> list[str]:
        """What differs from TRAINED_CAMERA, as 'hfov_deg 90 (trained 60)'."""
        return [f"{k} {getattr(self, k):g} (trained {getattr(TRAINED_CAMERA, k):g})" for k in type(self).model_fields
                if not math.isclose(float(getattr(self, k)), float(getattr(TRAINED_CAMERA, k)), abs_tol=1e-6)]


class Home(_Strict):
    """WGS84 position of the search area's centre (the scene origin)."""

    lat_deg: float = Field(47.397742, ge=-90, le=90)
    lon_deg: float = Field(8.545594, ge=-180, le=180)
    alt_m: float = 488.0


class FlightSection(_Strict):
    speed: float | Literal["max"] = "max"  # 1 = real time, N = N x real time, max
    arrive_radius_m: float = Field(0.5, gt=0)
    settle_speed_m_s: float = Field(0.3, gt=0)
    settle_time_s: float = Field(0.5, ge=0)
    step_timeout_s: float = Field(60.0, gt=0)
    connect_timeout_s: float = Field(30.0, gt=0)  # wall clock: the vehicle's heartbeat and health
    end_action: Literal["land", "rtl", "none"] = "land"
    vehicle_seed: int = Field(0, ge=0)  # sensor / estimator noise of the simulated vehicle
    # The controller drives the simulated vehicle's clock (sitl --lockstep), so the seeds fix the flight.
    # With --connect it is used when the vehicle supports it.
    lockstep: bool = True

    @field_validator("speed")
    @classmethod
    def _speed(cls, v):
        if v != "max" and not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
            raise ValueError("must be a positive number or 'max'")
        return v


class TeamSection(_Strict):
    """How many vehicles fly the mission (every mission: 1 without this section), and on a scene family with a
    team's task for how long. The paper's settings search with one vehicle and count their budget in views."""

    vehicles: int = Field(1, ge=1, le=16)  # `uavsearch fly --vehicles N` overrides it
    # simulated seconds of flight: on the vehicles' own clock when flown, the lattice's flight times in teleport
    mission_time_s: float = Field(240.0, gt=0, le=3600)
    max_views: int | None = Field(None, ge=1, le=72)  # a view budget too (Table III's T = 8); None: views until the time


class TeamMethod(NamedTuple):
    """How a scene family's mission searches: the fusion, the planner run_team asks, and what they are in words."""

    fusion: Fusion
    planner: TeamPlanner
    description: str


# A mission's name names its run folder (runs/fly__<name>__<time>): a name, never a path out of the runs root,
# and short enough that the folder's name fits a file system's 255 bytes in any script.
NAME_PATTERN = r"[^/\\\x00-\x1f\x7f\ud800-\udfff]{1,50}"


class Mission(_Strict):
    name: str = "mission"
    description: str = ""
    scene: SceneRef = SceneRef()
    search: SearchSection = SearchSection()
    fusion: str = "learned"  # a fusion method of the agent registry (search/agents.py)
    policy: str = "learned"  # a policy of the agent registry
    checkpoint: str | None = None  # default: models/search_s<setting>_<fusion>.pt (_<policy>.pt: agents.checkpoint_path)
    perception: str | None = None  # default: models/perception.pt
    policy_seed: int = Field(0, ge=0)
    greedy_policy: bool = False  # the learned policy takes its most likely action instead of sampling
    home: Home = Home()
    camera: CameraSection = CameraSection()
    flight: FlightSection = FlightSection()
    plan: str | None = None  # a QGroundControl .plan (relative to this file): `uavsearch mission upload` flies it
    team: TeamSection | None = None  # the vehicles (1 without it); a team's family: also its mission time
    source: str | None = Field(None, exclude=True)  # the file it came from (set by load_mission)

    @field_validator("name")
    @classmethod
    def _a_name(cls, v):
        if not re.fullmatch(NAME_PATTERN, v) or ".." in v or v.strip() in ("", "."):
            raise ValueError(f"a name, not a path: 1-50 characters without '/', '\\', '..' or control characters "
                             f"(got {v!r})")
        return v

    @field_validator("fusion", "policy")
    @classmethod
    def _registered(cls, v, info: ValidationInfo):
        if not _checks_registry(info):
            return v
        scene = info.data.get("scene")
        if scene is not None and scene.family is not None:  # a team's fusion spec and planner (search/team.py)
            from ..search.config import setting_config
            from ..search.agents import make_fusion, make_planner

            if v == {"fusion": FROM_CHECKPOINT, "policy": WIDE_POLICY}[info.field_name]:
                return v  # the learned wide-area policy and the fusion saved with it (checked in _consistent)
            try:
                if info.field_name == "fusion":
                    make_fusion(v)
                else:
                    make_planner(v, setting_config(scene.family))
            except UavsearchError as e:
                raise ValueError(str(e).replace("--wide-fusion", "a wide-area mission's fusion")) from None
            return v
        agents = _registry()
        known = {"fusion": agents.FUSIONS, "policy": agents.POLICIES}[info.field_name]
        if v not in known:
            kind = "fusion method" if info.field_name == "fusion" else "policy"
            raise ValueError(f"unknown {kind} {v!r}; valid: {', '.join(map(repr, known))}")
        return v

    @model_validator(mode="after")
    def _consistent(self, info: ValidationInfo):
        s = self.scene
        if s.spec is None and s.seed is None:
            raise ValueError("scene: give a seed or a spec file")
        if s.occupied_cells is not None and s.setting is not None and "setting" in s.model_fields_set:
            raise ValueError("scene: give setting OR occupied_cells, not both")
        if s.family is not None:
            if s.spec is not None:
                raise ValueError("scene: a scene family's mission names a seed, not a spec file")
            learned = self.policy == WIDE_POLICY
            if (self.fusion == FROM_CHECKPOINT) != learned:
                raise ValueError(f"fusion: the learned wide-area policy (policy: {WIDE_POLICY}) flies with the fusion "
                                 f"saved in its checkpoint (fusion: {FROM_CHECKPOINT}), and only it")
            if self.checkpoint is not None and not learned:
                raise ValueError(f"checkpoint: only the learned wide-area policy (policy: {WIDE_POLICY}) has a "
                                 "checkpoint; a team planner has none")
            if learned and self.vehicles != 1:
                raise ValueError(f"team.vehicles: the learned wide-area policy flies one vehicle, not {self.vehicles}")
            return self
        if self.vehicles != 1:
            raise ValueError(f"team.vehicles: the {self.policy} policy flies one vehicle, not {self.vehicles}; a team "
                             "flies a scene family's mission with a team planner (missions/wide_team.yaml)")
        for name in ("mission_time_s", "max_views"):
            if self.team is not None and getattr(self.team, name) != TeamSection.model_fields[name].default:
                raise ValueError(f"team.{name}: a paper setting's mission counts its budget in views (search.budget_T)")
        if _checks_registry(info) and _registry().trained_fusion(self.fusion) and \
                not _registry().loads_checkpoint(self.policy) and self.checkpoint is None and s.setting is None:
            raise ValueError(f"{self.fusion} fusion needs a checkpoint (no setting to pick a shipped one)")
        if self.search.allow_untrained:
            return self
        # A named checkpoint says what it was trained on, which needs torch: checked with the registry. The
        # shipped models were all trained on TRAINED_FOR.
        if self.checkpoint is not None and not _checks_registry(info):
            return self
        trained = trained_for(self.checkpoint_path) if _checks_registry(info) and \
            _registry().loads_checkpoint(self.policy) else TRAINED_FOR
        off = untrained_settings(self.search, trained)
        if off:
            raise ValueError(f"search: {', '.join(off)}; the models were trained at {trained['altitude_m']:g} m "
                             f"altitude with {trained['step_m']:g} m steps (set search.allow_untrained: true "
                             "to fly it anyway)")
        return self

    @model_validator(mode="after")
    def _camera_trained_for(self):
        off = self.camera.untrained()
        if off and not self.search.allow_untrained:
            raise ValueError(f"camera: {', '.join(off)}; the models were trained with a {TRAINED_CAMERA.width_px}x"
                             f"{TRAINED_CAMERA.height_px} px, {TRAINED_CAMERA.hfov_deg:g} deg camera (set "
                             "search.allow_untrained: true to fly it anyway)")
        return self

    # -- derived ---------------------------------------------------------------------------------
    @property
    def speed_factor(self) -> float:
        return math.inf if self.flight.speed == "max" else float(self.flight.speed)

    def _resolve(self, p: str) -> Path:
        path = Path(p).expanduser()
        if path.is_absolute():
            return path
        base = Path(self.source).parent if self.source else Path.cwd()
        for root in (base, Path.cwd(), REPO_ROOT):  # beside the mission file, then here, then the repository
            if (root / path).exists():
                return root / path
        return base / path

    @property
    def family(self) -> str | None:
        return self.scene.family

    @property
    def vehicles(self) -> int:
        return 1 if self.team is None else int(self.team.vehicles)

    @property
    def setting_for_models(self) -> int | str:
        if self.scene.setting is not None:
            return self.scene.setting  # its family names its checkpoints (a variant: its base's)
        k = self.scene.k
        return min(SETTINGS, key=lambda s: abs(SETTINGS[s] - k))  # nearest density's model

    @property
    def checkpoint_path(self) -> Path:
        if self.checkpoint:
            return self._resolve(self.checkpoint)
        if self.family is not None:  # the shipped learned wide-area policy of the mission's budget
            from ..search.checkpoints import shipped

            views = self.team.max_views if self.team is not None else None
            return shipped("map", budget=str(views) if views is not None else f"{self.search_config().budget_s:g}")
        agents = _registry()
        trained = self.policy in agents.POLICIES and agents.loads_checkpoint(self.policy)
        return agents.checkpoint_path(self.setting_for_models, self.fusion, policy=self.policy if trained else "learned")

    @property
    def perception_path(self) -> Path:
        if self.perception:
            if self.perception.startswith("detector:"):  # a detector of your own (search/detector.py), by name
                return Path(self.perception)
            return self._resolve(self.perception)
        from ..search.checkpoints import shipped

        return shipped("perception", self.family)  # the paper's models/perception.pt unless the family ships one

    @property
    def plan_path(self) -> Path | None:
        return self._resolve(self.plan) if self.plan else None

    @property
    def spec_path(self) -> Path | None:
        return self._resolve(self.scene.spec) if self.scene.spec else None

    def search_config(self) -> SearchConfig:
        s = self.search
        if self.family is not None:  # the family's lattice and camera; views until the mission time is flown
            from ..search.config import setting_config

            cfg = setting_config(self.family)
            team = self.team or TeamSection()
            return dataclasses.replace(cfg, budget_T=team.max_views or cfg.lattice.num_positions,
                                       budget_s=float(team.mission_time_s), intrinsics=self.camera.intrinsics())
        drawn = {} if self.scene.setting is None else {"render": setting_params(self.scene.setting).task.render}
        try:
            return SearchConfig(altitude_m=s.altitude_m, step_m=s.step_m, budget_T=s.budget_T, actions=tuple(s.actions),
                                altitudes_m=tuple(float(a) for a in s.altitudes_m), intrinsics=self.camera.intrinsics(),
                                **drawn)
        except UavsearchError as e:
            raise MissionError(f"mission {self.source}: search: {e}") from None

    def flight_settings(self) -> FlightSettings:
        f = self.flight
        return FlightSettings(arrive_radius_m=f.arrive_radius_m, settle_speed_m_s=f.settle_speed_m_s,
                              settle_time_s=f.settle_time_s, step_timeout_s=f.step_timeout_s, end_action=f.end_action,
                              lockstep=f.lockstep, connect_timeout_s=f.connect_timeout_s)

    def origin(self) -> GeodeticOrigin:
        return GeodeticOrigin(self.home.lat_deg, self.home.lon_deg, self.home.alt_m)

    def scene_spec(self):
        """The ground-truth scene (generated from the seed, or loaded from the spec file)."""
        if self.spec_path is not None:
            return load_scene(self.spec_path)
        if self.family is not None or (self.scene.setting is not None and self.scene.occupied_cells is None):
            from ..world.settings import generate_setting_scene  # the family's generator (1-3: generate_scene's)

            return generate_setting_scene(self.scene.setting, int(self.scene.seed))
        return generate_scene(int(self.scene.seed), self.scene.k)

    def agent(self, config: SearchConfig | None = None) -> LoadedAgent:
        """Perception + fusion + policy of the mission, from its checkpoints (agents.build_agent); the
        confidence net of learned fusion comes along for logging scores whatever the fusion."""
        agents = _registry()
        learned_ck = self.checkpoint_path if agents.trained_fusion(self.fusion) and self.checkpoint else \
            agents.checkpoint_path(self.setting_for_models, "learned")
        return agents.build_agent(self.fusion, self.policy, config or self.search_config(), checkpoint=self.checkpoint_path,
                           confidence_checkpoint=learned_ck, greedy=self.greedy_policy,
                           perception=self.perception_path, scores_net=True, error=MissionError,
                           where=f"mission {self.source}: ")

    def team_method(self, config: SearchConfig | None = None) -> TeamMethod:
        """A scene family's mission's fusion and planner (search/team.py's run_team flies them): a team planner
        with its fusion spec, or the learned wide-area policy with the fusion saved in its checkpoint (one
        vehicle; the checkpoint must have been trained for the mission's budget)."""
        from ..search.agents import make_fusion, make_planner
        from ..search.fusion import fusion_name
        from ..search.team import EachVehicle

        config = config or self.search_config()
        if self.policy != WIDE_POLICY:
            return TeamMethod(make_fusion(self.fusion), make_planner(self.policy, config),
                              f"{self.fusion} fusion + {self.policy} team planner")
        from ..search.agents import budget_text, load_wide_agent

        views = self.team.max_views if self.team is not None else None
        budget = dataclasses.replace(config, budget_s=None) if views else \
            dataclasses.replace(config, budget_T=config.lattice.num_positions)
        where = f"mission {self.source}: "
        agent = load_wide_agent(self.checkpoint_path, budget, error=MissionError, where=where)
        if agent is None:
            raise MissionError(f"{where}checkpoint: no file {display_path(self.checkpoint_path)}")
        return TeamMethod(agent.fusion, EachVehicle(agent.policy),
                          f"learned wide-area policy {display_path(self.checkpoint_path)} ({budget_text(budget)}, "
                          f"{fusion_name(agent.fusion)} fusion from its checkpoint)")

    def check_registry(self) -> "Mission":
        """The mission validated with its fusion / policy names checked against the agent registry."""
        return mission_from_dict(self.model_dump(mode="json"), self.source)

    def with_overrides(self, check_registry: bool = True, **changes) -> "Mission":
        """A copy with dotted-path overrides ({'scene.seed': 4, 'flight.speed': 'max'}), re-validated
        (`check_registry`: see REGISTRY)."""
        data = self.model_dump(mode="json")
        for key, value in changes.items():
            if value is None:
                continue
            d = data
            *parents, leaf = key.split(".")
            for p in parents:
                d = d[p]
            d[leaf] = value
            if key == "scene.seed":
                data["scene"]["spec"] = None
        return mission_from_dict(data, self.source, check_registry)

    def with_team(self, check_registry: bool = False, **team) -> "Mission":
        """A copy with the team section's fields changed ({'vehicles': 3}), re-validated."""
        data = self.model_dump(mode="json")
        data["team"] = {**(data.get("team") or {}), **team}
        return mission_from_dict(data, self.source, check_registry)


def mission_from_dict(data, source: str | None = None, check_registry: bool = True) -> Mission:
    src = source or "<dict>"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise MissionError(f"mission {src}: the file must be a YAML mapping of fields, got {type(data).__name__}")
    check_shape(data, src)
    try:
        m = Mission.model_validate(data, context={REGISTRY: bool(check_registry)})
    except ValidationError as e:
        raise MissionError(format_validation_error(e, src)) from None
    return m.model_copy(update={"source": source})


def mission_path(name) -> Path:
    """A mission file, or a bare name of one in missions/ (`wide`: missions/wide.yaml)."""
    path = Path(name)
    if path.suffix or len(path.parts) > 1 or path.exists():
        return path
    if not (MISSIONS_DIR / f"{path}.yaml").is_file():
        known = ", ".join(sorted(p.stem for p in MISSIONS_DIR.glob("*.yaml")))
        raise MissionError(f"mission {name}: no such file, nor {display_path(MISSIONS_DIR)}/{name}.yaml (named "
                           f"missions: {known})")
    return MISSIONS_DIR / f"{path}.yaml"


def load_mission(path=None, check_registry: bool = True) -> Mission:
    """Read and validate a mission file or named mission (default: missions/default.yaml; `check_registry`: see
    REGISTRY)."""
    path = mission_path(path) if path else DEFAULT_MISSION
    data = parse_yaml(read_bounded_text(path), str(path))
    return mission_from_dict(data, str(path), check_registry)


__all__ = ["DEFAULT_MISSION", "FLY_MISSION", "FROM_CHECKPOINT", "WIDE_POLICY", "Mission", "TeamMethod", "load_mission",
           "mission_from_dict", "mission_path"]

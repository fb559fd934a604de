"""The scene families and their scene splits, read from scenes/settings.yaml.

A family ("setting") is one of the paper's ids 1-3 (K = 2, 5, 10 on the 50 m grid) or a named one ("wide",
"wide-uniform", or a declared variant such as a darker "2-dusk"): K plus the scene parameters (grid, city size,
placement of people), where its seeds lie, and the search task it declares (SearchTask: lattice and move set,
budgets, default fusion, shipped models, render options, mission kind). Callers ask the family; nothing reads
a task from a family's name. Seeds are ranges, so a split is reproducible from the file alone and two parts never
share a scene. UAVSEARCH_SCENE_SETTINGS (or `settings_file`) points at another file, e.g. a test's variant.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..errors import SceneError
from ..geometry import Grid
from ..paths import SCENES_DIR
from .render import RenderOptions
from .scene import Placement, SceneParams, SceneSpec, generate_scene

SETTINGS_ENV = "UAVSEARCH_SCENE_SETTINGS"  # another settings file, inherited by the processes a run starts
SETTINGS_FILE = Path(os.environ.get(SETTINGS_ENV) or SCENES_DIR / "settings.yaml")
PARTS = ("train", "val", "test")

Setting = int | str


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class TaskLattice(_Frozen):
    """Where the camera may look from: altitude layers (the first is the start's), spacing, positions per side
    (None: as many as stay over the area) and how the next viewpoint is chosen ("steps": one of `actions`'
    step vectors; "any": any viewpoint)."""

    altitudes_m: tuple[float, ...] = Field(min_length=1)
    step_m: float = Field(gt=0)
    points: int | None = Field(None, ge=1)
    moves: Literal["steps", "any"] = "steps"
    actions: tuple[str, ...] = ()


class TaskBudget(_Frozen):
    """How long an episode lasts: views (the start view counts), and simulated seconds of flight (None: views only)."""

    views: int = Field(ge=1)
    seconds: float | None = Field(None, ge=0)


class SearchTask(_Frozen):
    """The search a family's scenes are searched with. `mission`: "moves" (one vehicle stepping by the move set,
    the paper's; its mission file may change altitude, step and T) or "team" (one vehicle or a team on the
    family's lattice, with a time budget). `perception` and `policies` name the shipped checkpoints in models/
    (`policies` is their stem). `render`: how images are made (world.render.RenderOptions' fields), in teleport
    and on the flown camera alike."""

    mission: Literal["moves", "team"]
    lattice: TaskLattice
    budget: TaskBudget
    fusion: str
    perception: str
    policies: str
    render: RenderOptions = Field(default_factory=RenderOptions)

    @field_validator("render", mode="before")
    @classmethod
    def _render(cls, v):
        if isinstance(v, dict):
            try:
                return RenderOptions(**v)
            except TypeError as e:
                raise ValueError(f"render: {e}") from None
        return v


class SceneFamily(_Frozen):
    """What a setting's scenes are: K, the grid, the city and how people are placed, where its seeds lie (`slot`
    in the seed layout, and the split used when none is asked for), and the task it declares. `variant_of`: the
    family it was declared from (its fields, overridden where the variant says)."""

    name: str
    k: int = Field(ge=0)
    grid_n: int = Field(10, ge=1)
    cell_m: float = Field(5.0, gt=0)
    city_half_m: float = 90.0
    placement: Placement = Field(default_factory=Placement)
    slot: int = Field(ge=1)
    split: str = "paper"
    task: SearchTask
    variant_of: str | None = None

    @property
    def grid(self) -> Grid:
        return Grid(self.grid_n, self.cell_m)

    @property
    def generic_scenes(self) -> bool:
        """Whether its scenes are generate_scene(seed, K) (the default scene parameters), so a seed and K alone
        rebuild one (a vehicle given only those renders the same scene)."""
        return (self.grid == Grid() and SceneParams(city_half_m=self.city_half_m) == SceneParams()
                and self.placement == Placement())

    def scene(self, seed: int) -> SceneSpec:
        return generate_scene(seed, self.k, SceneParams(city_half_m=self.city_half_m), self.grid, self.placement)


@functools.lru_cache(maxsize=1)
def _config() -> dict:
    try:
        cfg = yaml.safe_load(SETTINGS_FILE.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SceneError(f"cannot read scene settings {SETTINGS_FILE}: {e}") from None
    if not isinstance(cfg, dict) or not isinstance(cfg.get("families"), dict):
        raise SceneError(f"scene settings {SETTINGS_FILE} declare no families")
    return cfg


def _merged(base: dict, over: dict) -> dict:
    """`base` with `over`'s keys replacing its own, mappings merged key by key."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _declared(cfg: dict, name, seen: tuple = ()) -> dict:
    """A family's fields as declared, its `variant_of` base's fields under them."""
    fams = cfg["families"]
    d = fams[name]
    if not isinstance(d, dict):
        raise SceneError(f"bad scene family {name!r} in {SETTINGS_FILE}: not a mapping")
    if isinstance(d.get("task"), str):
        d = {**d, "task": {"base": d["task"]}}  # a task's name: the same as a mapping over it
    base = d.get("variant_of")
    if base is None:
        return d
    key = _lookup(fams, base)
    if key is None or key in seen or key == name:
        raise SceneError(f"bad scene family {name!r} in {SETTINGS_FILE}: variant_of {base!r} is not another family")
    return {**_merged(_declared(cfg, key, (*seen, name)), d), "variant_of": str(key)}


def _task(cfg: dict, d) -> dict:
    """A family's task: a name in `tasks`, or a mapping of fields over its `base` task's."""
    tasks = cfg.get("tasks") or {}
    d = dict(d or {})
    base = d.pop("base", None)
    if base is not None and base not in tasks:
        raise ValueError(f"task: unknown base {base!r}; valid: {', '.join(map(str, tasks))}")
    return _merged(tasks[base], d) if base is not None else d


def _lookup(keys, name):
    """The declared key a user's name means ("2" -> 2, " wide" -> "wide"); None if none."""
    if isinstance(name, bool):
        return None
    if name in keys:
        return name
    text = str(name).strip()
    return next((k for k in keys if str(k) == text), None)


def _families() -> dict[Setting, SceneFamily]:
    cfg = _config()
    out: dict[Setting, SceneFamily] = {}
    for key in cfg["families"]:
        try:
            d = _declared(cfg, key)
            d = {**d, "task": _task(cfg, d.get("task"))}
            out[key] = SceneFamily(name=str(key), **d)
        except ValidationError as e:
            err = e.errors()[0]
            where = ".".join(map(str, err["loc"]))
            raise SceneError(f"bad scene family {key!r} in {SETTINGS_FILE}: {where}: {err['msg']}".splitlines()[0]) from None
        except (TypeError, ValueError) as e:
            raise SceneError(f"bad scene family {key!r} in {SETTINGS_FILE}: {e}".splitlines()[0]) from None
    return out


def _settings() -> dict[int, int]:
    return {k: f.k for k, f in SCENE_FAMILIES.items() if isinstance(k, int)}


SCENE_FAMILIES: dict[Setting, SceneFamily] = _families()  # every setting: 1, 2, 3, "wide", "wide-uniform"
SETTINGS: dict[int, int] = _settings()  # the paper's setting ids -> occupied cells K: {1: 2, 2: 5, 3: 10}


def _load(path: Path) -> None:
    """Read the families from `path`; SETTINGS and SCENE_FAMILIES change in place (importers hold them)."""
    global SETTINGS_FILE
    SETTINGS_FILE = Path(path)
    _config.cache_clear()
    fams = _families()
    SCENE_FAMILIES.clear()
    SCENE_FAMILIES.update(fams)
    SETTINGS.clear()
    SETTINGS.update(_settings())


@contextlib.contextmanager
def settings_file(path):
    """Use the scene settings in `path` (e.g. a test's extra family) in this process; the vehicle processes it
    starts are told through `child_env()`. The previous file comes back on exit; the environment is never touched."""
    old_file = SETTINGS_FILE
    try:
        _load(Path(path))
        yield
    finally:
        _load(old_file)


def child_env() -> dict[str, str]:
    """What a process this one starts needs in its environment to read the same scene settings: the file, where it
    is not the repository's own."""
    if SETTINGS_FILE == SCENES_DIR / "settings.yaml":
        return {}
    return {SETTINGS_ENV: str(SETTINGS_FILE)}


def _valid() -> str:
    return ", ".join(map(str, SCENE_FAMILIES))


def setting_key(setting: Setting) -> Setting:
    """The declared key a user's setting names: 2 for 2 or "2", "wide" for " wide"; else a one-line error."""
    key = _lookup(SCENE_FAMILIES, setting)
    if key is None:
        raise SceneError(f"unknown setting {setting!r}; valid: {_valid()}")
    return key


def setting_params(setting: Setting) -> SceneFamily:
    """A setting's family (scenes, seeds, task): an id 1-3 (also as text) or a family name; else a one-line error."""
    return SCENE_FAMILIES[setting_key(setting)]


def generate_setting_scene(setting: Setting, seed: int) -> SceneSpec:
    """The scene of `seed` in a setting (for 1-3 exactly generate_scene(seed, SETTINGS[setting]))."""
    return setting_params(setting).scene(seed)


def splits() -> list[str]:
    return list(_config()["splits"])


def scene_seeds(setting: Setting, split: str | None = None, part: str = "train") -> list[int]:
    """The scene seeds of one part of one split of a setting (default split: the setting's own, "paper"
    for 1-3); generate each with generate_setting_scene(setting, seed)."""
    cfg = _config()
    fam = setting_params(setting)
    split = fam.split if split is None else split
    if split not in cfg["splits"]:
        raise SceneError(f"unknown split {split!r}; valid: {', '.join(cfg['splits'])}")
    if part not in PARTS:
        raise SceneError(f"unknown part {part!r}; valid: {', '.join(PARTS)}")
    start = cfg["base"][split] + (fam.slot - 1) * cfg["stride"][split] + cfg["offset"][part][split]
    return list(range(start, start + int(cfg["splits"][split][part])))


def density_scenes() -> list[tuple[int, int]]:
    """Table I's test scenes: (seed, K) with K in 1..12, `scenes_per_pair` per pair of densities
    (half at each density of the pair)."""
    d = _config()["density"]
    out = []
    for i, pair in enumerate(d["pairs"]):
        for j in range(int(d["scenes_per_pair"])):
            out.append((int(d["base"]) + 1000 * i + j, int(pair[j % len(pair)])))
    return out


def parse_settings(text: str, flag: str = "--setting", families: bool = False) -> list[Setting]:
    """A command line's settings: "all" (the paper's 1, 2, 3), one, or comma-separated ones (e.g. "1,3");
    family names ("wide") only where the caller takes them (`families`); else a one-line error."""
    if str(text).strip() == "all":
        return sorted(SETTINGS)
    valid = _valid() if families else ", ".join(map(str, sorted(SETTINGS)))
    out: list[Setting] = []
    for x in (x.strip() for x in str(text).split(",") if x.strip()):
        try:
            out.append(setting_key(x))
        except SceneError:
            raise SceneError(f"unknown setting {x!r} for {flag}; valid: {valid} or all") from None
        if out[-1] not in SETTINGS and not families:
            raise SceneError(f"{flag} {x} is a scene family this command does not take; valid: {valid} or all")
    if not out:
        raise SceneError(f"{flag} must be {valid} or all, not {text!r}")
    return out


def resolve_k(setting_or_k: Setting, *, is_setting: bool = True) -> int:
    """K for a setting (default: an id or a family name), or K itself (is_setting=False) after a range check."""
    if is_setting:
        return setting_params(setting_or_k).k
    try:
        v = int(setting_or_k)
    except (TypeError, ValueError):
        raise SceneError(f"not an integer: {setting_or_k!r}") from None
    if not 0 <= v <= 100:
        raise SceneError(f"occupied cells K={v} out of range: 0 <= K <= 100")
    return v


def all_seed_sets() -> dict[str, list[int]]:
    """Every seed list by name (for the disjointness check and listings); a variant that keeps its base's slot
    searches its base's scenes and is not listed again."""
    out = {}
    for split in splits():
        for setting, fam in SCENE_FAMILIES.items():
            if fam.variant_of is not None and fam.slot == setting_params(fam.variant_of).slot:
                continue
            for part in PARTS:
                out[f"{split}/setting{setting}/{part}"] = scene_seeds(setting, split, part)
    out["density"] = [s for s, _ in density_scenes()]
    return out


def scene_layout() -> bytes:
    """What decides a family's scenes, as bytes (view caches hash it): every family's scene parameters and the
    seed layout; its task is not in it (a task's render options are in the search config's render key)."""
    cfg = _config()
    fams = {str(k): f.model_dump(exclude={"task", "variant_of"}) for k, f in SCENE_FAMILIES.items()}
    layout = {k: cfg.get(k) for k in ("splits", "base", "stride", "offset", "density")}
    return json.dumps({"families": fams, **layout}, sort_keys=True).encode()


__all__ = ["SETTINGS", "SCENE_FAMILIES", "SETTINGS_ENV", "child_env", "SceneFamily", "SearchTask", "TaskBudget", "TaskLattice", "PARTS",
           "scene_seeds", "density_scenes", "parse_settings", "resolve_k", "splits", "all_seed_sets", "setting_key",
           "setting_params", "generate_setting_scene", "scene_layout", "settings_file"]

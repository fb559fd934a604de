"""The learning settings and their scene splits, read from scenes/settings.yaml.

A setting is one of the paper's ids 1-3 (K = 2, 5, 10 on the 50 m grid) or a named scene family
("wide", "wide-uniform"): K plus the scene parameters (grid, city size, placement of people).
Seeds are ranges, so a split is reproducible from the file alone and two parts never share a scene.
"""

from __future__ import annotations

import functools

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..errors import SceneError
from ..geometry import Grid
from ..paths import SCENES_DIR
from .scene import Placement, SceneParams, SceneSpec, generate_scene

SETTINGS_FILE = SCENES_DIR / "settings.yaml"
PARTS = ("train", "val", "test")

Setting = int | str


class SceneFamily(BaseModel):
    """What a setting's scenes are: K, the grid, the city and how people are placed, plus where its seeds
    lie (`slot` in the seed layout, and the split used when none is asked for)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    k: int = Field(ge=0)
    grid_n: int = Field(10, ge=1)
    cell_m: float = Field(5.0, gt=0)
    city_half_m: float = 90.0
    placement: Placement = Field(default_factory=Placement)
    slot: int = Field(ge=1)
    split: str = "paper"

    @property
    def grid(self) -> Grid:
        return Grid(self.grid_n, self.cell_m)

    def scene(self, seed: int) -> SceneSpec:
        return generate_scene(seed, self.k, SceneParams(city_half_m=self.city_half_m), self.grid, self.placement)


@functools.lru_cache(maxsize=1)
def _config() -> dict:
    try:
        cfg = yaml.safe_load(SETTINGS_FILE.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SceneError(f"cannot read scene settings {SETTINGS_FILE}: {e}") from None
    return cfg


def _settings() -> dict[int, int]:
    return {int(k): int(v) for k, v in _config()["settings"].items()}


SETTINGS: dict[int, int] = _settings()  # setting id -> occupied cells K: {1: 2, 2: 5, 3: 10}


def _families() -> dict[Setting, SceneFamily]:
    out: dict[Setting, SceneFamily] = {i: SceneFamily(name=str(i), k=k, slot=i) for i, k in SETTINGS.items()}
    for name, d in (_config().get("families") or {}).items():
        try:
            out[str(name)] = SceneFamily(name=str(name), **d)
        except (TypeError, ValidationError) as e:
            raise SceneError(f"bad scene family {name!r} in {SETTINGS_FILE}: {e}".splitlines()[0]) from None
    return out


SCENE_FAMILIES: dict[Setting, SceneFamily] = _families()  # every setting: 1, 2, 3, "wide", "wide-uniform"


def _valid() -> str:
    return ", ".join(map(str, SCENE_FAMILIES))


def setting_params(setting: Setting) -> SceneFamily:
    """The scene parameters of a setting: an id 1-3 (also as text) or a family name; else a one-line error."""
    key: Setting = setting
    if isinstance(setting, str) and setting.strip().isdigit():
        key = int(setting)
    elif isinstance(setting, str):
        key = setting.strip()
    if isinstance(key, bool) or key not in SCENE_FAMILIES:
        raise SceneError(f"unknown setting {setting!r}; valid: {_valid()}")
    return SCENE_FAMILIES[key]


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
            out.append(int(x) if x.isdigit() else setting_params(x).name)
            setting_params(out[-1])
        except SceneError:
            raise SceneError(f"unknown setting {x!r} for {flag}; valid: {valid} or all") from None
        if isinstance(out[-1], str) and not families:
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
    """Every seed list by name (for the disjointness check and listings)."""
    out = {}
    for split in splits():
        for setting in SCENE_FAMILIES:
            for part in PARTS:
                out[f"{split}/setting{setting}/{part}"] = scene_seeds(setting, split, part)
    out["density"] = [s for s, _ in density_scenes()]
    return out


__all__ = ["SETTINGS", "SCENE_FAMILIES", "SceneFamily", "PARTS", "scene_seeds", "density_scenes", "parse_settings",
           "resolve_k", "splits", "all_seed_sets", "setting_params", "generate_setting_scene"]

"""The paper's learning settings and their scene splits, read from scenes/settings.yaml.

Seeds are ranges, so a split is reproducible from the file alone and two parts never share a scene.
"""

from __future__ import annotations

import functools

import yaml

from ..errors import SceneError
from ..paths import SCENES_DIR

SETTINGS_FILE = SCENES_DIR / "settings.yaml"
PARTS = ("train", "val", "test")


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


def splits() -> list[str]:
    return list(_config()["splits"])


def scene_seeds(setting: int, split: str = "paper", part: str = "train") -> list[int]:
    """The scene seeds of one part of one split of a setting (generate each with K = SETTINGS[setting])."""
    cfg = _config()
    if setting not in SETTINGS:
        raise SceneError(f"unknown setting {setting!r}; valid: {', '.join(map(str, sorted(SETTINGS)))}")
    if split not in cfg["splits"]:
        raise SceneError(f"unknown split {split!r}; valid: {', '.join(cfg['splits'])}")
    if part not in PARTS:
        raise SceneError(f"unknown part {part!r}; valid: {', '.join(PARTS)}")
    start = cfg["base"][split] + (int(setting) - 1) * cfg["stride"][split] + cfg["offset"][part][split]
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


def parse_settings(text: str, flag: str = "--setting") -> list[int]:
    """A command line's settings: "all", one id, or comma-separated ids (e.g. "1,3"), or a one-line error."""
    if str(text).strip() == "all":
        return sorted(SETTINGS)
    try:
        out = [int(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise SceneError(f"{flag} must be 1, 2, 3 or all, not {text!r}") from None
    bad = [x for x in out if x not in SETTINGS]
    if bad or not out:
        raise SceneError(f"unknown setting {bad[0] if bad else text!r}; valid: {sorted(SETTINGS)} or all")
    return out


def resolve_k(setting_or_k: int | str, *, is_setting: bool = True) -> int:
    """K for a setting id (default), or K itself (is_setting=False) after a range check."""
    try:
        v = int(setting_or_k)
    except (TypeError, ValueError):
        raise SceneError(f"not an integer: {setting_or_k!r}") from None
    if is_setting:
        if v not in SETTINGS:
            raise SceneError(f"unknown setting {v}; valid: {', '.join(map(str, sorted(SETTINGS)))}")
        return SETTINGS[v]
    if not 0 <= v <= 100:
        raise SceneError(f"occupied cells K={v} out of range: 0 <= K <= 100")
    return v


def all_seed_sets() -> dict[str, list[int]]:
    """Every seed list by name (for the disjointness check and listings)."""
    out = {}
    for split in splits():
        for setting in SETTINGS:
            for part in PARTS:
                out[f"{split}/setting{setting}/{part}"] = scene_seeds(setting, split, part)
    out["density"] = [s for s, _ in density_scenes()]
    return out


__all__ = ["SETTINGS", "PARTS", "scene_seeds", "density_scenes", "parse_settings", "resolve_k", "splits",
           "all_seed_sets"]

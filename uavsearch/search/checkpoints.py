"""Where every shipped checkpoint lives, and which module builds each kind of net, imported only when a
checkpoint of that kind loads (loading one net never imports every net; this module needs no torch).

`shipped(kind, setting, fusion=..., budget=...)` is the one map from what a user names to a file in models/,
read from what the setting's family declares (scenes/settings.yaml: its task's `perception` and `policies`):
- "perception": the family's stage-1 net where it exists, else the paper's models/perception.pt;
- a paper setting's policy ("learned", or another policy registry name such as "reactive", "external"):
  <policies>_<fusion>.pt for the paper's learned policy, <policies>_<fusion>_<policy>.pt otherwise;
- "map": the wide-area policy of one of Table III's budgets, <policies>_T8_map.pt or <policies>_<seconds>s_map.pt.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from uavsearch.errors import UavsearchError
from uavsearch.paths import MODELS_DIR
from uavsearch.world.settings import setting_params

# the policy kind a search checkpoint records -> "module:NetClass:ConfigClass" (kind "paper": the paper's PolicyNet,
# also what a file without a kind holds)
POLICY_NETS: dict[str, str] = {
    "paper": "uavsearch.search.policy:PolicyNet:PolicyConfig",
    "reactive": "uavsearch.search.reactive:ReactivePolicyNet:ReactiveConfig",
    "external": "uavsearch.search.external_policy:ExternalPolicyNet:ExternalConfig",
    "map": "uavsearch.search.map_policy:MapPolicyNet:MapPolicyConfig",
}
def policy_net(kind: str) -> tuple[type, type]:
    """(net class, config class) of a search checkpoint's policy kind, its module imported now."""
    if kind not in POLICY_NETS:
        raise UavsearchError(f"unknown policy net kind {kind!r}; known: {', '.join(POLICY_NETS)}")
    module, net, config = POLICY_NETS[kind].split(":")
    m = importlib.import_module(module)
    return getattr(m, net), getattr(m, config)


def checkpoint_path(setting: int | str, fusion: str, models_dir=None, policy: str = "learned") -> Path:
    """Where `policy` trained with `fusion` for a paper `setting` lives (default: the shipped models/): the
    family's declared stem (search_s<id>) + _<fusion>.pt for the paper's "learned" policy, + _<fusion>_<policy>.pt
    otherwise."""
    suffix = "" if policy == "learned" else f"_{policy}"
    return Path(models_dir or MODELS_DIR) / f"{setting_params(setting).task.policies}_{fusion}{suffix}.pt"


def wide_checkpoint(budget: str, models_dir=None, family: str = "wide") -> Path:
    """Where the learned wide-area policy of a budget ("8" views or seconds such as "240") lives (default: the
    shipped one in models/)."""
    tag = "T8" if budget == "8" else f"{budget}s"
    return Path(models_dir or MODELS_DIR) / f"{setting_params(family).task.policies}_{tag}_map.pt"


def shipped_perception(setting=None) -> Path:
    """The shipped net for a setting: the one its family declares (scenes/settings.yaml: the wide families'
    perception_wide.pt, trained on their altitudes) where it exists, else the paper's models/perception.pt."""
    if setting is not None and (MODELS_DIR / setting_params(setting).task.perception).is_file():
        return MODELS_DIR / setting_params(setting).task.perception
    return MODELS_DIR / "perception.pt"


def shipped(kind: str, setting=None, *, fusion: str = "learned", budget: str | None = None, models_dir=None) -> Path:
    """The checkpoint of a kind ("perception", "map", or a paper policy's registry name) for a setting or family
    (module docstring)."""
    if kind == "perception":
        return shipped_perception(setting)
    if kind == "map":
        return wide_checkpoint(str(budget), models_dir, setting or "wide")
    return checkpoint_path(setting, fusion, models_dir, policy=kind)


__all__ = ["POLICY_NETS", "checkpoint_path", "policy_net", "shipped", "shipped_perception",
           "wide_checkpoint"]

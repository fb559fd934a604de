"""The gymnasium ids of uavsearch's environments, registered when this module is imported.

gymnasium imports it itself for an id written ``"uavsearch.envs:uavsearch/ActiveSearch-v0"`` (its
``module:id`` form), or after ``import uavsearch.envs``; nothing else in uavsearch imports gymnasium, so the
vehicle and render processes of a flight never pay for it.

- ``uavsearch/ActiveSearch-v0``: the paper's settings 1-3 (``setting=`` 1 | 2 | 3; search/envs/search_env.py ActiveSearchEnv).
- ``uavsearch/WideSearch-v0``: the wide scene family (search/envs/search_env.py WideSearchEnv).

- ``team_parallel_env(...)`` / ``team_aec_env(...)``: the team search as a PettingZoo env (search/envs/team_env.py;
  PettingZoo has no registry, so these two functions are where users find it).

Both gymnasium ids have a native vector env (search/envs/vector_env.py SearchVectorEnv, "cells" observations on the view caches):
``gym.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point", obs="cells")``.
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

ACTIVE_SEARCH_ID = "uavsearch/ActiveSearch-v0"
WIDE_SEARCH_ID = "uavsearch/WideSearch-v0"


def wide_vector_env(num_envs: int = 1, budget="8", **kwargs):
    """The vector entry point of WideSearch-v0: SearchVectorEnv on the wide family (setting "wide") with
    WideSearchEnv's task for the budget (search_env.wide_task: Table III's, fusion included)."""
    from uavsearch.search.envs.search_env import wide_task
    from uavsearch.search.envs.vector_env import SearchVectorEnv

    kwargs.setdefault("setting", "wide")
    config, fusion = wide_task(kwargs["setting"], budget, kwargs.pop("config", None), kwargs.get("cache"))
    kwargs["fusion"] = kwargs.get("fusion") or fusion
    return SearchVectorEnv(num_envs=num_envs, config=config, **kwargs)


def team_parallel_env(**kwargs):
    """The team search as a PettingZoo ParallelEnv (search/envs/team_env.py TeamSearchEnv; the ``pettingzoo``
    extra): by default the team task of missions/wide_team.yaml, 3 vehicles for 80 s on the wide family."""
    from uavsearch.search.envs.team_env import TeamSearchEnv

    return TeamSearchEnv(**kwargs)


def team_aec_env(**kwargs):
    """The same team env in PettingZoo's AEC form (its own ``parallel_to_aec`` conversion)."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(team_parallel_env(**kwargs))


# No max_episode_steps: the view budget T (and the wide family's time budget) is part of the task (a mission
# parameter), and the env terminates itself.
if ACTIVE_SEARCH_ID not in registry:
    register(id=ACTIVE_SEARCH_ID, entry_point="uavsearch.search.envs.search_env:ActiveSearchEnv",
             vector_entry_point="uavsearch.search.envs.vector_env:SearchVectorEnv")
if WIDE_SEARCH_ID not in registry:
    register(id=WIDE_SEARCH_ID, entry_point="uavsearch.search.envs.search_env:WideSearchEnv",
             vector_entry_point="uavsearch.envs:wide_vector_env")

__all__ = ["ACTIVE_SEARCH_ID", "WIDE_SEARCH_ID", "team_aec_env", "team_parallel_env", "wide_vector_env"]

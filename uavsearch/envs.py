"""The gymnasium ids of uavsearch's environments, registered when this module is imported.

gymnasium imports it itself for an id written ``"uavsearch.envs:uavsearch/ActiveSearch-v0"`` (its
``module:id`` form), or after ``import uavsearch.envs``; nothing else in uavsearch imports gymnasium, so the
vehicle and render processes of a flight never pay for it.
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

ACTIVE_SEARCH_ID = "uavsearch/ActiveSearch-v0"

if ACTIVE_SEARCH_ID not in registry:
    # No max_episode_steps: the view budget T is part of the task (a mission parameter), and the env
    # terminates itself after T views.
    register(id=ACTIVE_SEARCH_ID, entry_point="uavsearch.search.env:ActiveSearchEnv")

__all__ = ["ACTIVE_SEARCH_ID"]

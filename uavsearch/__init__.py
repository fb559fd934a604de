"""uavsearch: a flight-dynamics-realistic MAVLink UAV testbed for active object search."""

__version__ = "0.1.0"


def _register_envs() -> None:
    """Make `gymnasium.make("uavsearch/ActiveSearch-v0")` work after `import uavsearch`."""
    try:
        from gymnasium.envs.registration import register, registry
    except ImportError:  # gymnasium is a dependency; tolerate its absence for tools that don't need it
        return
    if "uavsearch/ActiveSearch-v0" not in registry:
        # No max_episode_steps: the view budget T is part of the task (a mission parameter), and the
        # env terminates itself after T views.
        register(id="uavsearch/ActiveSearch-v0", entry_point="uavsearch.search.env:ActiveSearchEnv")


_register_envs()

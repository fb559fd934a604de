"""uavsearch: a flight-dynamics-realistic MAVLink UAV testbed for active object search."""

import importlib.abc
import importlib.util
import sys

__version__ = "0.1.0"

ENV_ID = "uavsearch/ActiveSearch-v0"


def _register_envs() -> None:
    """Make `gymnasium.make("uavsearch/ActiveSearch-v0")` work after `import uavsearch`."""
    from gymnasium.envs.registration import register, registry

    if ENV_ID not in registry:
        # No max_episode_steps: the view budget T is part of the task (a mission parameter), and the
        # env terminates itself after T views.
        register(id=ENV_ID, entry_point="uavsearch.search.env:ActiveSearchEnv")


class _RegisterWhenGymnasiumLoads(importlib.abc.MetaPathFinder):
    """Registers the env right after gymnasium is first imported, by whoever imports it.

    Why not import gymnasium here: every uavsearch process would pay for it (about 0.1 s beyond numpy),
    including the vehicle and render processes of a flight, which never use it.
    """

    def find_spec(self, name, path=None, target=None):
        if name != "gymnasium":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:  # gymnasium is a dependency; tolerate its absence
            return spec
        exec_module = spec.loader.exec_module

        def exec_then_register(module):
            exec_module(module)
            _register_envs()

        spec.loader.exec_module = exec_then_register
        return spec


if "gymnasium" in sys.modules:
    _register_envs()
elif not any(isinstance(f, _RegisterWhenGymnasiumLoads) for f in sys.meta_path):
    sys.meta_path.insert(0, _RegisterWhenGymnasiumLoads())

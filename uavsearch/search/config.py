"""The search task's parameters (paper Sec. VI-B), shared by the teleport env, training and flight.

A SearchConfig says where the camera may go (its viewpoint lattice, search/lattice.py), what it sees
(grid, camera, render) and how long it may look (views). It travels with everything made for it: training
and evaluation arguments, checkpoints (`config_to_dict` / `config_from_dict`) and view caches
(`render_key`), so nothing below the command line assumes the paper's defaults.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..errors import UavsearchError
from ..geometry import CameraIntrinsics, Grid
from ..world.render import RenderOptions
from ..world.settings import setting_params

# Step vectors (east, north, up) in lattice units; "up" steps to the next higher altitude layer of the
# lattice, "down" to the next lower one. The paper's action set: heading fixed north, a constant step along
# one horizontal axis.
ACTIONS: dict[str, tuple[int, int, int]] = {
    "MoveAhead": (0, 1, 0),  # north
    "MoveRight": (1, 0, 0),  # east
    "MoveLeft": (-1, 0, 0),  # west
    "MoveBack": (0, -1, 0),  # south
    "Climb": (0, 0, 1),  # to the next higher altitude layer
    "Descend": (0, 0, -1),  # to the next lower altitude layer
}
PAPER_ACTIONS = ("MoveAhead", "MoveRight", "MoveLeft", "MoveBack")
# How an action picks the next viewpoint: "steps" applies one of `actions`' step vectors (the paper's rule);
# "any" names the viewpoint itself (action a flies to viewpoint a: any viewpoint may be chosen next).
MOVE_SETS = ("steps", "any")


def _autopilot_default(name: str) -> float:
    """The autopilot parameter's default (flight/control.py declares it once); imported here only when a
    config is made, so reading a mission never loads the flight stack."""
    from ..flight.control import CONTROL_PARAMS

    return float(next(p.default for p in CONTROL_PARAMS if p.name == name))


@dataclass(frozen=True)
class FlightSpeeds:
    """How fast the vehicle moves between viewpoints: the autopilot's limits (its parameter defaults) and
    the settling times fitted to flown legs (a 10 m step at 70 m in 6.0 s; 15 / 30 / 45 m descents in
    11.1 / 21.1 / 31.1 s; a 45 m climb in 16.6 s)."""

    cruise_m_s: float = field(default_factory=lambda: _autopilot_default("MPC_XY_CRUISE"))
    accel_hor_m_s2: float = field(default_factory=lambda: _autopilot_default("MPC_ACC_HOR"))
    climb_m_s: float = field(default_factory=lambda: _autopilot_default("MPC_Z_VEL_MAX_UP"))
    accel_up_m_s2: float = field(default_factory=lambda: _autopilot_default("MPC_ACC_UP_MAX"))
    descent_m_s: float = field(default_factory=lambda: _autopilot_default("MPC_Z_VEL_MAX_DN"))
    accel_down_m_s2: float = field(default_factory=lambda: _autopilot_default("MPC_ACC_DOWN_MAX"))
    settle_hor_s: float = 2.3
    settle_vert_s: float = 0.6


def _default_render_options():
    return RenderOptions()


@dataclass(frozen=True)
class SearchConfig:
    """Where the camera may go and what it sees: the paper's defaults (70 m, 10 m steps, T = 5)."""

    altitude_m: float = 70.0  # the start altitude (the first layer of the lattice)
    step_m: float = 10.0  # lattice spacing
    budget_T: int = 5  # views per episode; the start view counts as the first
    intrinsics: CameraIntrinsics = field(default_factory=CameraIntrinsics)
    grid: Grid = field(default_factory=Grid)
    actions: tuple[str, ...] = PAPER_ACTIONS
    render: object = field(default_factory=_default_render_options)  # world.render.RenderOptions
    min_cell_area_px: float = 1.0  # a cell counts as in view (c^t) from this many pixels
    altitudes_m: tuple[float, ...] = ()  # the lattice's altitude layers, the first = altitude_m; () = one layer
    lattice_points: int | None = None  # positions per side of a layer; None: as many as stay over the area
    speeds: FlightSpeeds = field(default_factory=FlightSpeeds)
    move_set: str = "steps"  # "steps": the `actions` step vectors; "any": the action is the next viewpoint's index
    budget_s: float | None = None  # simulated seconds of flight per episode (lattice.flight_time_s); None: views only

    def __post_init__(self):
        if self.move_set not in MOVE_SETS:
            raise UavsearchError(f"unknown move_set {self.move_set!r}; valid: {', '.join(MOVE_SETS)}")
        if self.budget_s is not None and not self.budget_s >= 0:
            raise UavsearchError(f"budget_s must be a non-negative number of seconds or None, got {self.budget_s}")
        unknown = [a for a in self.actions if a not in ACTIONS]
        if unknown:
            raise UavsearchError(f"unknown action(s) {unknown}; valid: {sorted(ACTIONS)}")
        if self.budget_T < 1:
            raise UavsearchError(f"budget_T must be at least 1, got {self.budget_T}")
        if self.step_m <= 0 or self.altitude_m <= 0 or any(a <= 0 for a in self.altitudes_m):
            raise UavsearchError("step_m and the altitudes must be positive")
        if self.altitudes_m and self.altitudes_m[0] != self.altitude_m:
            raise UavsearchError(f"the first lattice altitude ({self.altitudes_m[0]:g} m) must be the start "
                                 f"altitude_m ({self.altitude_m:g} m)")
        if len(set(self.altitudes_m)) != len(self.altitudes_m):
            raise UavsearchError(f"lattice altitudes repeat: {self.altitudes_m}")
        if self.lattice_points is not None and self.lattice_points < 1:
            raise UavsearchError(f"lattice_points must be at least 1, got {self.lattice_points}")

    @property
    def layers_m(self) -> tuple[float, ...]:
        """The lattice's altitudes, start layer first."""
        return tuple(float(a) for a in self.altitudes_m) or (float(self.altitude_m),)

    @property
    def lattice_size(self) -> int:
        """Positions per side of a layer: by default the odd step grid around the centre that stays above
        the search area ({-20, -10, 0, 10, 20} for the paper)."""
        if self.lattice_points is not None:
            return int(self.lattice_points)
        return 2 * int(np.floor(self.grid.half_m / self.step_m + 1e-9)) + 1

    @property
    def lattice(self):
        """The viewpoint lattice (search.lattice.Lattice), built once per config."""
        from .lattice import lattice_of

        return lattice_of(self)

    @property
    def num_actions(self) -> int:
        """How many actions a policy chooses from: the step vectors, or every viewpoint ("any")."""
        return self.lattice.num_positions if self.move_set == "any" else len(self.actions)

    def action_vectors(self) -> np.ndarray:
        """(num_actions, 3) lattice steps (east, north, up) of the configured action set."""
        return np.array([ACTIONS[a] for a in self.actions], dtype=np.int64)

    def render_key(self) -> str:
        """What decides the pixels of every lattice view: the camera, the grid, the render options and the
        viewpoints themselves (view caches are keyed by it; budgets, actions and speeds are not in it)."""
        pos = np.round(self.lattice.positions_enu, 3).tolist()
        return repr((self.intrinsics, self.grid, self.render, pos))


# Nested dataclasses a SearchConfig holds, rebuilt by config_from_dict.
_NESTED = {"intrinsics": CameraIntrinsics, "grid": Grid, "render": RenderOptions, "speeds": FlightSpeeds}


def config_to_dict(config: SearchConfig) -> dict:
    """Plain JSON-able fields (checkpoints and run args record the config they were made for)."""
    return dataclasses.asdict(config)


def config_from_dict(d: dict) -> SearchConfig:
    """The SearchConfig `config_to_dict` wrote; fields it lacks (an older record) take today's defaults."""
    names = {f.name for f in dataclasses.fields(SearchConfig)}
    kw = {}
    for k, v in d.items():
        if k not in names:
            continue
        if k in _NESTED and isinstance(v, dict):
            sub = {f.name for f in dataclasses.fields(_NESTED[k])}
            v = _NESTED[k](**{a: b for a, b in v.items() if a in sub})
        elif k in ("actions", "altitudes_m"):
            v = tuple(v)
        kw[k] = v
    return SearchConfig(**kw)


def wide_config() -> SearchConfig:
    """The wide family's search task (scenes/settings.yaml): 150 m of 30 x 30 cells; 6 x 6 viewpoints 25 m apart
    at 70 m and 40 m (plus the start above the centre at 70 m, lattice.py), any viewpoint next, T = 8 views, 240 s
    of flight."""
    return setting_config("wide")


def wide_budgets(config: SearchConfig) -> dict[str, SearchConfig]:
    """The wide family's two budgets (Table III's conditions) from its config, which holds both: T views with no
    time limit, and budget_s seconds of flight with as many views as fit."""
    if config.budget_s is None:
        raise UavsearchError("the wide search's budgets need a config with budget_s (the time budget)")
    return {f"T = {config.budget_T} views": dataclasses.replace(config, budget_s=None),
            f"{config.budget_s:g} s": dataclasses.replace(config, budget_T=config.lattice.num_positions)}


def setting_config(setting) -> SearchConfig:
    """The search task a scene family declares (world/settings.py's SearchTask) on the family's grid: the paper's
    for settings 1-3, the wide one for the wide families, whatever a declared variant says."""
    fam = setting_params(setting)
    task, lat = fam.task, fam.task.lattice
    layers = tuple(float(a) for a in lat.altitudes_m)
    return SearchConfig(altitude_m=layers[0], step_m=float(lat.step_m), budget_T=int(task.budget.views), grid=fam.grid,
                        actions=tuple(lat.actions) or PAPER_ACTIONS,  # "any" keeps them: checkpoints compare them
                        render=task.render, altitudes_m=layers if len(layers) > 1 else (), lattice_points=lat.points,
                        move_set=lat.moves, budget_s=task.budget.seconds)


__all__ = ["ACTIONS", "MOVE_SETS", "PAPER_ACTIONS", "wide_config", "FlightSpeeds", "SearchConfig", "config_from_dict", "config_to_dict",
           "setting_config", "wide_budgets"]

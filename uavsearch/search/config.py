"""The search task's parameters (paper Sec. VI-B), shared by the teleport env, training and flight."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import UavsearchError
from ..geometry import CameraIntrinsics, Grid
from ..world.render import RenderOptions

# The paper's action set: heading fixed north, a constant step along one axis (ENU unit vectors).
ACTIONS: dict[str, tuple[int, int]] = {
    "MoveAhead": (0, 1),  # north
    "MoveRight": (1, 0),  # east
    "MoveLeft": (-1, 0),  # west
    "MoveBack": (0, -1),  # south
}
PAPER_ACTIONS = ("MoveAhead", "MoveRight", "MoveLeft", "MoveBack")


def _default_render_options():
    return RenderOptions()


@dataclass(frozen=True)
class SearchConfig:
    """Where the camera may go and what it sees: the paper's defaults (70 m, 10 m steps, T = 5)."""

    altitude_m: float = 70.0
    step_m: float = 10.0
    budget_T: int = 5  # views per episode; the start view counts as the first
    intrinsics: CameraIntrinsics = field(default_factory=CameraIntrinsics)
    grid: Grid = field(default_factory=Grid)
    actions: tuple[str, ...] = PAPER_ACTIONS
    render: object = field(default_factory=_default_render_options)  # world.render.RenderOptions
    min_cell_area_px: float = 1.0  # a cell counts as in view (c^t) from this many pixels

    def __post_init__(self):
        unknown = [a for a in self.actions if a not in ACTIONS]
        if unknown:
            raise UavsearchError(f"unknown action(s) {unknown}; valid: {sorted(ACTIONS)}")
        if self.budget_T < 1:
            raise UavsearchError(f"budget_T must be at least 1, got {self.budget_T}")
        if self.step_m <= 0 or self.altitude_m <= 0:
            raise UavsearchError("step_m and altitude_m must be positive")

    @property
    def lattice_half_steps(self) -> int:
        """How many steps from the centre the lattice reaches while staying over the search area."""
        return int(np.floor(self.grid.half_m / self.step_m + 1e-9))

    @property
    def lattice_size(self) -> int:
        return 2 * self.lattice_half_steps + 1

    def action_vectors(self) -> np.ndarray:
        """(num_actions, 2) lattice moves (east, north) of the configured action set."""
        return np.array([ACTIONS[a] for a in self.actions], dtype=np.int64)


def lattice_positions(config: SearchConfig) -> np.ndarray:
    """All camera positions the search can reach, (L*L, 3) ENU, row-major from the NW corner.

    The lattice is the step grid around the centre that stays above the search area
    ({-20, -10, 0, 10, 20}^2 for the paper); index = row * L + col like the cell grid.
    """
    h = config.lattice_half_steps
    coords = np.arange(-h, h + 1) * config.step_m
    ys, xs = coords[::-1], coords
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, config.altitude_m)], axis=-1)


def lattice_index(config: SearchConfig, ij: tuple[int, int]) -> int:
    """Index into lattice_positions of lattice coordinates (east steps, north steps) from the centre."""
    h = config.lattice_half_steps
    i, j = ij
    return (h - j) * config.lattice_size + (i + h)


def lattice_coords(config: SearchConfig, position_enu) -> tuple[int, int]:
    """Nearest lattice coordinates (east steps, north steps) of a position."""
    return (int(round(position_enu[0] / config.step_m)), int(round(position_enu[1] / config.step_m)))

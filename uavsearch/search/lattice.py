"""The viewpoint lattice: every camera position a search may take, built once from its SearchConfig.

Everything that depends on where the camera may go reads it from here: positions in 3-D, index <->
coordinates, the start viewpoint, the move rule of the action set, each (viewpoint, cell) pair's distance
and pixel area, and the vehicle's flight time between viewpoints.

Indexing: one square layer of L x L positions per altitude, row-major from the north-west corner like
the cell grid (index = layer * L * L + row * L + col), layers in the config's order of altitudes. The
paper's lattice is one layer of 5 x 5 at 70 m, 10 m apart, centred on the search area: index 12 is the
centre and the start. Where no layer point lies above the centre at the first altitude (an even L, e.g.
the wide family's 6 x 6 at 25 m), the start is a viewpoint of its own, appended as the last index
(P = layers * L * L + 1): every view from there is taken, cached and fused like any other.

Moves (config.move_set "steps"): an action is a step vector (east, north, up) in lattice units (`config.ACTIONS`); "up" steps to
the next higher altitude layer, "down" to the next lower one. A move that would leave the lattice keeps the camera where
it is (the view is re-taken and counts as a revisit), the paper's rule. With move_set "any" the action
is the index of the next viewpoint: moves[p, a] = a, any viewpoint may be chosen next (staying re-takes
the view), and what a move costs is its flight time (`flight_time_s`).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from ..errors import UavsearchError
from ..geometry import cell_pixel_areas, nadir_camera_pose


def _trapezoid_s(distance_m: np.ndarray, speed_m_s: float, accel_m_s2: float) -> np.ndarray:
    """Time to cover `distance_m` from rest to rest with a speed limit and a constant acceleration."""
    d = np.abs(distance_m)
    ramp_m = speed_m_s ** 2 / accel_m_s2  # distance spent accelerating and braking at full speed
    return np.where(d >= ramp_m, d / speed_m_s + speed_m_s / accel_m_s2, 2.0 * np.sqrt(d / accel_m_s2))


class Lattice:
    """The viewpoints of one SearchConfig (build it with `config.lattice`; it is cached per config)."""

    def __init__(self, config):
        self.config = config
        self.altitudes_m: tuple[float, ...] = config.layers_m
        self.size = config.lattice_size  # L: positions per side of a layer
        self.spacing_m = float(config.step_m)
        L = self.size
        offsets = (np.arange(L) - (L - 1) / 2.0) * self.spacing_m  # west -> east; centred on the area
        ys, xs = offsets[::-1], offsets  # row 0 is the northernmost
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        layers = [np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, alt)], axis=-1) for alt in self.altitudes_m]
        start = np.array([[0.0, 0.0, self.altitudes_m[0]]])
        self.extra_start = bool(np.linalg.norm(layers[0] - start, axis=1).min() > 1e-6)
        if self.extra_start:
            layers.append(start)
        self.positions_enu: np.ndarray = np.concatenate(layers).astype(float)  # (P, 3)
        self.num_positions = len(self.positions_enu)
        self.positions_enu.setflags(write=False)

    # -- index <-> coordinates ---------------------------------------------------------------------

    def index(self, ij, layer: int = 0) -> int:
        """Index of lattice coordinates (east steps, north steps) from the centre (odd L), in `layer`."""
        h = (self.size - 1) // 2
        i, j = int(ij[0]), int(ij[1])
        return layer * self.size ** 2 + (h - j) * self.size + (i + h)

    def coords(self, index: int) -> tuple[int, int, int]:
        """(col, row, layer) of an index: col from the west edge, row from the north edge."""
        layer, rest = divmod(int(index), self.size ** 2)
        row, col = divmod(rest, self.size)
        return col, row, layer

    def nearest(self, position_enu) -> int:
        """The viewpoint nearest a position (east, north, up)."""
        d = np.linalg.norm(self.positions_enu - np.asarray(position_enu, dtype=float)[None, :3], axis=1)
        return int(np.argmin(d))

    @property
    def start_index(self) -> int:
        """Above the middle of the search area at the first altitude (the centre of an odd layer, else the
        appended last index)."""
        if self.extra_start:
            return self.num_positions - 1
        return self.nearest([0.0, 0.0, self.altitudes_m[0]])

    # -- the move rule -------------------------------------------------------------------------------

    @functools.cached_property
    def action_vectors(self) -> np.ndarray:
        """(A, 3) steps (east, north, up) of the configured action set, in lattice units."""
        return self.config.action_vectors()

    @functools.cached_property
    def moves(self) -> torch.Tensor:
        """(P, A) long: the index reached from viewpoint p by action a (p itself if it leaves the lattice);
        with move_set "any" (P, P): moves[p, a] = a."""
        if self.config.move_set == "any":
            return torch.arange(self.num_positions).expand(self.num_positions, -1).contiguous()
        if self.extra_start:
            raise UavsearchError("step moves need a lattice point above the centre (an odd lattice_points); "
                                 "use move_set='any'")
        L, K = self.size, len(self.altitudes_m)
        by_height = list(np.argsort(self.altitudes_m))  # layer indices from the lowest altitude up
        table = np.zeros((self.num_positions, len(self.action_vectors)), dtype=np.int64)
        for p in range(self.num_positions):
            col, row, layer = self.coords(p)
            for a, (de, dn, du) in enumerate(self.action_vectors):
                c, r, rank = col + de, row - dn, by_height.index(layer) + du
                inside = 0 <= c < L and 0 <= r < L and 0 <= rank < K
                table[p, a] = by_height[rank] * L * L + r * L + c if inside else p
        return torch.as_tensor(table)

    # -- what each viewpoint sees --------------------------------------------------------------------

    @functools.cached_property
    def cell_areas(self) -> torch.Tensor:
        """(P, N) float: each cell's pixel area (F_size) in the nadir view from each viewpoint."""
        c = self.config
        return torch.as_tensor(np.stack([cell_pixel_areas(c.grid, c.intrinsics, nadir_camera_pose(p))
                                         for p in self.positions_enu]), dtype=torch.float32)

    @functools.cached_property
    def cell_distances(self) -> torch.Tensor:
        """(P, N) float: horizontal distance in metres from each viewpoint to each cell centre.

        With a nadir camera over flat ground a cell's pixel area depends only on the altitude; what changes
        within a layer is how far off-nadir the cell is (parallax, people hidden by buildings and trees).
        """
        pos = self.positions_enu[:, None, :2]
        centres = self.config.grid.centers_enu[None, :, :2]
        return torch.as_tensor(np.linalg.norm(pos - centres, axis=-1), dtype=torch.float32)

    # -- flying between viewpoints -------------------------------------------------------------------

    @functools.cached_property
    def flight_time_s(self) -> np.ndarray:
        """(P, P) seconds the vehicle needs from viewpoint a to viewpoint b, settled for the picture.

        Each axis flies a speed-limited, acceleration-limited profile (the autopilot's cruise, climb and
        descent limits); horizontal and vertical legs overlap, and the slower one decides, plus the time
        the position controller takes to settle within the capture radius.
        """
        s = self.config.speeds
        pos = self.positions_enu
        horiz = np.linalg.norm(pos[None, :, :2] - pos[:, None, :2], axis=-1)
        rise = pos[None, :, 2] - pos[:, None, 2]  # + climb, - descend
        t_h = _trapezoid_s(horiz, s.cruise_m_s, s.accel_hor_m_s2) + np.where(horiz > 0, s.settle_hor_s, 0.0)
        t_up = _trapezoid_s(rise, s.climb_m_s, s.accel_up_m_s2)
        t_dn = _trapezoid_s(rise, s.descent_m_s, s.accel_down_m_s2)
        t_v = np.where(rise > 0, t_up, t_dn) + np.where(rise != 0, s.settle_vert_s, 0.0)
        out = np.maximum(t_h, t_v)
        np.fill_diagonal(out, 0.0)
        return out

    @functools.cached_property
    def flight_time_t(self) -> torch.Tensor:
        """flight_time_s as a float64 tensor (the search loop's budget reads it every view)."""
        return torch.as_tensor(self.flight_time_s, dtype=torch.float64)


@functools.lru_cache(maxsize=16)
def lattice_of(config) -> Lattice:
    return Lattice(config)


__all__ = ["Lattice", "lattice_of"]

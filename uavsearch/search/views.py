"""One search loop, two vehicles: what a vehicle returns for each view, and the teleport vehicle.

A vehicle goes to a position, takes a picture and returns a View: the image and the pose it REPORTS
for it. The teleport vehicle reports the exact pose; the MAVLink vehicle reports its estimator's, so
estimation error becomes projection error exactly as on a real drone.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..geometry import CameraIntrinsics, CameraPose, Grid, cell_label_image, cell_pixel_areas, nadir_camera_pose
from ..world.render import SceneRenderer
from .config import SearchConfig


@dataclass(frozen=True)
class View:
    """An image and everything perception needs to read it against the grid."""

    image: np.ndarray  # (H, W, 3) uint8
    pose: CameraPose  # the pose the image is reported at
    position_enu: np.ndarray  # (3,) reported camera position
    cell_label: np.ndarray  # (H, W) int16: the cell each pixel sees, -1 off the grid (mask m_i = label == i)
    cell_area_px: np.ndarray  # (num_cells,) float32: F_size, clipped image polygon area
    cells_in_view: np.ndarray  # (num_cells,) bool: c^t
    person_mask: np.ndarray | None = None  # (H, W) bool ground truth, when the vehicle knows it
    person_fraction: np.ndarray | None = None  # (H, W) float32 share of each pixel showing a person, likewise
    person_index: np.ndarray | None = None  # (H, W) int16 the person (spec.people index) each pixel shows, -1 none


def make_view(
    image: np.ndarray,
    pose: CameraPose,
    grid: Grid,
    intrinsics: CameraIntrinsics,
    person_mask: np.ndarray | None = None,
    min_cell_area_px: float = 1.0,
    person_fraction: np.ndarray | None = None,
    person_index: np.ndarray | None = None,
    geometry: tuple[np.ndarray, np.ndarray] | None = None,
) -> View:
    """Project the grid into an image taken at `pose` (Eq. 1) and package it. `geometry`: the pose's
    (cell label image, cell areas) when the caller already has them."""
    label, areas = geometry if geometry is not None else (cell_label_image(grid, intrinsics, pose),
                                                          cell_pixel_areas(grid, intrinsics, pose).astype(np.float32))
    return View(
        image=image,
        pose=pose,
        position_enu=np.asarray(pose.position_enu, dtype=float),
        cell_label=label,
        cell_area_px=areas,
        cells_in_view=areas >= min_cell_area_px,
        person_mask=person_mask,
        person_fraction=person_fraction,
        person_index=person_index,
    )


class Vehicle(Protocol):
    """What the search loop needs of a vehicle (teleport or MAVLink)."""

    config: SearchConfig

    def capture(self, position_enu) -> View:
        """Go to `position_enu` (heading north), take a picture, return it with the reported pose."""

    def close(self) -> None: ...


@functools.lru_cache(maxsize=256)
def nadir_view_geometry(grid: Grid, intrinsics: CameraIntrinsics, position_enu: tuple) -> tuple[np.ndarray, np.ndarray]:
    """A nadir view's grid projection depends on its position only: every scene of a lattice shares it
    (a third of a teleport capture's own time). Read-only, as the views share it."""
    pose = nadir_camera_pose(np.array(position_enu, dtype=float))
    label, areas = cell_label_image(grid, intrinsics, pose), cell_pixel_areas(grid, intrinsics, pose).astype(np.float32)
    label.flags.writeable = areas.flags.writeable = False
    return label, areas


class TeleportVehicle:
    """Sets the camera pose directly: no dynamics, no MAVLink; renders cached per position.

    Renders with sensor randomisation draw their noise from a generator seeded by (scene seed,
    position), so a cached view and a fresh render of the same position are identical.
    """

    def __init__(self, spec, config: SearchConfig | None = None, cache: bool = True):
        self.spec = spec
        self.config = config or SearchConfig()
        self._renderer = SceneRenderer(spec, self.config.intrinsics, self.config.render)
        self._cache: dict[tuple[int, int], View] | None = {} if cache else None
        self.renders = 0

    def _rng_for(self, key: tuple[int, int]) -> np.random.Generator:
        offset = 1 << 20  # SeedSequence entropy must be non-negative
        return np.random.default_rng([int(self.spec.seed), key[0] + offset, key[1] + offset])

    def capture(self, position_enu) -> View:
        pos = np.asarray(position_enu, dtype=float)
        key = (int(round(pos[0] * 1000)), int(round(pos[1] * 1000)), int(round(pos[2] * 1000)))
        if self._cache is not None and key in self._cache:
            return self._cache[key]
        pose = nadir_camera_pose(pos)
        r = self._renderer.render(pose, self._rng_for(key[:2]))
        self.renders += 1
        view = make_view(r.rgb, pose, self.config.grid, self.config.intrinsics, r.person_mask,
                         self.config.min_cell_area_px, r.person_fraction, r.person_index,
                         nadir_view_geometry(self.config.grid, self.config.intrinsics, tuple(pos.tolist())))
        if self._cache is not None:
            self._cache[key] = view
        return view

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["View", "Vehicle", "TeleportVehicle", "make_view", "nadir_view_geometry"]

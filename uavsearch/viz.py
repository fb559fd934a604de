"""Pictures people look at: the grid drawn over a view, occupancy maps, scene overviews (PNG)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .errors import UavsearchError
from .geometry import CameraIntrinsics, Grid, cell_image_polygons
from .world.topdown import draw_topdown


def pyplot():
    """matplotlib.pyplot on the Agg backend (files, no display)."""
    # lazy: choosing the backend is process-wide, and pyplot costs ~1 s (shared machine); only drawing pays it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


OVERLAY_GRID_RGB = (255, 255, 0)  # draw_grid_overlay's cell outlines
OVERLAY_OCCUPIED_RGB = (255, 40, 40)  # and its ground-truth occupied cells (figures' keys name both)


def draw_grid_overlay(
    image: np.ndarray,
    pose,
    grid: Grid,
    intrinsics: CameraIntrinsics,
    occupancy: np.ndarray | None = None,
    scale: int = 3,
) -> np.ndarray:
    """Upscale a view and draw every cell's projected outline; ground-truth occupied cells in red."""
    big = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    polys = cell_image_polygons(grid, intrinsics, pose)
    shift = 4  # sub-pixel drawing precision (cv2 fixed point)
    for i, poly in enumerate(polys):
        if len(poly) < 3:
            continue
        pts = np.round(poly * scale * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)
        occupied = occupancy is not None and occupancy[i]
        color, thickness = (OVERLAY_OCCUPIED_RGB, 2) if occupied else (OVERLAY_GRID_RGB, 1)
        cv2.polylines(big, [pts], True, color, thickness, cv2.LINE_AA, shift)
    return big


def map_image(values: np.ndarray, grid: Grid) -> np.ndarray:
    """A (num_cells,) vector as the (N, N) north-up array matplotlib's imshow expects."""
    return np.asarray(values, dtype=float).reshape(grid.n, grid.n)


def overflow_in(fig) -> float:
    """How far (inches) anything drawn (titles, legends, axis labels, colour bars) reaches past the canvas:
    0 when it all fits. A figure rendered to a fixed canvas (video frames) loses whatever sticks out."""
    fig.canvas.draw()
    box = fig.get_tightbbox(fig.canvas.get_renderer())
    w, h = fig.get_size_inches()
    return float(max(0.0, -box.x0, -box.y0, box.x1 - w, box.y1 - h))


def settle_tight_layout(fig) -> None:
    """tight_layout for a fixed canvas, twice: the first pass places axes before an image's aspect shrinks
    them, which moves their labels; the second sees the labels where they end up."""
    fig.tight_layout()
    fig.canvas.draw()
    fig.tight_layout()


def save_figure(fig, out: str | Path) -> Path:
    """Save a matplotlib figure, turning an unwritable path into a one-line error."""
    out = Path(out)
    if out.parent and not out.parent.exists():
        raise UavsearchError(f"cannot write {out}: directory {out.parent} does not exist")
    try:
        fig.savefig(out, dpi=110, bbox_inches="tight")
    except OSError as e:
        raise UavsearchError(f"cannot write {out}: {e.strerror or e}") from None
    finally:
        pyplot().close(fig)
    return out


def scene_show_figure(spec, view, grid: Grid, intrinsics: CameraIntrinsics, out: str | Path) -> Path:
    """`uavsearch scene show`: scene_figure as a PNG."""
    return save_figure(scene_figure(spec, view, grid, intrinsics), out)


def scene_figure(spec, view, grid: Grid, intrinsics: CameraIntrinsics):
    """The start view with the grid and the occupied cells, beside a top-down map of the scene."""
    occ = spec.occupancy_array()
    fig, axes = pyplot().subplots(1, 2, figsize=(13, 6.5), layout="constrained")
    axes[0].imshow(draw_grid_overlay(view.image, view.pose, grid, intrinsics, occ))
    axes[0].set_title(
        f"start view at {view.position_enu[2]:.0f} m, {intrinsics.width_px}x{intrinsics.height_px} px, "
        f"{intrinsics.hfov_deg:.0f} deg FOV\n(grid in yellow, occupied cells in red)"
    )
    axes[0].axis("off")
    draw_topdown(spec, ax=axes[1])
    title = f"scene seed {spec.seed}: {int(occ.sum())} occupied cells of {grid.n} x {grid.n}"
    if spec.group_centres_m:
        title += (f" in {len(spec.group_centres_m)} groups\n(cyan: 1 and 2 sigma = {spec.placement.sigma_m:g} m "
                  "around each group centre)")  # fmt: skip
    axes[1].set_title(title)
    return fig

"""Top-down pictures of a scene: the painted ground (also the renderer's ground texture) and a map.

paint_ground draws roads, markings, sidewalks, grass, plazas and parking lots into a north-up RGB
raster with a little grain and a few stains, deterministically from the scene seed. draw_topdown adds
roofs, trees, cars, clutter, people (dots) and the grid with the occupied cells highlighted.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .scene import GROUND_KINDS, Raster, SceneObject, SceneSpec, footprint_corners

GROUND_TEXTURE_PX = 1536  # texels per side for the paper's 180 m city (+ rim): 13 cm a texel
GROUND_TEXTURE_REF_HALF_M = 100.0  # the half side that GROUND_TEXTURE_PX covers


def ground_raster(spec: SceneSpec, texture_px: int | None = None) -> Raster:
    """The square the ground texture covers: the city plus a 10 m rim; by default a larger city gets
    more texels (a multiple of 64), so its ground is as sharp as the paper's."""
    half = spec.params.city_half_m + 10.0
    if texture_px is None:
        texture_px = max(GROUND_TEXTURE_PX, 64 * math.ceil(GROUND_TEXTURE_PX * half / GROUND_TEXTURE_REF_HALF_M / 64))
    return Raster(half, 2 * half / texture_px)


def _stripes(o: SceneObject, width_m: float, period_m: float) -> list[np.ndarray]:
    """Stripes `width_m` long (along the rectangle's long axis) and as wide as the rectangle, every
    `period_m`: dashes of a centre line, zebra stripes, parking stall lines."""
    long_is_x = o.sx_m >= o.sy_m
    length = max(o.sx_m, o.sy_m)
    across = min(o.sx_m, o.sy_m)
    c, s = math.cos(o.yaw_rad), math.sin(o.yaw_rad)
    rot = np.array([[c, -s], [s, c]])
    out = []
    t = -length / 2 + (period_m - width_m) / 2
    while t + width_m <= length / 2 + 1e-9:
        a0, a1 = t, t + width_m
        rect = np.array([[a0, -across / 2], [a1, -across / 2], [a1, across / 2], [a0, across / 2]])
        if not long_is_x:
            rect = rect[:, ::-1]
        out.append(rect @ rot.T + [o.x_m, o.y_m])
        t += period_m
    return out


def paint_ground(spec: SceneSpec, raster: Raster | None = None, grain: bool = True) -> np.ndarray:
    """(n, n, 3) uint8 north-up RGB of the ground inside `raster` (default: the renderer's texture)."""
    raster = raster or ground_raster(spec)
    img = np.zeros((raster.n, raster.n, 3), np.uint8)
    rng = np.random.default_rng([spec.seed, 0x6A0])
    for o in spec.objects:
        if o.kind not in GROUND_KINDS:
            continue
        colour = tuple(int(v) for v in o.color)
        if o.kind == "base":
            img[:] = colour
        elif o.kind != "marking":
            raster.fill(img, footprint_corners(o), colour)
        elif o.variant == "dashed":
            for r in _stripes(o, 3.0, 6.0):
                raster.fill(img, r, colour)
        elif o.variant == "crosswalk":
            for r in _stripes(o, 0.5, 1.0):
                raster.fill(img, r, colour)
        elif o.variant.startswith("stalls"):
            for r in _stripes(o, 0.12, 2.6):
                raster.fill(img, r, colour)
        else:
            raster.fill(img, footprint_corners(o), colour)
    if grain:
        _stains(img, spec, raster, rng)
        noise = rng.normal(0.0, 5.0, (raster.n, raster.n, 1)).astype(np.float32)
        img = np.clip(img.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    return img


def _stains(img: np.ndarray, spec: SceneSpec, raster: Raster, rng: np.random.Generator) -> None:
    """Oil stains, manhole covers and worn patches on roads and pavements (dark blobs: confusers)."""
    paved = [o for o in spec.objects if o.kind in ("road", "sidewalk", "plaza", "parking")]
    if not paved:
        return
    area = sum(o.sx_m * o.sy_m for o in paved)
    for _ in range(int(area / 120.0)):
        o = paved[int(rng.integers(len(paved)))]
        x = o.x_m + rng.uniform(-0.5, 0.5) * o.sx_m
        y = o.y_m + rng.uniform(-0.5, 0.5) * o.sy_m
        kind = rng.random()
        if kind < 0.3:  # manhole
            raster.disk(img, (x, y), 0.35, (52, 52, 54))
        else:
            r = rng.uniform(0.25, 1.2)
            base = img[int(np.clip(raster.to_px((x, y))[1], 0, raster.n - 1)),
                       int(np.clip(raster.to_px((x, y))[0], 0, raster.n - 1))].astype(float)  # fmt: skip
            f = rng.uniform(0.6, 0.9) if kind < 0.85 else rng.uniform(1.08, 1.2)
            raster.disk(img, (x, y), r, tuple(int(min(255, c * f)) for c in base))


OCCUPIED_FILL_RGB, OCCUPIED_RGB = (255, 220, 0), (255, 200, 0)  # an occupied cell's fill and outline
PERSON_RGB, PERSON_OUTSIDE_RGB = (230, 0, 160), (255, 120, 0)  # a person in the grid's cells, and outside them
GROUP_RGB = (0, 220, 255)  # a clustered scene's group centre and its 1 and 2 sigma circles


def topdown_keys(spec: SceneSpec) -> list:
    """Legend handles of what draw_topdown draws, for a figure whose title does not say it."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    def rgb(c):
        return tuple(v / 255 for v in c)

    keys = [Patch(facecolor=rgb(OCCUPIED_FILL_RGB), edgecolor=rgb(OCCUPIED_RGB), alpha=0.8, label="occupied cell"),
            Line2D([], [], ls="", marker="o", ms=5, mfc=rgb(PERSON_RGB), mec="white", label="person")]
    if any(o.cell < 0 for o in spec.people):
        keys.append(Line2D([], [], ls="", marker="o", ms=5, mfc=rgb(PERSON_OUTSIDE_RGB), mec="white",
                           label="person outside the grid"))
    if spec.group_centres_m:
        keys.append(Line2D([], [], ls="", marker="o", ms=9, mfc="none", mec=rgb(GROUP_RGB), mew=2,
                           label=f"group: 1 and 2 sigma ({spec.placement.sigma_m:g} m)"))
    return keys


def draw_topdown(spec: SceneSpec, ax=None, half_m: float | None = None, m_per_px: float = 0.2):
    """A north-up map of the scene around the search area; draws into a matplotlib Axes (ENU metres)
    when `ax` is given, else returns the (n, n, 3) uint8 image."""
    half = half_m if half_m is not None else spec.grid.half_m + 20.0
    raster = Raster(half, m_per_px)
    img = paint_ground(spec, raster, grain=False)
    for o in spec.objects:
        if o.kind in ("building", "roof_unit", "car") or (o.kind == "clutter" and o.variant in ("kiosk", "fountain",
                                                                                                  "bench", "planter")):  # fmt: skip
            top = o.color2 if o.kind in ("building", "kiosk") or o.variant in ("kiosk", "fountain", "planter") else o.color
            if o.kind == "car":
                top = o.color
            raster.fill(img, footprint_corners(o), tuple(int(v) for v in (top or o.color)))
            pts = np.round(raster.to_px(footprint_corners(o)) * 16 - 8).astype(np.int32)
            if o.kind == "building":
                cv2.polylines(img, [pts], True, (40, 40, 40), 1, cv2.LINE_AA, 4)
        elif o.kind == "clutter":
            raster.disk(img, (o.x_m, o.y_m), max(o.sx_m, 0.3) / 2, tuple(int(v) for v in o.color))
    canopy = img.copy()
    for o in spec.objects_of("tree"):
        raster.disk(canopy, (o.x_m, o.y_m), o.sx_m / 2, tuple(int(v) for v in o.color))
    img = cv2.addWeighted(canopy, 0.7, img, 0.3, 0)
    # grid and occupied cells
    occ = spec.occupancy_array()
    grid = spec.grid
    overlay = img.copy()
    for i in np.flatnonzero(occ):
        raster.fill(overlay, grid.cell_corners_enu(int(i))[:, :2], OCCUPIED_FILL_RGB)
    img = cv2.addWeighted(overlay, 0.45, img, 0.55, 0)
    for k in range(grid.n + 1):
        a = -grid.half_m + k * grid.cell_m
        for p0, p1 in (((a, -grid.half_m), (a, grid.half_m)), ((-grid.half_m, a), (grid.half_m, a))):
            q0, q1 = (np.round(raster.to_px(np.array(p)) * 16 - 8).astype(int) for p in (p0, p1))
            cv2.line(img, tuple(int(v) for v in q0), tuple(int(v) for v in q1), (255, 255, 255), 1, cv2.LINE_AA, 4)
    grow = max(1.0, half / 45.0)  # a wider map is shown smaller: thicker outlines and dots keep it legible
    for i in np.flatnonzero(occ):
        pts = np.round(raster.to_px(grid.cell_corners_enu(int(i))[:, :2]) * 16 - 8).astype(np.int32)
        cv2.polylines(img, [pts], True, OCCUPIED_RGB, int(round(2 * grow)), cv2.LINE_AA, 4)
    for o in spec.people:
        raster.disk(img, (o.x_m, o.y_m), 0.55 * grow, (255, 255, 255))
        raster.disk(img, (o.x_m, o.y_m), 0.38 * grow, PERSON_RGB if o.cell >= 0 else PERSON_OUTSIDE_RGB)
    _draw_groups(img, spec, raster)
    if ax is None:
        return img
    ax.imshow(img, extent=[raster.centre[0] - half, raster.centre[0] + half, raster.centre[1] - half,
                           raster.centre[1] + half])  # fmt: skip
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    title = f"scene {spec.seed}: K={spec.occupied_cells_k} occupied cells (yellow), people (dots)"
    if spec.group_centres_m:
        title += f"\n{len(spec.group_centres_m)} groups (cyan: 1 and 2 sigma = {spec.placement.sigma_m:g} m around the centre)"
        for j, (x, y) in enumerate(spec.group_centres_m):
            ax.annotate(f"G{j + 1}", (x, y), xytext=(x + 1.5 * spec.placement.sigma_m, y + spec.placement.sigma_m),
                        color="black", fontsize=9, fontweight="bold",
                        bbox=dict(boxstyle="round,pad=0.2", fc=(0.0, 0.86, 1.0), ec="none"))  # fmt: skip
    ax.set_title(title)
    return ax


def _draw_groups(img: np.ndarray, spec: SceneSpec, raster: Raster) -> None:
    """Clustered scenes: each group centre (a cross) with circles at 1 and 2 sigma."""
    sigma = spec.placement.sigma_m
    for x, y in spec.group_centres_m:
        c = np.round(raster.to_px(np.array([x, y])) * 16 - 8).astype(int)
        centre = (int(c[0]), int(c[1]))
        for k, thick in ((1, 3), (2, 2)):
            cv2.circle(img, centre, int(round(k * sigma / raster.m_per_px * 16)), GROUP_RGB, thick, cv2.LINE_AA, 4)
        arm = int(round(1.5 / raster.m_per_px * 16))
        for d in ((arm, 0), (0, arm)):
            cv2.line(img, (centre[0] - d[0], centre[1] - d[1]), (centre[0] + d[0], centre[1] + d[1]), GROUP_RGB, 3,
                     cv2.LINE_AA, 4)  # fmt: skip


__all__ = ["paint_ground", "ground_raster", "draw_topdown", "topdown_keys", "GROUND_TEXTURE_PX"]

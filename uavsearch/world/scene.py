"""Procedural city scenes: a seed and K -> a JSON scene spec with every object and the ground-truth map.

The search area (the N x N grid, 50 m in the paper; any n and cell size) sits inside a larger city
(180 m by default, `SceneParams.city_half_m`) so edge views see city, not void. Streets run on a jittered grid with at least one street crossing the
search area each way; blocks become buildings (recursive lot split, varied heights, roof units),
parks, plazas or parking lots. People stand on walkable ground (sidewalks, plazas, parks, yards,
sometimes the road), never inside an obstacle, and exactly K grid cells hold at least one person:
a person's position (the point between the feet) lies at least `cell_margin_m` inside its cell, so
occupancy is never ambiguous. People outside the grid stand at least `outside_margin_m` away from it.

Which K cells are occupied is the `Placement`: "uniform" (the paper's) draws them independently,
weighted by walkable ground; "clustered" draws 1-3 groups around places people gather and each
occupied cell near one of them (Gaussian, sigma 7.5 m), so that where one person is, others are likely.

Everything is drawn from one numpy Generator seeded with the scene seed; coordinates are rounded to
millimetres so the JSON round trip is exact and the same seed gives byte-identical JSON.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..errors import SceneError
from ..geometry import GeodeticOrigin, Grid

GENERATOR_VERSION = "city-v1"

RGB = tuple[int, int, int]

# Ground kinds are painted into the ground texture in list order; the rest are 3-D bodies.
GROUND_KINDS = ("base", "block", "yard", "grass", "plaza", "path", "parking", "sidewalk", "road", "marking")
SOLID_KINDS = ("building", "roof_unit", "tree", "car", "clutter", "person")
Kind = Literal[
    "base", "block", "yard", "grass", "plaza", "path", "parking", "sidewalk", "road", "marking",
    "building", "roof_unit", "tree", "car", "clutter", "person",
]  # fmt: skip


class SceneParams(BaseModel):
    """Generator knobs (JSON-serialisable; stored in every scene so a spec documents how it was made)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    city_half_m: float = Field(90.0, description="half the side of the rendered city square")
    ground_half_m: float = Field(400.0, description="half the side of the plain ground beyond the city")
    block_pitch_m: tuple[float, float] = Field((36.0, 58.0), description="street centre-line spacing")
    road_width_m: tuple[float, float] = (7.0, 12.0)
    sidewalk_width_m: tuple[float, float] = (2.2, 4.5)
    block_type_probs: dict[str, float] = Field(
        default_factory=lambda: {"buildings": 0.6, "park": 0.15, "plaza": 0.15, "parking": 0.1}
    )
    lot_size_m: tuple[float, float] = Field((9.0, 24.0), description="building lots are split down to this size")
    empty_lot_prob: float = 0.18
    building_height_m: tuple[float, float] = (5.0, 32.0)
    street_tree_prob: float = Field(0.6, description="chance that a street side is lined with trees")
    street_tree_spacing_m: tuple[float, float] = (7.0, 13.0)
    tree_canopy_radius_m: tuple[float, float] = (1.8, 4.0)
    park_trees_per_100m2: float = 0.9
    parked_car_prob: float = Field(0.45, description="chance that a curb-side parking slot holds a car")
    moving_cars_per_100m: float = 0.8
    clutter_per_100m2_sidewalk: float = Field(2.2, description="bins, bollards, benches, cones, planters")
    lamp_spacing_m: tuple[float, float] = (18.0, 30.0)
    people_per_occupied_cell: tuple[int, int] = (1, 3)
    person_scale: tuple[float, float] = (0.88, 1.1)
    child_prob: float = 0.1
    background_people_per_100m2: float = Field(0.35, description="people outside the search area")
    surface_weight: dict[str, float] = Field(
        default_factory=lambda: {
            "sidewalk": 1.0, "plaza": 1.0, "path": 1.0, "grass": 0.45, "yard": 0.35,
            "parking": 0.35, "road": 0.2, "block": 0.3, "base": 0.1,
        },  # fmt: skip
        description="relative chance that a person stands on each ground kind",
    )
    shade_weight: float = Field(3.0, description="people prefer shade: weight multiplier under tree canopies and parasols")
    cell_margin_m: float = Field(0.35, description="a person's position lies at least this far inside its cell")
    outside_margin_m: float = 0.6
    person_clearance_m: float = Field(0.55, description="distance kept from obstacles and other people")


class Placement(BaseModel):
    """How the K occupied cells are drawn. Stored in a scene only when it is not the paper's uniform one,
    so the paper's scenes keep their bytes (a spec without it was made with the default)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["uniform", "clustered"] = "uniform"
    groups: tuple[int, int] = Field((1, 3), description="clustered: the number of groups is drawn in this range")
    sigma_m: float = Field(7.5, gt=0, description="clustered: spread of a group's cells around its centre")
    gather_weight: float = Field(4.0, ge=0, description="clustered: extra weight of plazas and street corners "
                                                        "as group centres, over plain walkable ground")  # fmt: skip
    corner_radius_m: float = Field(12.0, description="clustered: how far from a street crossing counts as its corner")


class SceneObject(BaseModel):
    """One object: a footprint rectangle (centre, size, yaw) extruded from z_m, with up to three colours.

    kind-specific meaning: building color2 = roof; tree sz = total height, sx/sy = canopy diameter,
    color2 = trunk; car color2 = windows; person color = shirt, color2 = trousers, color3 = skin,
    color4 = hair, variant = pose; clutter variant = bin|bollard|bench|cone|planter|lamp|parasol|fountain|kiosk;
    marking variant = dashed|solid|crosswalk|stalls.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Kind
    x_m: float
    y_m: float
    sx_m: float
    sy_m: float
    sz_m: float = 0.0
    z_m: float = 0.0
    yaw_rad: float = 0.0
    color: RGB
    color2: RGB | None = None
    color3: RGB | None = None
    color4: RGB | None = None
    variant: str = ""
    cell: int = Field(-1, description="person only: the grid cell it stands in, -1 outside the grid")
    group: int = Field(-1, description="person only, clustered placement: index of its group, -1 none")


class SceneSpec(BaseModel):
    """A whole scene: how it was generated and every object in it, plus the ground-truth occupancy."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    generator_version: str
    seed: int
    occupied_cells_k: int
    params: SceneParams
    grid: Grid
    home: GeodeticOrigin
    sun_azimuth_deg: float = 135.0
    sun_elevation_deg: float = 55.0
    objects: list[SceneObject]
    occupancy: list[int]
    placement: Placement = Field(default_factory=Placement)
    group_centres_m: list[tuple[float, float]] = Field(default_factory=list, description="clustered: (x, y) of each group")

    def occupancy_array(self) -> np.ndarray:
        return np.asarray(self.occupancy, dtype=np.int8)

    def objects_of(self, *kinds: str) -> list[SceneObject]:
        return [o for o in self.objects if o.kind in kinds]

    @property
    def people(self) -> list[SceneObject]:
        return self.objects_of("person")


# --------------------------------------------------------------------------------------------------
# Footprints and rasters (shared with the top-down map and the ground texture)


def footprint_corners(obj: SceneObject) -> np.ndarray:
    """(4, 2) ENU x/y corners of an object's footprint rectangle."""
    c, s = math.cos(obj.yaw_rad), math.sin(obj.yaw_rad)
    hx, hy = obj.sx_m / 2.0, obj.sy_m / 2.0
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + [obj.x_m, obj.y_m]


class Raster:
    """A north-up raster over a square of the ground: pixel (0, 0) is the north-west corner."""

    def __init__(self, half_m: float, m_per_px: float, centre=(0.0, 0.0)):
        self.half_m = half_m
        self.m_per_px = m_per_px
        self.centre = np.asarray(centre, dtype=float)
        self.n = int(round(2 * half_m / m_per_px))

    def to_px(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=float) - self.centre
        return np.stack([(xy[..., 0] + self.half_m) / self.m_per_px, (self.half_m - xy[..., 1]) / self.m_per_px], -1)

    def to_m(self, col, row) -> np.ndarray:
        x = (np.asarray(col) + 0.5) * self.m_per_px - self.half_m + self.centre[0]
        y = self.half_m - (np.asarray(row) + 0.5) * self.m_per_px + self.centre[1]
        return np.stack([x, y], -1)

    def fill(self, img: np.ndarray, corners_xy: np.ndarray, value) -> None:
        """Fill a convex polygon given in metres (sub-pixel accurate, 1/16 px)."""
        pts = np.round(self.to_px(corners_xy) * 16.0 - 8.0).astype(np.int32)  # pixel centres at +0.5
        cv2.fillConvexPoly(img, pts, value, lineType=cv2.LINE_8, shift=4)

    def disk(self, img: np.ndarray, xy, radius_m: float, value) -> None:
        c = np.round(self.to_px(xy) * 16.0 - 8.0).astype(np.int32)
        cv2.circle(img, (int(c[0]), int(c[1])), int(round(radius_m / self.m_per_px * 16.0)), value, -1, cv2.LINE_8, 4)


def obstacle_radius_m(obj: SceneObject) -> float | None:
    """People keep clear of solid objects; tree canopies do not block (people stand under them)."""
    if obj.kind == "tree":
        return 0.35  # the trunk
    if obj.kind == "clutter" and obj.variant in ("lamp", "parasol", "bollard"):
        return max(obj.sx_m, 0.25) / 2.0 + 0.1  # thin poles: the pole, not the parasol's disc
    return None


def obstacle_raster(objects: list[SceneObject], raster: Raster) -> np.ndarray:
    """uint8 raster, 1 where a person may not stand (buildings, cars, clutter, trunks, other people)."""
    occ = np.zeros((raster.n, raster.n), np.uint8)
    for o in objects:
        if o.kind in GROUND_KINDS or o.kind == "roof_unit":
            continue
        r = obstacle_radius_m(o)
        if o.kind == "person":
            raster.disk(occ, (o.x_m, o.y_m), 0.3, 1)
        elif r is not None:
            raster.disk(occ, (o.x_m, o.y_m), r, 1)
        else:
            raster.fill(occ, footprint_corners(o), 1)
    return occ


def surface_raster(objects: list[SceneObject], raster: Raster, weights: dict[str, float]) -> np.ndarray:
    """float32 raster of how likely a person stands on each ground pixel (painted in ground order)."""
    w = np.zeros((raster.n, raster.n), np.float32)
    for o in objects:
        if o.kind in GROUND_KINDS and o.kind != "marking":
            raster.fill(w, footprint_corners(o), float(weights.get(o.kind, 0.0)))
    return w


# --------------------------------------------------------------------------------------------------
# Colours

ASPHALT = [(72, 72, 76), (84, 83, 86), (62, 63, 66), (92, 90, 88)]
SIDEWALK = [(170, 166, 158), (186, 180, 170), (156, 152, 146), (178, 170, 156)]
PLAZA = [(196, 186, 168), (172, 160, 146), (206, 200, 190), (160, 150, 140)]
GRASS = [(86, 122, 62), (98, 132, 70), (78, 112, 58), (110, 128, 74)]
YARD = [(150, 144, 128), (120, 126, 96), (140, 132, 120)]
WALLS = [(196, 180, 160), (176, 160, 140), (150, 110, 90), (210, 206, 196), (120, 120, 126), (168, 90, 70),
         (224, 214, 180), (140, 150, 160), (100, 96, 92), (186, 150, 110)]  # fmt: skip
ROOFS = [(90, 90, 94), (120, 116, 110), (150, 80, 60), (60, 62, 66), (170, 170, 168), (110, 120, 90),
         (130, 100, 80), (200, 200, 198), (80, 70, 66)]  # fmt: skip
CARS = [(200, 200, 204), (30, 30, 34), (150, 150, 156), (160, 20, 24), (20, 50, 120), (230, 230, 226),
        (90, 96, 100), (200, 160, 20), (40, 90, 60), (120, 70, 40)]  # fmt: skip
SHIRTS = [(220, 40, 40), (240, 200, 40), (245, 245, 240), (40, 80, 200), (40, 150, 70), (230, 120, 30),
          (200, 60, 150), (25, 25, 30), (40, 44, 70), (90, 90, 96), (110, 80, 60), (60, 70, 60),
          (150, 146, 140), (80, 80, 84), (175, 168, 156), (120, 130, 90)]  # fmt: skip
TROUSERS = [(30, 34, 60), (25, 25, 28), (70, 70, 76), (110, 100, 80), (150, 140, 120), (50, 60, 90)]
SKIN = [(232, 196, 170), (200, 160, 120), (160, 110, 80), (110, 74, 50), (240, 210, 190)]
HAIR = [(30, 24, 20), (70, 50, 30), (120, 90, 50), (200, 180, 130), (140, 140, 140), (20, 20, 20)]
FOLIAGE = [(58, 96, 48), (70, 110, 52), (48, 84, 44), (84, 118, 60), (64, 90, 40)]


def _jitter(rng: np.random.Generator, base: RGB, amount: int = 10) -> RGB:
    return tuple(int(np.clip(c + rng.integers(-amount, amount + 1), 0, 255)) for c in base)


def _pick(rng: np.random.Generator, palette, amount: int = 10) -> RGB:
    return _jitter(rng, palette[int(rng.integers(len(palette)))], amount)


# --------------------------------------------------------------------------------------------------
# Generation


def _r(v: float) -> float:
    """Round to the millimetre so JSON is short and round trips exactly."""
    return float(round(float(v), 3)) + 0.0


class _Builder:
    """Collects objects while the layout is generated (one Generator, fixed call order)."""

    def __init__(self, rng: np.random.Generator, p: SceneParams):
        self.rng = rng
        self.p = p
        self.ground: list[SceneObject] = []
        self.solids: list[SceneObject] = []

    def add(self, kind: str, x, y, sx, sy, sz=0.0, z=0.0, yaw=0.0, **kw) -> SceneObject:
        o = SceneObject(kind=kind, x_m=_r(x), y_m=_r(y), sx_m=_r(sx), sy_m=_r(sy), sz_m=_r(sz), z_m=_r(z),
                        yaw_rad=_r(yaw), **kw)  # fmt: skip
        (self.ground if kind in GROUND_KINDS else self.solids).append(o)
        return o

    def rect(self, kind: str, x0, y0, x1, y1, **kw) -> SceneObject:
        return self.add(kind, (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, **kw)


def _street_lines(rng: np.random.Generator, p: SceneParams) -> list[tuple[float, float, float]]:
    """(centre, road width, sidewalk width) of parallel streets; one crosses the middle of the search area."""
    c0 = rng.uniform(-18.0, 18.0)
    centres = [c0]
    x = c0
    while x < p.city_half_m + p.block_pitch_m[1]:
        x += rng.uniform(*p.block_pitch_m)
        centres.append(x)
    x = c0
    while x > -p.city_half_m - p.block_pitch_m[1]:
        x -= rng.uniform(*p.block_pitch_m)
        centres.append(x)
    centres.sort()
    return [(c, rng.uniform(*p.road_width_m), rng.uniform(*p.sidewalk_width_m)) for c in centres]


def _layout_streets(b: _Builder, xs, ys) -> None:
    rng, h = b.rng, b.p.city_half_m
    for vertical, lines in ((True, xs), (False, ys)):
        for c, road, side in lines:
            w = road + 2 * side
            if vertical:
                b.rect("sidewalk", c - w / 2, -h, c + w / 2, h, color=_pick(rng, SIDEWALK, 6))
            else:
                b.rect("sidewalk", -h, c - w / 2, h, c + w / 2, color=_pick(rng, SIDEWALK, 6))
    asphalt = _pick(rng, ASPHALT, 4)
    for vertical, lines in ((True, xs), (False, ys)):
        for c, road, side in lines:
            if vertical:
                b.rect("road", c - road / 2, -h, c + road / 2, h, color=asphalt)
            else:
                b.rect("road", -h, c - road / 2, h, c + road / 2, color=asphalt)
    # Markings: centre lines between intersections, crosswalks at each intersection approach.
    white, yellow = (228, 228, 220), (220, 190, 60)
    centre_colour = white if rng.random() < 0.6 else yellow
    for vertical, lines, cross in ((True, xs, ys), (False, ys, xs)):
        for c, road, side in lines:
            stops = sorted([-h] + [cc for cc, *_ in cross if -h < cc < h] + [h])
            for a, bnd in zip(stops[:-1], stops[1:]):
                half_a = next((r / 2 + s for cc, r, s in cross if cc == a), 0.0)
                half_b = next((r / 2 + s for cc, r, s in cross if cc == bnd), 0.0)
                s0, s1 = a + half_a + 3.5, bnd - half_b - 3.5
                if s1 - s0 < 4:
                    continue
                variant = "dashed" if road < 10.5 else "solid"
                if vertical:
                    b.rect("marking", c - 0.08, s0, c + 0.08, s1, color=centre_colour, variant=variant)
                else:
                    b.rect("marking", s0, c - 0.08, s1, c + 0.08, color=centre_colour, variant=variant)
                for s_edge, sign in ((a + half_a, 1), (bnd - half_b, -1)):
                    if not -h < s_edge < h or rng.random() > 0.7:
                        continue
                    lo, hi = sorted((s_edge + sign * 0.4, s_edge + sign * 3.4))
                    if vertical:
                        b.rect("marking", c - road / 2, lo, c + road / 2, hi, color=white, variant="crosswalk")
                    else:
                        b.rect("marking", lo, c - road / 2, hi, c + road / 2, color=white, variant="crosswalk",
                               yaw=0.0)  # fmt: skip


def _street_furniture(b: _Builder, xs, ys) -> None:
    """Trees, lamps, parked and moving cars, and clutter along every street side."""
    p, rng, h = b.p, b.rng, b.p.city_half_m
    for vertical, lines, cross in ((True, xs, ys), (False, ys, xs)):
        for c, road, side in lines:
            gaps = [(cc - r / 2 - s - 1.0, cc + r / 2 + s + 1.0) for cc, r, s in cross]

            def free(s, half_len=0.0):
                return -h + 1 < s < h - 1 and all(not (g0 - half_len < s < g1 + half_len) for g0, g1 in gaps)

            for sign in (-1, 1):
                curb = c + sign * road / 2
                # trees near the curb
                if rng.random() < p.street_tree_prob:
                    s = -h + rng.uniform(0, 6)
                    species = rng.integers(len(FOLIAGE))
                    while s < h:
                        if free(s, 1.0):
                            _tree(b, *(_xy(vertical, curb + sign * min(1.1, side * 0.4), s)), species=species)
                        s += rng.uniform(*p.street_tree_spacing_m)
                # lamps at the outer edge of the sidewalk
                s = -h + rng.uniform(0, 10)
                while s < h:
                    if free(s):
                        x, y = _xy(vertical, curb + sign * 0.45, s)
                        b.add("clutter", x, y, 0.18, 0.18, 6.5, variant="lamp", color=(60, 62, 66))
                    s += rng.uniform(*p.lamp_spacing_m)
                # parked cars along the curb
                s = -h + rng.uniform(0, 5)
                while s < h:
                    length = rng.uniform(4.0, 5.2)
                    if free(s, length / 2) and rng.random() < p.parked_car_prob:
                        x, y = _xy(vertical, curb - sign * 1.15, s)
                        _car(b, x, y, length, vertical)
                    s += length + rng.uniform(0.8, 2.5)
                # clutter on the sidewalk
                n = rng.poisson(p.clutter_per_100m2_sidewalk * side * 2 * h / 100.0)
                for _ in range(n):
                    s = rng.uniform(-h, h)
                    if free(s):
                        off = curb + sign * rng.uniform(0.5, side - 0.3)
                        _clutter(b, *_xy(vertical, off, s), rng.choice(["bin", "bollard", "bench", "cone", "planter"],
                                                                      p=[0.35, 0.3, 0.15, 0.08, 0.12]),
                                 vertical)  # fmt: skip
            # moving cars in the lanes
            for _ in range(rng.poisson(p.moving_cars_per_100m * 2 * h / 100.0)):
                s = rng.uniform(-h, h)
                lane = c + rng.choice([-1, 1]) * road / 4
                if free(s, 3.0) and road > 8:
                    _car(b, *_xy(vertical, lane, s), rng.uniform(4.0, 5.0), vertical)


def _xy(vertical: bool, across: float, along: float) -> tuple[float, float]:
    return (across, along) if vertical else (along, across)


def _tree(b: _Builder, x, y, species=None, scale=1.0) -> None:
    rng = b.rng
    radius = rng.uniform(*b.p.tree_canopy_radius_m) * scale
    height = radius * rng.uniform(1.6, 2.6) + rng.uniform(1.5, 3.0)
    leaf = FOLIAGE[int(species if species is not None else rng.integers(len(FOLIAGE)))]
    b.add("tree", x, y, 2 * radius, 2 * radius * rng.uniform(0.85, 1.0), height, yaw=rng.uniform(0, math.pi),
          color=_jitter(rng, leaf, 12), color2=(84, 66, 50))  # fmt: skip


def _car(b: _Builder, x, y, length, vertical: bool) -> None:
    rng = b.rng
    yaw = (math.pi / 2 if vertical else 0.0) + (math.pi if rng.random() < 0.5 else 0.0) + rng.normal(0, 0.03)
    van = rng.random() < 0.15
    b.add("car", x, y, length * (1.15 if van else 1.0), rng.uniform(1.75, 1.95), rng.uniform(2.0, 2.4) if van else
          rng.uniform(1.35, 1.55), yaw=yaw, color=_pick(rng, CARS, 12), color2=(34, 40, 48),
          variant="van" if van else "car")  # fmt: skip


def _clutter(b: _Builder, x, y, variant: str, vertical: bool) -> None:
    rng = b.rng
    yaw = (math.pi / 2 if vertical else 0.0) + rng.normal(0, 0.05)
    if variant == "bin":
        d = rng.uniform(0.5, 0.7)
        colour = _pick(rng, [(40, 70, 50), (30, 30, 32), (90, 90, 96), (60, 60, 120), (150, 120, 40)])
        b.add("clutter", x, y, d, d, rng.uniform(0.9, 1.1), yaw=yaw, color=colour, variant="bin")
    elif variant == "bollard":
        d = rng.uniform(0.18, 0.3)
        b.add("clutter", x, y, d, d, rng.uniform(0.8, 1.0), color=_pick(rng, [(40, 40, 44), (120, 120, 126),
                                                                               (150, 40, 40)]), variant="bollard")  # fmt: skip
    elif variant == "bench":
        b.add("clutter", x, y, rng.uniform(1.5, 2.0), 0.55, 0.5, yaw=yaw,
              color=_pick(rng, [(120, 86, 56), (70, 70, 74), (140, 110, 80)]), variant="bench")  # fmt: skip
    elif variant == "cone":
        b.add("clutter", x, y, 0.36, 0.36, 0.7, color=(236, 110, 30), variant="cone")
    elif variant == "planter":
        s = rng.uniform(0.9, 1.6)
        b.add("clutter", x, y, s, s, rng.uniform(0.5, 0.8), yaw=yaw, color=(150, 146, 140),
              color2=_pick(rng, FOLIAGE, 15), variant="planter")  # fmt: skip


def _split_lots(rng, x0, y0, x1, y1, lo, hi, out) -> None:
    w, hgt = x1 - x0, y1 - y0
    if max(w, hgt) <= hi or (max(w, hgt) < 2 * lo):
        out.append((x0, y0, x1, y1))
        return
    if w >= hgt:
        s = rng.uniform(x0 + lo, x1 - lo)
        _split_lots(rng, x0, y0, s, y1, lo, hi, out)
        _split_lots(rng, s, y0, x1, y1, lo, hi, out)
    else:
        s = rng.uniform(y0 + lo, y1 - lo)
        _split_lots(rng, x0, y0, x1, s, lo, hi, out)
        _split_lots(rng, x0, s, x1, y1, lo, hi, out)


def _block(b: _Builder, x0, y0, x1, y1) -> None:
    p, rng = b.p, b.rng
    types = list(p.block_type_probs)
    probs = np.array([p.block_type_probs[t] for t in types], float)
    kind = types[int(rng.choice(len(types), p=probs / probs.sum()))]
    w, hgt = x1 - x0, y1 - y0
    if kind == "buildings":
        b.rect("block", x0, y0, x1, y1, color=_pick(rng, YARD, 8))
        lots: list = []
        _split_lots(rng, x0, y0, x1, y1, p.lot_size_m[0], p.lot_size_m[1], lots)
        for lx0, ly0, lx1, ly1 in lots:
            if rng.random() < p.empty_lot_prob:
                b.rect(rng.choice(["yard", "grass"]), lx0, ly0, lx1, ly1,
                       color=_pick(rng, YARD if rng.random() < 0.5 else GRASS, 8))  # fmt: skip
                if rng.random() < 0.5:
                    _tree(b, rng.uniform(lx0 + 2, lx1 - 2), rng.uniform(ly0 + 2, ly1 - 2))
                continue
            inset = [rng.uniform(0, 2.0) if rng.random() < 0.4 else 0.2 for _ in range(4)]
            bx0, by0, bx1, by1 = lx0 + inset[0], ly0 + inset[1], lx1 - inset[2], ly1 - inset[3]
            if bx1 - bx0 < 4 or by1 - by0 < 4:
                continue
            height = float(np.clip(rng.lognormal(math.log(12.0), 0.45), *p.building_height_m))
            bld = b.rect("building", bx0, by0, bx1, by1, sz=height, color=_pick(rng, WALLS, 10),
                         color2=_pick(rng, ROOFS, 8))  # fmt: skip
            for _ in range(rng.integers(0, 4)):
                s = rng.uniform(0.8, 2.6)
                if bld.sx_m > s + 1 and bld.sy_m > s + 1:
                    b.add("roof_unit", rng.uniform(bx0 + s / 2 + 0.3, bx1 - s / 2 - 0.3),
                          rng.uniform(by0 + s / 2 + 0.3, by1 - s / 2 - 0.3), s, s * rng.uniform(0.5, 1.2),
                          rng.uniform(0.6, 2.2), z=height, color=_pick(rng, [(180, 180, 184), (120, 120, 124),
                                                                             (90, 88, 86)], 10))  # fmt: skip
    elif kind == "park":
        b.rect("grass", x0, y0, x1, y1, color=_pick(rng, GRASS, 6))
        path_colour = _pick(rng, PLAZA, 8)
        pw = rng.uniform(2.0, 3.5)
        cx, cy = rng.uniform(x0 + 0.3 * w, x1 - 0.3 * w), rng.uniform(y0 + 0.3 * hgt, y1 - 0.3 * hgt)
        b.rect("path", cx - pw / 2, y0, cx + pw / 2, y1, color=path_colour)
        b.rect("path", x0, cy - pw / 2, x1, cy + pw / 2, color=path_colour)
        for _ in range(rng.poisson(p.park_trees_per_100m2 * w * hgt / 100.0)):
            tx, ty = rng.uniform(x0 + 1.5, x1 - 1.5), rng.uniform(y0 + 1.5, y1 - 1.5)
            if abs(tx - cx) > pw and abs(ty - cy) > pw:
                _tree(b, tx, ty, scale=rng.uniform(0.8, 1.3))
        for _ in range(rng.poisson(0.2 * (w + hgt))):
            along_x = rng.random() < 0.5
            t = rng.uniform(x0 + 1, x1 - 1) if along_x else rng.uniform(y0 + 1, y1 - 1)
            off = rng.choice([-1, 1]) * (pw / 2 + 0.6)
            xy = (t, cy + off) if along_x else (cx + off, t)
            _clutter(b, *xy, "bench" if rng.random() < 0.7 else "bin", not along_x)
    elif kind == "plaza":
        b.rect("plaza", x0, y0, x1, y1, color=_pick(rng, PLAZA, 6))
        cx, cy = (x0 + x1) / 2 + rng.uniform(-0.2, 0.2) * w, (y0 + y1) / 2 + rng.uniform(-0.2, 0.2) * hgt
        if rng.random() < 0.5:
            d = rng.uniform(3.0, 6.0)
            b.add("clutter", cx, cy, d, d, 0.6, color=(170, 170, 172), color2=(70, 110, 150), variant="fountain")
        spacing = rng.uniform(7, 11)
        for tx in np.arange(x0 + 3, x1 - 2, spacing):
            for ty in (y0 + 3, y1 - 3):
                if rng.random() < 0.7:
                    _tree(b, tx, ty, scale=0.8)
        for _ in range(rng.poisson(0.015 * w * hgt)):
            v = rng.choice(["bench", "planter", "bin", "bollard", "parasol", "kiosk"], p=[0.3, 0.2, 0.15, 0.15, 0.15, 0.05])
            x, y = rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2)
            if math.hypot(x - cx, y - cy) < 4:
                continue
            if v == "parasol":
                d = rng.uniform(2.2, 3.2)
                b.add("clutter", x, y, d, d, 2.4, color=_pick(rng, SHIRTS[:7], 10), variant="parasol")
            elif v == "kiosk":
                b.add("clutter", x, y, 3.0, 2.5, 3.0, yaw=rng.uniform(0, math.pi), color=_pick(rng, WALLS),
                      color2=_pick(rng, ROOFS), variant="kiosk")  # fmt: skip
            else:
                _clutter(b, x, y, v, rng.random() < 0.5)
    else:  # parking
        b.rect("parking", x0, y0, x1, y1, color=_pick(rng, ASPHALT, 6))
        vertical_rows = w < hgt
        row_len = hgt if vertical_rows else w
        rows = np.arange((x0 if vertical_rows else y0) + 3.0, (x1 if vertical_rows else y1) - 2.5, 6.5)
        for r in rows:
            b.rect("marking", *((r - 2.5, y0 + 1, r + 2.5, y1 - 1) if vertical_rows else (x0 + 1, r - 2.5, x1 - 1,
                                                                                           r + 2.5)),
                   color=(220, 220, 214), variant="stalls_x" if vertical_rows else "stalls_y")  # fmt: skip
            for s in np.arange(1.0 + 1.3, row_len - 2.0, 2.6):
                if rng.random() < 0.55:
                    along = (y0 if vertical_rows else x0) + s
                    x, y = (r, along) if vertical_rows else (along, r)
                    yaw = (0.0 if vertical_rows else math.pi / 2) + (math.pi if rng.random() < 0.5 else 0)
                    b.add("car", x, y, rng.uniform(4.0, 4.8), rng.uniform(1.75, 1.9), rng.uniform(1.35, 1.55),
                          yaw=yaw + rng.normal(0, 0.04), color=_pick(rng, CARS, 12), color2=(34, 40, 48),
                          variant="car")  # fmt: skip


def _person(b: _Builder, x, y, cell: int, group: int = -1) -> None:
    rng, p = b.rng, b.p
    child = rng.random() < p.child_prob
    scale = rng.uniform(0.6, 0.75) if child else rng.uniform(*p.person_scale)
    pose = str(rng.choice(["standing", "walking", "crouching"], p=[0.45, 0.45, 0.1]))
    height = 1.75 * scale * (0.65 if pose == "crouching" else 1.0)
    b.add("person", x, y, 0.5 * scale, 0.3 * scale, height, yaw=rng.uniform(-math.pi, math.pi),
          color=_pick(rng, SHIRTS, 12), color2=_pick(rng, TROUSERS, 10), color3=_pick(rng, SKIN, 8),
          color4=_pick(rng, HAIR, 8), variant=pose, cell=cell, group=group)  # fmt: skip


def _sample_point(rng, weights: np.ndarray, raster: Raster) -> tuple[float, float]:
    """A point drawn by weight: a pixel (by the running sum of the positive weights in row-major order), then a
    uniform offset within it."""
    return _PointSampler(weights, raster).draw(rng)


class _PointSampler:
    """_sample_point's running sum, kept between draws.

    `origin` (row, col): `weights` is the box of a larger raster starting at that pixel, holding every positive
    weight of it (the same positive weights in the same order, so the same draw from a smaller array).
    `rows_changed`: the weights (a whole raster, written in place) lost positive pixels (zeroed where a drawn
    person now stands). A pixel that left keeps its place in the sum with weight 0 (never drawn: the sum does
    not rise there) and the sum is taken again from the first such pixel, on from the kept sum before it: the
    sums at the pixels still positive are those _sample_point would take on the weights as they are then, so
    every draw is the same."""

    def __init__(self, weights: np.ndarray, raster: Raster, origin: tuple[int, int] = (0, 0)):
        self.raster, self.origin, self.width = raster, origin, weights.shape[1]
        self.flat = weights.reshape(-1)  # a view of a contiguous array: in-place writes show through
        self.nz = np.flatnonzero(self.flat > 0)
        self.cum = np.cumsum(self.flat[self.nz], dtype=np.float64)
        self.alive = np.ones(len(self.nz), dtype=bool)

    def draw(self, rng) -> tuple[float, float]:
        cum, nz = self.cum, self.nz
        k = min(int(np.searchsorted(cum, rng.uniform(0.0, cum[-1]), side="right")), len(nz) - 1)
        while self.flat[nz[k]] <= 0:  # only where the draw hit the very top of the sum: the last pixel still in
            k -= 1
        row, col = divmod(int(nz[k]), self.width)
        r0, c0 = self.origin
        xy = self.raster.to_m(c0 + col + rng.uniform(-0.5, 0.5), r0 + row + rng.uniform(-0.5, 0.5))
        return float(xy[0]), float(xy[1])

    def rows_changed(self, row_lo: int, row_hi: int) -> None:
        """Pixels of rows [row_lo, row_hi) may have dropped to zero."""
        lo, hi = np.searchsorted(self.nz, [max(row_lo, 0) * self.width, max(row_hi, 0) * self.width])
        left = self.flat[self.nz[lo:hi]] <= 0
        gone = np.flatnonzero(left & self.alive[lo:hi])
        if len(gone) == 0:
            return
        self.alive[lo:hi] &= ~left
        j = lo + int(gone[0])  # the first pixel that left now: the sums before it stand
        start = self.cum[j - 1:j] if j > 0 else np.zeros(1)
        self.cum[j:] = np.cumsum(np.concatenate([start, self.flat[self.nz[j:]]]))[1:]


def _mask_box(mask: np.ndarray) -> tuple[slice, slice]:
    """The bounding box (rows, cols) of a mask's True pixels (it has some)."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def generate_scene(
    seed: int,
    occupied_cells: int,
    params: SceneParams | None = None,
    grid: Grid | None = None,
    placement: Placement | None = None,
) -> SceneSpec:
    """A city scene in which exactly `occupied_cells` cells of `grid` (default: the paper's 10 x 10 of
    5 m) hold at least one person, drawn as `placement` says (default: uniform, the paper's)."""
    p = params or SceneParams()
    grid = grid or Grid()
    placement = placement or Placement()
    try:
        seed = int(seed)
        k = int(occupied_cells)
    except (TypeError, ValueError) as e:
        raise SceneError(f"scene seed and occupied cells must be integers: {e}") from None
    if seed < 0:
        raise SceneError(f"scene seed must be >= 0, got {seed}")
    if not 0 <= k <= grid.num_cells:
        raise SceneError(f"occupied cells K={k} out of range: 0 <= K <= {grid.num_cells}")
    if grid.n < 1 or grid.cell_m <= 2 * p.cell_margin_m or grid.half_m + p.outside_margin_m > p.city_half_m:
        raise SceneError(f"a {grid.n} x {grid.n} grid of {grid.cell_m:g} m cells does not fit a city of "
                         f"{2 * p.city_half_m:g} m (cells must be wider than 2 x {p.cell_margin_m:g} m)")  # fmt: skip
    lo_g, hi_g = placement.groups
    if placement.kind == "clustered" and not 1 <= lo_g <= hi_g:
        raise SceneError(f"clustered placement needs 1 <= groups[0] <= groups[1], got {lo_g}, {hi_g}")
    rng = np.random.default_rng([seed, 0x5CE4E])
    b = _Builder(rng, p)
    h = p.city_half_m
    b.rect("base", -p.ground_half_m, -p.ground_half_m, p.ground_half_m, p.ground_half_m, color=_pick(rng, GRASS, 4))
    xs, ys = _street_lines(rng, p), _street_lines(rng, p)
    # Blocks between consecutive streets, clipped to the city.
    edges_x = [(-h - 60, -h - 60)] + [(c - r / 2 - s, c + r / 2 + s) for c, r, s in xs] + [(h + 60, h + 60)]
    edges_y = [(-h - 60, -h - 60)] + [(c - r / 2 - s, c + r / 2 + s) for c, r, s in ys] + [(h + 60, h + 60)]
    for (_, ax1), (bx0, _) in zip(edges_x[:-1], edges_x[1:]):
        for (_, ay1), (by0, _) in zip(edges_y[:-1], edges_y[1:]):
            x0, x1, y0, y1 = max(ax1, -h), min(bx0, h), max(ay1, -h), min(by0, h)
            if x1 - x0 > 6 and y1 - y0 > 6:
                _block(b, x0, y0, x1, y1)
    _layout_streets(b, xs, ys)
    _street_furniture(b, xs, ys)

    # People: exactly K occupied cells inside the grid, background people outside it.
    weights = p.surface_weight
    raster = Raster(h, 0.2)
    surface = surface_raster(b.ground, raster, weights)
    shade = np.zeros_like(surface, dtype=np.uint8)
    for o in b.solids:
        if o.kind == "tree" or (o.kind == "clutter" and o.variant == "parasol"):
            raster.disk(shade, (o.x_m, o.y_m), 0.45 * (o.sx_m + o.sy_m) / 2, 1)
    surface = np.where(shade > 0, surface * p.shade_weight, surface).astype(np.float32)
    cell_w, ok = _make_room(b, grid, raster, surface, k)
    if placement.kind == "clustered":
        gather = _gather_weight(b, raster, surface, xs, ys, placement)
        occupied, group_of, centres = _clustered_cells(rng, grid, raster, gather, cell_w, ok, k, placement)
    else:
        occupied, group_of, centres = _uniform_cells(rng, grid, cell_w, ok, k), {}, []
    blocked = obstacle_raster(b.solids, raster)
    cell_img = _cell_raster(grid, raster, p.cell_margin_m)
    obstacles_only = _free(blocked, raster, p.person_clearance_m)
    lo, hi = p.people_per_occupied_cell
    extra = {cell: int(rng.integers(lo, hi + 1)) - 1 for cell in occupied}
    # One person per occupied cell first (so every chosen cell is occupied), then the extra ones.
    for cell in occupied + [c for c in occupied for _ in range(extra[c])]:
        box = _mask_box(cell_img == cell)  # the cell's pixels: its weights drawn from as from the whole raster
        in_cell = cell_img[box] == cell
        w = np.where(in_cell & _free(blocked, raster, p.person_clearance_m)[box], surface[box], 0.0)
        if w.sum() <= 0:
            if any(o.kind == "person" and o.cell == cell for o in b.solids):
                continue  # no room left for an extra person
            w = np.where(in_cell & obstacles_only[box], surface[box], 0.0)  # crowded: may stand close to someone
        x, y = _PointSampler(np.ascontiguousarray(w), raster, (box[0].start, box[1].start)).draw(rng)
        _person(b, x, y, cell, group_of.get(cell, -1))
        raster.disk(blocked, (x, y), 0.3, 1)
    outside = _cell_raster(grid, raster, -p.outside_margin_m) < -1  # outside the grid grown by the margin
    walk_area_m2 = float((surface > 0)[outside].sum()) * raster.m_per_px**2
    free = _free(blocked, raster, p.person_clearance_m)
    wout = np.where(outside & free, surface, 0.0)
    sampler = _PointSampler(wout, raster)
    radius_m = p.person_clearance_m + 0.3
    reach = radius_m / raster.m_per_px + 2.0  # the disk's rows, with room for its sub-pixel rounding
    for _ in range(rng.poisson(p.background_people_per_100m2 * walk_area_m2 / 100.0 * 0.5)):
        x, y = sampler.draw(rng)
        _person(b, x, y, -1)
        raster.disk(wout, (x, y), radius_m, 0.0)
        row = float(raster.to_px((x, y))[1])
        sampler.rows_changed(int(math.floor(row - reach)), int(math.ceil(row + reach)) + 1)

    occ = np.zeros(grid.num_cells, np.int8)
    for o in b.solids:
        if o.kind == "person" and o.cell >= 0:
            occ[o.cell] = 1
    if int(occ.sum()) != k:  # a generator bug, not bad input
        raise AssertionError(f"scene {seed}: {int(occ.sum())} occupied cells instead of {k}")
    sun_az = float(rng.uniform(0, 360))
    sun_el = float(rng.uniform(35, 75))
    return SceneSpec(
        generator_version=GENERATOR_VERSION, seed=seed, occupied_cells_k=k, params=p, grid=grid,
        home=GeodeticOrigin(), sun_azimuth_deg=_r(sun_az), sun_elevation_deg=_r(sun_el),
        objects=b.ground + b.solids, occupancy=[int(v) for v in occ], placement=placement,
        group_centres_m=[(_r(x), _r(y)) for x, y in centres],
    )  # fmt: skip


def _cell_raster(grid: Grid, raster: Raster, margin_m: float) -> np.ndarray:
    """int16 raster of cell indices (-1 outside); a positive margin shrinks every cell, a negative one
    grows the grid (then -1 marks the grown border and -2 the outside)."""
    line = raster.to_m(np.arange(raster.n), np.arange(raster.n))  # a pixel's x depends on its column only, y on
    x, y = line[:, 0][None, :], line[:, 1][:, None]  # its row: one row and one column, broadcast (the same floats)
    if margin_m >= 0:
        idx = grid.cell_of_points(x, y)
        fx = np.mod(x + grid.half_m, grid.cell_m)
        fy = np.mod(y + grid.half_m, grid.cell_m)
        inner = (fx >= margin_m) & (fx <= grid.cell_m - margin_m) & (fy >= margin_m) & (fy <= grid.cell_m - margin_m)
        return np.where(inner, idx, -1).astype(np.int16)
    grown = (np.abs(x) <= grid.half_m - margin_m) & (np.abs(y) <= grid.half_m - margin_m)
    return np.where(grown, -1, -2).astype(np.int16)


def _free(blocked: np.ndarray, raster: Raster, clearance_m: float) -> np.ndarray:
    r = max(1, int(round(clearance_m / raster.m_per_px)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(blocked, kernel) == 0


def _box(o: SceneObject) -> tuple[np.ndarray, np.ndarray]:
    fc = footprint_corners(o)
    return fc.min(0), fc.max(0)


def _overlaps(o: SceneObject, lo, hi) -> bool:
    a, b = _box(o)
    return bool(np.all(b > lo) and np.all(a < hi))


def _make_room(b: _Builder, grid: Grid, raster: Raster, surface: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per cell, the walkable weight where a person has room, and which cells have any; clears obstacles
    when fewer than K cells have room."""
    p, rng = b.p, b.rng
    cell_img = _cell_raster(grid, raster, p.cell_margin_m)
    order = rng.permutation(grid.num_cells)
    while True:
        free = _free(obstacle_raster(b.solids, raster), raster, p.person_clearance_m)
        w = np.where(free & (cell_img >= 0), surface, 0.0)
        cell_w = np.bincount(cell_img[cell_img >= 0], weights=w[cell_img >= 0], minlength=grid.num_cells)
        ok = cell_w > 0
        if ok.sum() >= k:
            return cell_w, ok
        # Too crowded for K: demolish everything solid in the next full cell (deterministic order).
        target = next(int(c) for c in order if not ok[c])
        corners = grid.cell_corners_enu(target)[:, :2]
        lo, hi = corners.min(0) - 1.0, corners.max(0) + 1.0
        removed = [o for o in b.solids if o.kind not in ("person", "roof_unit") and _overlaps(o, lo, hi)]
        gone = {id(o) for o in removed}
        for o in b.solids:  # roof units go with their building
            if o.kind == "roof_unit" and any(s.kind == "building" and _overlaps(o, *_box(s)) for s in removed):
                gone.add(id(o))
        b.solids = [o for o in b.solids if id(o) not in gone]


def _uniform_cells(rng, grid: Grid, cell_w: np.ndarray, ok: np.ndarray, k: int) -> list[int]:
    """The paper's placement: K cells with room, drawn independently by walkable weight."""
    if k == 0:
        return []
    prob = cell_w / cell_w.sum()
    chosen = rng.choice(grid.num_cells, size=k, replace=False, p=np.where(ok, np.maximum(prob, 1e-9), 0.0) /
                        np.where(ok, np.maximum(prob, 1e-9), 0.0).sum())  # fmt: skip
    return sorted(int(c) for c in chosen)


def _gather_weight(b: _Builder, raster: Raster, surface: np.ndarray, xs, ys, pl: Placement) -> np.ndarray:
    """Where groups gather: walkable ground (the people weights), `gather_weight` times more on plazas and
    within `corner_radius_m` of a street crossing (its sidewalk corners, crosswalks and the curb)."""
    plaza = surface_raster(b.ground, raster, {"plaza": 1.0}) > 0  # visible plaza: painted over by nothing
    corner = np.zeros(surface.shape, np.uint8)
    for cx, *_ in xs:
        for cy, *_ in ys:
            raster.disk(corner, (cx, cy), pl.corner_radius_m, 1)
    return surface * (1.0 + pl.gather_weight * (plaza | (corner > 0)))


def _clustered_cells(rng, grid: Grid, raster: Raster, gather: np.ndarray, cell_w: np.ndarray, ok: np.ndarray,
                     k: int, pl: Placement) -> tuple[list[int], dict[int, int], list[tuple[float, float]]]:  # fmt: skip
    """K cells in groups: group centres drawn by gathering weight inside the search area, then each
    occupied cell from a group chosen at random, by walkable weight times a Gaussian around its centre.
    Returns the sorted cells, cell -> group, and the group centres."""
    if k == 0:
        return [], {}, []
    inside = _cell_raster(grid, raster, 0.0) >= 0
    n_groups = int(rng.integers(pl.groups[0], pl.groups[1] + 1))
    centres = [_sample_point(rng, np.where(inside, gather, 0.0), raster) for _ in range(n_groups)]
    xy = grid.centers_enu[:, :2]
    log_w = np.log(np.where(ok, cell_w, 1.0))
    free = ok.copy()
    group_of: dict[int, int] = {}
    for _ in range(k):
        g = int(rng.integers(n_groups))
        d2 = ((xy - centres[g]) ** 2).sum(1)
        logit = np.where(free, log_w - d2 / (2.0 * pl.sigma_m**2), -np.inf)
        prob = np.exp(logit - logit.max())
        cell = int(rng.choice(grid.num_cells, p=prob / prob.sum()))
        free[cell] = False
        group_of[cell] = g
    return sorted(group_of), group_of, centres


# --------------------------------------------------------------------------------------------------
# I/O


def scene_to_json(spec: SceneSpec) -> str:
    """Compact, deterministic JSON: the same scene gives the same bytes.

    Objects leave out their default fields (z, yaw, unused colours) to stay small; everything else is
    written in full so that a saved scene never depends on today's defaults.
    """
    d = spec.model_dump(mode="json", exclude={"objects", *_unset_optional(spec)})
    d["objects"] = [o.model_dump(mode="json", exclude_defaults=True) for o in spec.objects]
    return json.dumps(d, separators=(",", ":"))


def _unset_optional(spec: SceneSpec) -> set[str]:
    """Fields newer than the paper's scenes, left out at their defaults so those scenes keep their bytes."""
    out = set()
    if spec.placement == Placement():
        out.add("placement")
    if not spec.group_centres_m:
        out.add("group_centres_m")
    return out


def scene_from_json(text: str | bytes) -> SceneSpec:
    try:
        spec = SceneSpec.model_validate_json(text)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(x) for x in first.get("loc", ())) or "document"
        raise SceneError(f"corrupt scene JSON ({e.error_count()} errors; first at {where}: {first['msg']})") from None
    except (ValueError, TypeError) as e:
        raise SceneError(f"corrupt scene JSON: {e}") from None
    if len(spec.occupancy) != spec.grid.num_cells or any(v not in (0, 1) for v in spec.occupancy):
        raise SceneError(f"corrupt scene JSON: occupancy must be {spec.grid.num_cells} values of 0 or 1")
    if sum(spec.occupancy) != spec.occupied_cells_k:
        raise SceneError("corrupt scene JSON: occupancy does not match occupied_cells_k")
    return spec


def save_scene(spec: SceneSpec, path) -> Path:
    path = Path(path)
    try:
        path.write_text(scene_to_json(spec))
    except OSError as e:
        raise SceneError(f"cannot write scene to {path}: {e.strerror or e}") from None
    return path


def load_scene(path) -> SceneSpec:
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"cannot read scene {path}: {getattr(e, 'strerror', None) or e}") from None
    return scene_from_json(text)


def scene_summary(spec: SceneSpec) -> dict:
    """Object counts by kind (for logs and the CLI)."""
    counts: dict[str, int] = {}
    for o in spec.objects:
        counts[o.kind] = counts.get(o.kind, 0) + 1
    return {"seed": spec.seed, "k": spec.occupied_cells_k, "objects": counts}


__all__ = [
    "GENERATOR_VERSION", "SceneParams", "Placement", "SceneObject", "SceneSpec", "generate_scene", "save_scene", "load_scene",
    "scene_to_json", "scene_from_json", "footprint_corners", "Raster", "scene_summary",
]  # fmt: skip

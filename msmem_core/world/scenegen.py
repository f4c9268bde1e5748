"""Random shelf scenes: seed -> ``SceneSpec`` with a target floor occupancy and, optionally, hardness.

Objects (random class, random yaw, upright on the floor) are added until the fraction of the shelf
floor covered by their footprints reaches a target drawn from ``occupancy_range``. Footprints are
rasterised on a fine floor grid (``raster_m``) from the parts' projections; a new object must keep
``min_gap_m`` to every other object and ``wall_clearance_m`` to the walls and the front edge.

Hidden objects need deliberate structure: the 300 views look into the shelf from +-45 degrees
and from above, so a randomly scattered scene hides nothing, and every gap between two objects
leaks a wedge of sight. Like MEM's shelves, a scene therefore usually starts with a row of tall
classes along the front, broad side to the cameras and ``min_gap_m`` apart
(``front_row_probability``); the remaining objects are random, tall ones biased to the front and
short ones to the back (``front_bias``); the short ones are mostly small classes
(``small_fill_probability``), and a small one goes, with ``hide_probability``, to the darkest
spot found (ranked with point-visibility maps, the best few checked by exact ray counts, "plugs"
behind the row's gaps block their sight lines). A scene is *hard* when at least
``min_hidden`` objects are hidden from all viewpoints (``visibility.hidden_objects``); with
``require_hard`` the generator retries with sub-seeds derived from the seed until one is.
Every random choice flows from the seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

from msmem_core.errors import UserError
from msmem_core.util.validation import FROZEN_MODEL_CONFIG, Bool, Int
from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import yaw_quat
from msmem_core.world.meshes import part_mesh_local
from msmem_core.world.scene import OBJECT_CLASSES, ClassSpec, ObjectClass, ObjectSpec, Part, SceneSpec, ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints
from msmem_core.world.visibility import (
    MIN_VISIBLE_PIXELS,
    InsertionProbe,
    count_views_seeing,
    hidden_objects,
    object_pixel_counts,
)


class SceneGenConfig(BaseModel):
    """How random scenes are generated and what makes one hard."""

    model_config = FROZEN_MODEL_CONFIG

    occupancy_range: tuple[float, float] = (0.30, 0.45)
    """Range of the floor fraction covered by footprints; each scene's target is drawn from it."""
    min_gap_m: float = Field(0.005, ge=0.0, le=0.1)
    """Minimum distance between any two objects."""
    require_hard: Bool = True
    """Retry until at least ``min_hidden`` objects are hidden from every viewpoint."""
    min_hidden: Int = Field(4, ge=0)
    """Hidden objects a hard scene needs ("more than 3")."""
    max_tries: Int = Field(50, ge=1)
    """Attempts (sub-seeds) before giving up on a hard scene."""
    shelf: ShelfSpec = ShelfSpec()
    wall_clearance_m: float = Field(0.01, ge=0.0, le=0.1)
    """Minimum distance from an object to the side/back walls, the top board and the open front."""
    raster_m: float = Field(0.0025, gt=0.0, le=0.01)
    """Cell size of the floor raster used for footprints, overlap and occupancy."""
    front_bias: float = Field(3.0, ge=0.0)
    """Strength of the tall-in-front, short-behind preference (0 = uniform placement)."""
    occluder_yaw_spread_deg: float = Field(5.0, ge=0.0, le=90.0)
    """Occluder classes face the front with their broad side, yaw jittered uniformly by this much."""
    front_row_probability: float = Field(0.9, ge=0.0, le=1.0)
    """Chance that a scene starts with a row of occluder classes along the front (MEM-like shelves)."""
    small_fill_probability: float = Field(0.8, ge=0.0, le=1.0)
    """After the front row, chance that a drawn class comes from the small classes only."""
    hide_probability: float = Field(0.9, ge=0.0, le=1.0)
    """Chance that a small object goes to the least-seen spot found instead of a back-biased random one."""
    viewpoints: ViewpointConfig = ViewpointConfig()
    """Candidate views the hardness check casts from."""
    camera: CameraConfig = CameraConfig()
    visibility_stride: Int = Field(4, ge=1)
    """Hardness check: cast every stride-th pixel of every view."""
    min_visible_pixels: Int = Field(MIN_VISIBLE_PIXELS, ge=1)
    """Hardness check: an object is hidden if fewer strided pixels summed over all views see it."""
    classes: tuple[ClassSpec, ...] = ()
    """Classes to draw from beside the built-ins (as a scene file declares them: parts or a mesh);
    every generated scene declares them all."""
    builtin_classes: Bool = True
    """Draw the built-in classes too (False: only ``classes``, and the scenes' registries hold only
    them: ``SceneSpec.builtin_classes``)."""

    @model_validator(mode="after")
    def _some_class(self) -> SceneGenConfig:
        if not self.builtin_classes and not self.classes:
            raise ValueError("classes: builtin_classes is false, so at least one class must be declared")
        if self.classes:
            try:  # names against the built-ins, geometry (mesh files), confusable_with
                _class_pool(self)
            except ValidationError as e:
                msgs = (str(err["msg"]).removeprefix("Value error, ") for err in e.errors())
                raise ValueError("; ".join(msgs)) from None
        return self


    @field_validator("occupancy_range")
    @classmethod
    def _range(cls, v: tuple[float, float]) -> tuple[float, float]:
        lo, hi = v
        if not (0.0 < lo < 0.9 and 0.0 < hi < 0.9):
            raise ValueError(f"both bounds must lie in (0, 0.9), got {v}")
        if lo > hi:
            raise ValueError(f"lower bound {lo} exceeds upper bound {hi}")
        return v


@dataclass(frozen=True)
class _Footprint:
    """A class at one yaw rasterised around its origin: odd-sized kernels centred on the origin."""

    foot: NDArray[np.bool_]
    """Cells whose centre lies inside a part's projection."""
    grown: NDArray[np.bool_]
    """Cells within the gap distance of a part's projection (used against other footprints)."""

    @property
    def area_cells(self) -> int:
        return int(self.foot.sum())


@cache
def _part_outline(part: Part) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A part's floor projection in the object frame: its vertices (M, 2) and hull half-planes.

    Half-planes are rows (n_x, n_y, c) with n . p + c <= 0 inside (scipy's ``ConvexHull.equations``).
    """
    from scipy.spatial import ConvexHull
    xy = np.asarray(part_mesh_local(part).vertices)[:, :2]
    return xy, ConvexHull(xy).equations


def _yaw_rotation(yaw: float) -> NDArray[np.float64]:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _footprint_extent(cls_: ObjectClass, yaw: float) -> NDArray[np.float64]:
    """(xmin, xmax, ymin, ymax) of the class's footprint at ``yaw`` relative to its origin."""
    pts = np.concatenate([_part_outline(p)[0] for p in cls_.parts]) @ _yaw_rotation(yaw).T
    return np.array([pts[:, 0].min(), pts[:, 0].max(), pts[:, 1].min(), pts[:, 1].max()])


def _rasterise_footprint(cls_: ObjectClass, yaw: float, cell_m: float, grow_m: float) -> _Footprint:
    """Footprint of a class at ``yaw`` on a raster whose centre cell holds the object's origin."""
    rot = _yaw_rotation(yaw)
    k = int(np.ceil((cls_.footprint_radius_m + grow_m) / cell_m)) + 1
    u = np.arange(-k, k + 1) * cell_m
    pts = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    # Signed distance to each convex part: max over its half-planes (mitred offset when grown);
    # rotating the part by yaw rotates its hull normals and keeps the offsets.
    hulls = [_part_outline(p)[1] for p in cls_.parts]
    dist = np.min([np.max(pts @ (rot @ h[:, :2].T) + h[:, 2], axis=1) for h in hulls], axis=0)
    shape = (2 * k + 1, 2 * k + 1)
    return _Footprint(foot=(dist <= 0.0).reshape(shape), grown=(dist <= grow_m).reshape(shape))


@cache
def _class_pool(cfg: SceneGenConfig) -> tuple[ObjectClass, ...]:
    """The classes objects are drawn from, numbered as a scene declaring ``cfg.classes`` numbers them."""
    return SceneSpec(shelf=cfg.shelf, classes=cfg.classes, builtin_classes=cfg.builtin_classes).object_classes


def _box_bodied(cls_: ObjectClass) -> bool:
    """A front-row candidate: a box body (built-ins), or a footprint that fills at least
    ``BOX_FILL`` of its bounding rectangle at yaw 0 (mesh classes); round ones leave wide gaps."""
    if cls_.parts[0].kind != "convex":
        return cls_.parts[0].kind == "box"
    xmin, xmax, ymin, ymax = _footprint_extent(cls_, 0.0)
    cell = 0.0025
    area = _rasterise_footprint(cls_, 0.0, cell, 0.0).area_cells * cell**2
    return bool(area >= BOX_FILL * (xmax - xmin) * (ymax - ymin))


def _row_width(cls_: ObjectClass) -> float:
    """Width of a front-row class along the front (x) at yaw 0: its body's, or its footprint's."""
    if cls_.parts[0].kind == "box":
        return cls_.parts[0].size_m[0]
    xmin, xmax, _, _ = _footprint_extent(cls_, 0.0)
    return float(xmax - xmin)


@cache
def _class_height(cls_: ObjectClass) -> float:
    """Height of the class's top above its support."""
    return max(float(np.asarray(part_mesh_local(p).vertices)[:, 2].max()) for p in cls_.parts)


class _Floor:
    """The shelf floor raster, padded by ``pad`` blocked cells on every side.

    Interior cell (i, j) (padded index (i + pad, j + pad)) has its centre at
    ``interior_lower + (i + 0.5, j + 0.5) * cell``.
    """

    def __init__(self, cfg: SceneGenConfig, pad: int) -> None:
        shelf, c = cfg.shelf, cfg.raster_m
        self.cell, self.pad = c, pad
        self.nx, self.ny = round(shelf.width_m / c), round(shelf.depth_m / c)
        self.lower = shelf.interior_lower[:2]
        xs = self.lower[0] + (np.arange(-pad, self.nx + pad) + 0.5) * c
        ys = self.lower[1] + (np.arange(-pad, self.ny + pad) + 0.5) * c
        clr = cfg.wall_clearance_m + 2 * c  # a footprint reaches < 2 cells past its outermost cell centre
        ok_x = (xs > -shelf.width_m / 2 + clr) & (xs < shelf.width_m / 2 - clr)
        ok_y = (ys > clr) & (ys < shelf.depth_m - clr)
        self.blocked = ~(ok_x[:, None] & ok_y[None, :])
        """Cells a footprint may not cover: outside the interior shrunk by the clearance (plus raster slack)."""
        self.occupied = np.zeros_like(self.blocked)
        self.y_norm = np.clip((ys - ys[pad]) / max(ys[pad + self.ny - 1] - ys[pad], 1e-9), 0.0, 1.0)

    def feasible(self, fp: _Footprint) -> NDArray[np.bool_]:
        """Padded cells where the object's origin may go: no overlap (with gap), clearance kept."""
        from scipy.signal import fftconvolve
        hit_obj = fftconvolve(self.occupied.astype(np.float32), fp.grown[::-1, ::-1].astype(np.float32), mode="same")
        hit_wall = fftconvolve(self.blocked.astype(np.float32), fp.foot[::-1, ::-1].astype(np.float32), mode="same")
        ok: NDArray[np.bool_] = (hit_obj < 0.5) & (hit_wall < 0.5) & ~self.blocked
        return ok

    def stamp(self, fp: _Footprint, i: int, j: int) -> None:
        """Mark the footprint with its origin at padded cell (i, j) (it must lie inside the padding)."""
        k = fp.foot.shape[0] // 2
        self.occupied[i - k : i + k + 1, j - k : j + k + 1] |= fp.foot

    def position(self, i: int, j: int) -> tuple[float, float]:
        """World (x, y) of padded cell (i, j)'s centre."""
        return (
            float(self.lower[0] + (i - self.pad + 0.5) * self.cell),
            float(self.lower[1] + (j - self.pad + 0.5) * self.cell),
        )

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        i, j = np.floor((np.array([x, y]) - self.lower) / self.cell).astype(int) + self.pad
        return int(i), int(j)

    @property
    def covered_cells(self) -> int:
        return int(self.occupied.sum())

    @property
    def fraction(self) -> float:
        """Covered fraction of the floor (the interior cells)."""
        return self.covered_cells / (self.nx * self.ny)


def _pad_cells(cfg: SceneGenConfig, grow_m: float, classes: tuple[ObjectClass, ...] = ()) -> int:
    reach = max(c.footprint_radius_m for c in (*OBJECT_CLASSES, *classes)) + grow_m
    return int(np.ceil(reach / cfg.raster_m)) + 2


def footprint_fraction(scene: SceneSpec, cell_m: float = 0.0025) -> float:
    """Fraction of the shelf floor covered by the footprints of the scene's upright objects.

    The generator's measure (``SceneSpec.occupancy_fraction``), recomputed from a scene.
    """
    cfg = SceneGenConfig(shelf=scene.shelf, raster_m=cell_m, require_hard=False)
    floor = _Floor(cfg, _pad_cells(cfg, 0.0, scene.object_classes))
    for obj in scene.objects:
        q = obj.quat_xyzw
        fp = _rasterise_footprint(obj.object_class, 2 * float(np.arctan2(q[2], q[3])), cell_m, 0.0)
        i, j = floor.cell_of(obj.position_m[0], obj.position_m[1])
        k = fp.foot.shape[0] // 2
        if not (k <= i < floor.occupied.shape[0] - k and k <= j < floor.occupied.shape[1] - k):
            raise UserError(f"object {obj.id} stands outside the shelf floor")
        floor.stamp(fp, i, j)
    return floor.fraction


# Placement constants (documented knobs live in SceneGenConfig; these shape the structure).
OCCLUDER_HEIGHT_M = 0.12
"""Classes at least this tall make the front row (box-bodied ones) and are biased to the front."""
ROW_JITTER_M = 0.01
"""Random setback of a front-row object from the front clearance line."""
ROW_START_SLACK_M = 0.03
"""Random distance of the front row's first object from its wall."""
BOX_FILL = 0.85
"""A mesh class whose footprint fills this share of its bounding rectangle counts as box-bodied."""
PLUG_MIN_HEIGHT_M = 0.08
"""Classes at least this tall may plug a gap of the front row."""
PLUG_REACH_M = 0.02
"""How far from the spot right behind a gap a plug may stand (else the gap stays open)."""
SMALL_HEIGHT_M = 0.06
SMALL_RADIUS_M = 0.075
"""Classes at most this tall and this wide (tuna cans, gelatin boxes, ...) are the ones that hide."""
HIDE_YAW_TRIES = 4
"""Yaws tried for a small object looking for a dark spot."""
HIDE_CANDIDATES = 3
"""Dark spots whose exact visibility is counted for each small object."""
HIDE_TEMPERATURE = 0.5
"""Softness (in footprint cells seen) of the preference for the darkest spot."""
MAX_FAILURES = 60
"""Objects that found no spot before an attempt counts as jammed."""


@cache
def _nominal_area_cells(cls_: ObjectClass, cell_m: float) -> int:
    return _rasterise_footprint(cls_, 0.0, cell_m, 0.0).area_cells


class _ShadowMaps:
    """Per object height, how many viewpoints see a point at that height above each floor cell.

    Sampled at blocks of ``BLOCK`` x ``BLOCK`` raster cells (1 cm by default). For upright,
    prism-like occluders a point hidden at height h is hidden at every lower height, so an object
    whose footprint lies in cells unseen at its top height is hidden entirely.
    """

    BLOCK = 4
    ABOVE_TOP_M = 0.002

    def __init__(self, cfg: SceneGenConfig, floor: _Floor, views: NDArray[np.float64]) -> None:
        self.cfg, self.floor, self.views = cfg, floor, views
        self.maps: dict[float, NDArray[np.float32]] = {}

    def views_seeing(self, height_m: float, objects: list[ObjectSpec]) -> NDArray[np.float32]:
        """Padded raster of view counts at ``height_m`` (computed once per height per attempt)."""
        if height_m not in self.maps:
            f, b = self.floor, self.BLOCK
            i, j = np.arange(0, f.nx, b), np.arange(0, f.ny, b)
            xy = f.lower + (np.stack(np.meshgrid(i, j, indexing="ij"), axis=-1) + b / 2) * f.cell  # block centres
            z = np.full((*xy.shape[:2], 1), height_m + self.ABOVE_TOP_M)
            pts = np.concatenate([xy, z], axis=-1).reshape(-1, 3)
            seen = count_views_seeing(pts, objects, self.cfg.shelf, self.views, self.cfg.camera)
            blocks = np.repeat(np.repeat(seen.reshape(len(i), len(j)), b, axis=0), b, axis=1)[: f.nx, : f.ny]
            full = np.full(f.blocked.shape, float(len(self.views)), dtype=np.float32)
            full[f.pad : f.pad + f.nx, f.pad : f.pad + f.ny] = blocks
            self.maps[height_m] = full
        return self.maps[height_m]


class _Placer:
    """State of one placement attempt: the floor, the objects so far and the shadow maps."""

    def __init__(self, rng: np.random.Generator, cfg: SceneGenConfig, views: NDArray[np.float64]) -> None:
        self.rng, self.cfg = rng, cfg
        self.grow = cfg.min_gap_m + 2 * cfg.raster_m  # raster slack: real gaps stay >= min_gap_m
        pool = _class_pool(cfg)
        self.floor = _Floor(cfg, _pad_cells(cfg, self.grow, pool))
        top = cfg.shelf.height_m - cfg.wall_clearance_m
        self.classes = [c for c in pool if _class_height(c) <= top]
        if not self.classes:
            raise UserError(f"no object class fits a shelf {cfg.shelf.height_m} m high")
        self.heights = np.array([_class_height(c) for c in self.classes])
        span = max(float(np.ptp(self.heights)), 1e-9)
        self.tallness = (self.heights - self.heights.min()) / span * 2 - 1  # -1 short .. +1 tall
        self.occluders = [i for i, h in enumerate(self.heights) if h >= OCCLUDER_HEIGHT_M]
        # Front-row classes: box-bodied occluders (round ones leave wide gaps), wider ones likelier.
        self.row_classes = [i for i in self.occluders if _box_bodied(self.classes[i])] or self.occluders
        widths = np.array([_row_width(self.classes[i]) for i in self.row_classes])
        self.row_weights = widths**2 / np.sum(widths**2)
        self.plug_classes = [i for i, h in enumerate(self.heights) if h >= PLUG_MIN_HEIGHT_M]
        self.plug_classes = self.plug_classes or list(range(len(self.classes)))
        self.upper_cells = cfg.occupancy_range[1] * self.floor.nx * self.floor.ny
        self.shadows = _ShadowMaps(cfg, self.floor, views)
        self.objects: list[ObjectSpec] = []

    def _yaw(self, c: int) -> float:
        if c in self.occluders:  # broad side towards the cameras, give or take the spread
            spread = np.radians(self.cfg.occluder_yaw_spread_deg)
            return float(np.pi * self.rng.integers(2) + spread * self.rng.uniform(-1.0, 1.0))
        return float(self.rng.uniform(0.0, 2 * np.pi))

    def _fits_budget(self, fp: _Footprint) -> bool:
        return self.floor.covered_cells + fp.area_cells <= self.upper_cells

    def _spec(self, c: int, yaw: float, i: int, j: int) -> ObjectSpec:
        """The next object: class c at padded raster cell (i, j), standing on the floor."""
        x, y = self.floor.position(i, j)
        qx, qy, qz, qw = (float(v) for v in yaw_quat(yaw))
        spec = ObjectSpec(
            id=len(self.objects), class_name=self.classes[c].name, position_m=(x, y, 0.0), quat_xyzw=(qx, qy, qz, qw)
        )
        spec._class = self.classes[c]  # a declared class is known only to the registry it came from
        return spec

    def _add(self, c: int, yaw: float, fp: _Footprint, i: int, j: int) -> None:
        self.floor.stamp(fp, i, j)
        self.objects.append(self._spec(c, yaw, i, j))

    def front_row(self) -> list[tuple[float, float]]:
        """Line the front with occluders, side by side from one wall, until none fits any more.

        Positions are computed from the footprints' exact extents (and rounded away from the
        previous object onto the raster), so neighbours stand ``min_gap_m`` to one cell apart.
        Returns the gaps between neighbours as (x of the gap, y of the row's back there).
        """
        cfg, f = self.cfg, self.floor
        lo_x = -cfg.shelf.width_m / 2 + cfg.wall_clearance_m
        hi_x = cfg.shelf.width_m / 2 - cfg.wall_clearance_m
        direction = 1 if self.rng.uniform() < 0.5 else -1
        slack = self.rng.uniform(0.0, ROW_START_SLACK_M)
        cursor = lo_x + slack if direction > 0 else hi_x - slack
        gaps: list[tuple[float, float]] = []
        last_back: float | None = None
        while True:
            n_row = len(self.row_classes)
            order = self.rng.choice(n_row, size=n_row, replace=False, p=self.row_weights)
            for c in (self.row_classes[int(k)] for k in order):
                yaw = self._yaw(c)
                ext = _footprint_extent(self.classes[c], yaw)  # xmin, xmax, ymin, ymax
                x = cursor - (ext[0] if direction > 0 else ext[1])
                i = (np.ceil if direction > 0 else np.floor)((x - f.lower[0]) / f.cell - 0.5)
                y = cfg.wall_clearance_m - ext[2] + self.rng.uniform(0.0, ROW_JITTER_M)
                j = np.ceil((y - f.lower[1]) / f.cell - 0.5)
                x, y = f.lower + (np.array([i, j]) + 0.5) * f.cell
                if x + ext[0] < lo_x or x + ext[1] > hi_x or y + ext[3] > cfg.shelf.depth_m - cfg.wall_clearance_m:
                    continue
                fp = _rasterise_footprint(self.classes[c], yaw, cfg.raster_m, self.grow)
                if not self._fits_budget(fp):
                    continue
                self._add(c, yaw, fp, int(i) + f.pad, int(j) + f.pad)
                near_side = x + (ext[0] if direction > 0 else ext[1])
                if last_back is not None:
                    gaps.append((float(near_side - direction * cfg.min_gap_m / 2), max(last_back, float(y + ext[3]))))
                last_back = float(y + ext[3])
                cursor = x + ext[1] + cfg.min_gap_m if direction > 0 else x + ext[0] - cfg.min_gap_m
                break
            else:
                return gaps

    def plug(self, gaps: list[tuple[float, float]]) -> None:
        """Stand an object right behind each gap of the front row, blocking the sight line through it."""
        f = self.floor
        for gx, back in gaps:
            c = self.plug_classes[int(self.rng.integers(len(self.plug_classes)))]
            yaw = self._yaw(c)
            fp = _rasterise_footprint(self.classes[c], yaw, self.cfg.raster_m, self.grow)
            if not self._fits_budget(fp):
                continue
            ok = f.feasible(fp)
            ext = _footprint_extent(self.classes[c], yaw)
            ti, tj = f.cell_of(gx - (ext[0] + ext[1]) / 2, back + self.cfg.min_gap_m - ext[2])
            ii, jj = np.nonzero(ok)
            if len(ii) == 0:
                continue
            d2 = (ii - ti) ** 2 + (jj - tj) ** 2
            k = int(np.argmin(d2))
            if d2[k] * f.cell**2 <= PLUG_REACH_M**2:
                self._add(c, yaw, fp, int(ii[k]), int(jj[k]))

    def _spot_weights(self, c: int, ok: NDArray[np.bool_]) -> NDArray[np.float64]:
        """Tall classes towards the front, short ones towards the back."""
        return np.exp(-self.cfg.front_bias * self.tallness[c] * self.floor.y_norm)[None, :] * ok

    def _draw(self, weights: NDArray[np.float64], size: int = 1) -> list[tuple[int, int]]:
        p = (weights / weights.sum()).ravel()
        size = min(size, int(np.count_nonzero(p)))
        flat = self.rng.choice(p.size, size=size, replace=False, p=p)
        return [(int(i), int(j)) for i, j in zip(*np.unravel_index(flat, weights.shape), strict=True)]

    def _hiding_spot(self, c: int) -> tuple[float, _Footprint, int, int] | None:
        """The least visible of a few dark spots for a small object, or None if it fits nowhere.

        Ranks spots with the shadow map at the object's height (over ``HIDE_YAW_TRIES`` yaws), draws
        ``HIDE_CANDIDATES`` of the darkest and counts exactly how many pixels of all views would
        see the object at each.
        """
        from scipy.signal import fftconvolve
        best: tuple[float, float, _Footprint, NDArray[np.float64]] | None = None
        seen = self.shadows.views_seeing(float(self.heights[c]), self.objects)
        for _ in range(HIDE_YAW_TRIES):
            yaw = self._yaw(c)
            fp = _rasterise_footprint(self.classes[c], yaw, self.cfg.raster_m, self.grow)
            if not self._fits_budget(fp):
                return None
            ok = self.floor.feasible(fp)
            if not ok.any():
                continue
            # Score: footprint cells seen by any view, then (tie-break) mean views per cell.
            kernel = fp.foot[::-1, ::-1].astype(np.float32)
            score = fftconvolve((seen > 0).astype(np.float32), kernel, mode="same")
            score += fftconvolve(seen, kernel, mode="same") / (fp.area_cells * len(self.shadows.views))
            s_min = float(score[ok].min())
            if best is None or s_min < best[0]:
                best = (s_min, yaw, fp, np.exp(-(np.maximum(score, s_min) - s_min) / HIDE_TEMPERATURE) * ok)
        if best is None:
            return None
        _, yaw, fp, weights = best
        spots = self._draw(weights, HIDE_CANDIDATES)
        if len(spots) == 1:
            return yaw, fp, *spots[0]
        probe = InsertionProbe(
            self.objects, self.cfg.shelf, self.shadows.views, self.cfg.camera, self.cfg.visibility_stride
        )
        counts = []
        for i, j in spots:
            counts.append(probe.pixel_count(self._spec(c, yaw, i, j)))
            if counts[-1] == 0:
                break
        return yaw, fp, *spots[int(np.argmin(counts))]

    def fill(self, target: float) -> bool:
        """Add random classes until the target fraction; False if the floor jams first.

        Draws classes whose nominal footprints reach the target (small ones with
        ``small_fill_probability``) and places them lowest first. A small class goes, with
        ``hide_probability``, to the least visible spot found (``_hiding_spot``); the others are
        drawn with the front/back bias.
        """
        floor_cells = self.floor.nx * self.floor.ny
        small = [
            i
            for i, (h, c) in enumerate(zip(self.heights, self.classes, strict=True))
            if h <= SMALL_HEIGHT_M and c.footprint_radius_m <= SMALL_RADIUS_M
        ]
        queue: list[int] = []
        planned = self.floor.covered_cells
        while planned < target * floor_cells:
            pool = small if small and self.rng.uniform() < self.cfg.small_fill_probability else range(len(self.classes))
            queue.append(int(self.rng.choice(list(pool))))
            planned += _nominal_area_cells(self.classes[queue[-1]], self.cfg.raster_m)
        queue.sort(key=lambda c: self.heights[c])  # lowest first: they get the darkest spots
        failures = 0
        while self.floor.fraction < target:
            if failures >= MAX_FAILURES:
                return False
            c = queue.pop(0) if queue else int(self.rng.integers(len(self.classes)))
            spot: tuple[float, _Footprint, int, int] | None = None
            if c in small and self.rng.uniform() < self.cfg.hide_probability:
                spot = self._hiding_spot(c)
            else:
                yaw = self._yaw(c)
                fp = _rasterise_footprint(self.classes[c], yaw, self.cfg.raster_m, self.grow)
                ok = self.floor.feasible(fp) if self._fits_budget(fp) else None
                if ok is not None and ok.any():
                    spot = (yaw, fp, *self._draw(self._spot_weights(c, ok))[0])
            if spot is None:
                failures += 1
                continue
            self._add(c, *spot)
        return True


def _place_objects(
    rng: np.random.Generator, cfg: SceneGenConfig, views: NDArray[np.float64]
) -> tuple[list[ObjectSpec], float] | None:
    """One attempt: draws the target fraction, lines the front with occluders (with probability
    ``front_row_probability``), then fills up with random classes; None if the floor jams."""
    placer = _Placer(rng, cfg, views)
    target = float(rng.uniform(*cfg.occupancy_range))
    if rng.uniform() < cfg.front_row_probability:
        placer.plug(placer.front_row())
    if not placer.fill(target):
        return None
    return placer.objects, placer.floor.fraction


def _count_hidden(objects: list[ObjectSpec], cfg: SceneGenConfig, views: NDArray[np.float64]) -> int:
    """Objects hidden from every view (``visibility.hidden_objects`` with the config's stride and threshold)."""
    return len(hidden_objects(objects, cfg.shelf, views, cfg.camera, cfg.visibility_stride, cfg.min_visible_pixels))


def _may_be_hard(objects: list[ObjectSpec], cfg: SceneGenConfig, views: NDArray[np.float64]) -> bool:
    """Quick screen: do at least ``min_hidden`` of the non-occluder objects pass as hidden?

    Counts exactly but casts only the rays that can reach those objects; tall objects, which
    are practically never hidden, are left out, so the screen may (rarely) reject a hard scene
    and never accepts one that is not.
    """
    short = [o.id for o in objects if _class_height(o.object_class) < OCCLUDER_HEIGHT_M]
    if len(short) < cfg.min_hidden:
        return False
    counts = object_pixel_counts(objects, short, cfg.shelf, views, cfg.camera, cfg.visibility_stride)
    return sum(c < cfg.min_visible_pixels for c in counts.values()) >= cfg.min_hidden


def generate_scene(seed: int, cfg: SceneGenConfig | None = None) -> SceneSpec:
    """A reproducible random scene for ``seed`` (same seed and config -> identical ``SceneSpec``).

    Attempt k uses the k-th sub-seed drawn from ``np.random.default_rng(seed)``. The scene records
    its floor ``occupancy_fraction`` and the number of ``hidden_objects``; with ``require_hard``
    attempts go on until at least ``min_hidden`` objects are hidden (``UserError`` after
    ``max_tries``).
    """
    cfg = cfg or SceneGenConfig()
    if seed < 0:
        raise UserError(f"scene seed must be >= 0, got {seed}")
    return _generate(int(seed), cfg)


def clear_generated_scenes() -> None:
    """Forget the scenes ``generate_scene`` keeps for this process (the next call generates again)."""
    _generate.cache_clear()


@lru_cache(maxsize=16)
def _generate(seed: int, cfg: SceneGenConfig) -> SceneSpec:
    """``generate_scene``'s work, kept per process: a scene is a pure function of its seed and
    config (both immutable), and generating one takes seconds."""
    sub_seeds = np.random.default_rng(seed).integers(0, 2**63 - 1, size=cfg.max_tries)
    views = generate_viewpoints(cfg.viewpoints, cfg.shelf)
    best, unplaced, screened = -1, 0, 0
    for sub in sub_seeds:
        placed = _place_objects(np.random.default_rng(int(sub)), cfg, views)
        if placed is None:
            unplaced += 1
            continue
        if cfg.require_hard and not _may_be_hard(placed[0], cfg, views):
            screened += 1
            continue
        objects, fraction = placed
        hidden = _count_hidden(objects, cfg, views)
        best = max(best, hidden)
        if not cfg.require_hard or hidden >= cfg.min_hidden:
            return SceneSpec(
                name=f"gen-{seed}",
                seed=seed,
                shelf=cfg.shelf,
                builtin_classes=cfg.builtin_classes,
                classes=cfg.classes,
                objects=tuple(objects),
                occupancy_fraction=round(fraction, 6),
                hidden_objects=hidden,
            )
    tried = f"the best attempt hid {best}" if best >= 0 else "no attempt got as far as counting hidden objects"
    raise UserError(
        f"no scene for seed {seed} passed the hardness check (>= {cfg.min_hidden} objects hidden from all"
        f" {len(views)} views) in {cfg.max_tries} tries: {tried}; {unplaced} tries could not place the objects,"
        f" {screened} were screened out as unable to hide enough. Lower min_hidden"
        + (f" (to {best} or less to accept the best)" if best >= 0 else "")
        + ", raise max_tries, or raise min_visible_pixels (objects seen by fewer pixels count as hidden)"
    )

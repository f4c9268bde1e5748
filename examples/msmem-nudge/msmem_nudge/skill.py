"""The nudge skill: push an object's top sideways with the closed fingers.

A motion the built-in skills do not make. The push skill drives the tool horizontally into the
shelf from the front, low on the object; the nudge comes *from above*, beside the object:

1. approach from in front of the shelf (``approach_y_m``) at ``clearance_m`` above the object's
   believed top, fingers closed, pointing down, closing axis along y (so the 10 cm palm lies
   front-to-back beside the object, not across it);
2. move in above the object's side and lower the fingertips to ``height_fraction`` (70 %) of the
   object's believed height, ``standoff_m`` away from its believed side face;
3. move sideways (along x) by the standoff plus 3-5 cm: the object is nudged by 3-5 cm;
4. lift back to the approach height, retreat out of the shelf, park.

Proposals come from the belief only: objects are the connected bird's-eye-view components of
believed-occupied columns (expected occupancy > ``occupied_threshold``) of one argmax class (not
background) holding at least ``min_cells`` confidently occupied ones (>= ``confidence_threshold``),
parts up to ``merge_gap_m`` apart merged, near the shelf front (front face within ``front_band_m``)
whose top is visible (the voxel above the top is believed free in at least ``min_top_visible`` of
the columns). A candidate
is dropped if the gripper would not fit under the top board, if the tool's path meets a
believed-occupied voxel other than the target (approach, descent, lift, retreat and the nudge
itself), if the nudged object would run into another believed object, or if the nudge would
probably tip the object over (``assumed_friction`` * contact height > half its believed width).

``execute`` only moves the gripper; MSAS measures what moved and what fell or left the shelf.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from msmem_core.interfaces import Action, Category, DecisionContext, Outcome, Simulator, Skill, Workspace
from msmem_core.world.gripper import GripperSpec

Box = tuple[float, float, float, float, float, float]
"""Axis-aligned box (x_lo, y_lo, z_lo, x_hi, y_hi, z_hi) in metres."""


class NudgeConfig(BaseModel):
    """How nudges are proposed and executed."""

    model_config = ConfigDict(extra="forbid")

    gripper: GripperSpec = GripperSpec()
    """The run's gripper (filled in by the runner)."""
    height_fraction: float = Field(0.7, gt=0.2, lt=1.0)
    """Fingertip height during the nudge, as a fraction of the object's believed height."""
    min_nudge_m: float = Field(0.03, gt=0.0, le=0.2)
    max_nudge_m: float = Field(0.05, gt=0.0, le=0.2)
    """The object is moved by a distance uniform in [min_nudge_m, max_nudge_m]."""
    lengths_per_side: int = Field(2, ge=1, le=10)
    """Nudge distances sampled per object and side."""
    max_candidates: int = Field(40, ge=1, le=1000)
    standoff_m: float = Field(0.015, ge=0.0, le=0.1)
    """Gap between the fingers and the object's believed side face before the sideways move."""
    clearance_m: float = Field(0.03, gt=0.0, le=0.2)
    """Height of the fingertips above the object's believed top while approaching and retreating."""
    contact_depth_m: float = Field(0.025, ge=0.0, le=0.2)
    """The fingers touch the object this far behind its believed front face."""
    front_band_m: float = Field(0.15, gt=0.0, le=1.0)
    """Only objects whose believed front face is within this distance of the shelf front."""
    confidence_threshold: float = Field(0.9, gt=0.5, lt=1.0)
    occupied_threshold: float = Field(0.5, ge=0.0, lt=1.0)
    """Expected occupancy above which a voxel is an obstacle for the tool's path."""
    free_threshold: float = Field(0.2, ge=0.0, lt=0.5)
    """Expected occupancy at or below which the voxel above a column's top counts as seen free."""
    min_top_visible: float = Field(0.5, ge=0.0, le=1.0)
    min_cells: int = Field(3, ge=1)
    """Smallest object footprint (bird's-eye-view cells) worth a nudge."""
    merge_gap_m: float = Field(0.03, ge=0.0, le=0.2)
    """Believed parts of one class up to this far apart (bird's-eye view) are one object."""
    assumed_friction: float = Field(0.5, ge=0.0, le=2.0)
    """Friction coefficient of the tipping test (sliding needs friction * height < half width)."""
    min_tip_height_m: float = Field(0.015, gt=0.0, le=0.2)
    approach_y_m: float = Field(-0.1, lt=0.0, ge=-1.0)
    """The approach starts, and the retreat ends, at this y in front of the shelf."""
    speed_mps: float = Field(0.05, gt=0.0, le=1.0)
    travel_speed_mps: float = Field(0.2, gt=0.0, le=2.0)
    settle_s: float = Field(0.5, ge=0.0, le=10.0)


class NudgeAction(Action):
    """Nudge the object of ``target_class`` sideways: the fingertips start at ``start_m`` (beside the
    object, at ``height_fraction`` of its top) and travel ``length_m`` along ``direction``."""

    kind: str = "nudge"
    category: Literal["manipulation"] = "manipulation"
    start_m: tuple[float, float, float]
    direction: tuple[float, float, float]
    """Unit vector, +x or -x."""
    length_m: float = Field(gt=0.0, le=0.5)
    """Fingertip travel: the standoff plus ``nudge_m``."""
    nudge_m: float = Field(gt=0.0, le=0.5)
    """How far the object is expected to move."""
    approach_z_m: float
    """Fingertip height of the approach and the retreat."""
    approach_y_m: float
    target_class: int
    footprint_m: tuple[float, float, float, float]
    """Believed footprint of the object (x_lo, y_lo, x_hi, y_hi)."""
    top_m: float
    """Believed height of the object's top."""

    def path_boxes(self, tool: tuple[float, ...]) -> list[Box]:
        """Boxes the tool (``tool_of``) sweeps: approach, descent, nudge, lift and retreat (in that order)."""
        x0, y, zt = self.start_m
        x1 = x0 + self.length_m * self.direction[0]
        za, ya = self.approach_z_m, self.approach_y_m
        return [
            *_sweep(tool, (x0, ya, za), (x0, y, za)),
            *_sweep(tool, (x0, y, za), (x0, y, zt)),
            *_sweep(tool, (x0, y, zt), (x1, y, zt)),
            *_sweep(tool, (x1, y, zt), (x1, y, za)),
            *_sweep(tool, (x1, y, za), (x1, ya, za)),
        ]

    def swept_volume(self, workspace: Workspace) -> NDArray[np.bool_]:
        mask = np.zeros(workspace.grid.shape, dtype=bool)
        for box in self.path_boxes(tool_of(workspace.gripper)):
            mask[box_slices(workspace.grid, box)] = True
        return mask


def tool_of(gripper: GripperSpec) -> tuple[float, float, float, float, float, float]:
    """Half-extents of the closed tool pointing down with its closing axis along y: fingers
    (x: finger_width/2, y: finger_thickness, z: finger_length) and palm (x: palm_width/2,
    y: palm_length/2, z: palm_depth)."""
    g = gripper
    return (g.finger_width_m / 2, g.finger_thickness_m, g.finger_length_m,
            g.palm_width_m / 2, g.palm_length_m / 2, g.palm_depth_m)


def tool_boxes(tool: tuple[float, ...], tip: tuple[float, float, float]) -> list[Box]:
    """Fingers and palm as world boxes with the fingertips' centre at ``tip``."""
    fx, fy, fl, px, py, pd = tool
    x, y, z = tip
    return [(x - fx, y - fy, z, x + fx, y + fy, z + fl), (x - px, y - py, z + fl, x + px, y + py, z + fl + pd)]


def _sweep(tool: tuple[float, ...], a: tuple[float, float, float], b: tuple[float, float, float]) -> list[Box]:
    """The tool's boxes swept along the straight segment a -> b (exact for axis-aligned moves)."""
    out = []
    for ba, bb in zip(tool_boxes(tool, a), tool_boxes(tool, b), strict=True):
        out.append((*(min(ba[i], bb[i]) for i in range(3)), *(max(ba[i + 3], bb[i + 3]) for i in range(3))))
    return out  # type: ignore[return-value]


def box_slices(grid: Any, box: Box) -> tuple[slice, slice, slice]:
    """Index slices of the voxels whose centres lie inside ``box`` (clipped to the grid)."""
    o, s = grid.origin, grid.voxel_m
    lo = np.ceil((np.asarray(box[:3]) - o) / s - 0.5).astype(int)
    hi = np.floor((np.asarray(box[3:]) - o) / s - 0.5).astype(int)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, np.asarray(grid.shape) - 1)
    return tuple(slice(int(a), int(b) + 1) if b >= a else slice(0, 0) for a, b in zip(lo, hi, strict=True))  # type: ignore[return-value]


@dataclass
class BelievedObject:
    """An object as the belief sees it: class, footprint cells and voxels, top."""

    cls: int
    cells: NDArray[np.int64]
    """[N, 2] bird's-eye-view cells (i, j)."""
    voxels: NDArray[np.bool_]
    """[X, Y, Z] believed-occupied voxels of any object class in its footprint columns."""
    footprint_m: tuple[float, float, float, float]
    top_m: float


def believed_objects(belief: Any, shelf: Any, cfg: NudgeConfig) -> list[BelievedObject]:
    """Confident objects near the front whose top was seen (see the module docstring)."""
    grid = belief.grid
    o, s = grid.origin, grid.voxel_m
    c = grid.centers()
    interior = np.all((c > shelf.interior_lower) & (c < shelf.interior_upper), axis=-1)
    p = belief.expected_occupancy()
    cls = np.argmax(belief.eta, axis=0)
    conf = (p >= cfg.confidence_threshold) & interior & (cls != 0)
    occupied = (p > cfg.occupied_threshold) & interior
    objects = occupied & (cls != 0)
    out = []
    for k in np.unique(cls[conf]):
        # an object: a connected footprint of believed-occupied columns of one class (one view rarely
        # makes a whole top confident), holding at least min_cells confidently occupied columns;
        # parts up to merge_gap_m apart are connected (a top seen at a grazing angle comes out
        # striped, a side face seen obliquely patchy)
        mine = occupied & (cls == k)
        bev = mine.any(axis=2)
        square = np.ones((3, 3), dtype=bool)
        grow = max(0, math.ceil(cfg.merge_gap_m / s / 2 - 1e-9))
        near = ndimage.binary_dilation(bev, structure=square, iterations=grow) if grow else bev
        labels, n = ndimage.label(near, structure=square)
        labels[~bev] = 0
        sure = (conf & (cls == k)).any(axis=2)
        for lab in range(1, n + 1):
            foot = labels == lab
            if (sure & foot).sum() < cfg.min_cells:
                continue
            cells = np.argwhere(foot)
            col = mine & foot[:, :, None]
            tops = (grid.shape[2] - 1 - np.argmax(col[:, :, ::-1], axis=2))[foot]
            above = np.minimum(tops + 1, grid.shape[2] - 1)
            seen_free = p[cells[:, 0], cells[:, 1], above] <= cfg.free_threshold
            if seen_free.mean() < cfg.min_top_visible:
                continue
            i0, j0 = cells.min(axis=0)
            i1, j1 = cells.max(axis=0) + 1
            fp = (float(o[0] + i0 * s), float(o[1] + j0 * s), float(o[0] + i1 * s), float(o[1] + j1 * s))
            if fp[1] - shelf.interior_lower[1] > cfg.front_band_m:
                continue
            top = float(o[2] + (tops.max() + 1) * s)
            out.append(BelievedObject(int(k), cells, objects & foot[:, :, None], fp, top))
    out.sort(key=lambda b: b.footprint_m[1])
    return out


class NudgeSkill(Skill):
    category: ClassVar[Category] = "manipulation"

    def __init__(self, config: NudgeConfig | None = None) -> None:
        self.config = config or NudgeConfig()
        self.tool = tool_of(self.config.gripper)

    # ----------------------------------------------------------------------------------- proposal
    def propose(self, ctx: DecisionContext) -> list[Action]:
        if not ctx.manipulation_allowed:
            return []
        return list(self.sample(ctx.belief, ctx.shelf, ctx.rng))

    def sample(self, belief: Any, shelf: Any, rng: np.random.Generator) -> list[NudgeAction]:
        cfg = self.config
        grid = belief.grid
        p = belief.expected_occupancy()
        c = grid.centers()
        interior = np.all((c > shelf.interior_lower) & (c < shelf.interior_upper), axis=-1)
        # believed objects; occupied voxels of class background are shelf boards, kept off by the bounds test
        obstacles = (p > cfg.occupied_threshold) & interior & (np.argmax(belief.eta, axis=0) != 0)
        tool_h = cfg.gripper.finger_length_m + cfg.gripper.palm_depth_m
        lo, hi = shelf.interior_lower, shelf.interior_upper
        out: list[NudgeAction] = []
        for obj in believed_objects(belief, shelf, cfg):
            z_tip = cfg.height_fraction * obj.top_m
            z_app = obj.top_m + cfg.clearance_m
            x_lo, y_lo, x_hi, _ = obj.footprint_m
            if z_tip < cfg.min_tip_height_m or z_app + tool_h > hi[2] - 0.005:
                continue  # the closed gripper does not fit above the object under the top board
            if cfg.assumed_friction * z_tip > (x_hi - x_lo) / 2:
                continue  # it would probably tip over rather than slide
            y = y_lo + cfg.contact_depth_m
            for sign in (1.0, -1.0):
                x0 = (x_lo - cfg.standoff_m - self.tool[0]) if sign > 0 else (x_hi + cfg.standoff_m + self.tool[0])
                for nudge in rng.uniform(cfg.min_nudge_m, cfg.max_nudge_m, cfg.lengths_per_side):
                    a = NudgeAction(
                        start_m=(float(x0), float(y), float(z_tip)), direction=(sign, 0.0, 0.0),
                        length_m=float(cfg.standoff_m + nudge), nudge_m=float(nudge), approach_z_m=float(z_app),
                        approach_y_m=cfg.approach_y_m, target_class=obj.cls, footprint_m=obj.footprint_m,
                        top_m=obj.top_m,
                    )
                    if self._valid(a, obj, obstacles, grid, lo, hi):
                        out.append(a)
            if len(out) >= cfg.max_candidates:
                break
        return out[: cfg.max_candidates]

    def _valid(self, a: NudgeAction, obj: BelievedObject, obstacles: NDArray[np.bool_], grid: Any,
               lo: NDArray[np.float64], hi: NDArray[np.float64]) -> bool:
        boxes = a.path_boxes(self.tool)
        for b in boxes:  # the tool stays inside the shelf (the front is open)
            if b[0] < lo[0] or b[3] > hi[0] or b[5] > hi[2] or b[4] > hi[1]:
                return False
        others = obstacles & ~obj.voxels
        for i, b in enumerate(boxes):
            # the approach and descent must miss the target too; from the nudge on, the tool touches it
            region = (obstacles if i < 4 else others)[box_slices(grid, b)]
            if region.any():
                return False
        shift = round(a.nudge_m * a.direction[0] / grid.voxel_m)
        moved = shift_x(obj.voxels, shift)
        return not (moved & others).any()

    # ----------------------------------------------------------------------------------- execution
    def execute(self, sim: Simulator, action: Action, ctx: DecisionContext) -> Outcome:
        cfg = self.config
        a = NudgeAction.model_validate(action.model_dump())
        x0, y, zt = a.start_m
        x1 = x0 + a.length_m * a.direction[0]
        za, ya = a.approach_z_m, a.approach_y_m
        sim.move_gripper([tool_pose(x0, ya, za), tool_pose(x0, y, za), tool_pose(x0, y, zt)], opening_m=0.0,
                         speed_mps=cfg.travel_speed_mps)
        reached = sim.move_gripper([tool_pose(x1, y, zt)], speed_mps=cfg.speed_mps)
        sim.move_gripper([tool_pose(x1, y, za), tool_pose(x1, ya, za)], speed_mps=cfg.travel_speed_mps)
        sim.park_gripper()
        if cfg.settle_s > 0:
            sim.step(cfg.settle_s)
        miss = float(np.linalg.norm(reached[:3, 3] - np.array([x1, y, zt])))
        return Outcome(success=miss < 0.02, info={"tool_end_error_m": miss})


def tool_pose(x: float, y: float, z: float) -> NDArray[np.float64]:
    """``GripperSpec`` pose with the fingertips at (x, y, z), approach axis down, closing axis along y."""
    t = np.eye(4)
    t[:3, 0] = (0.0, 1.0, 0.0)  # closing axis
    t[:3, 1] = (1.0, 0.0, 0.0)  # z x x
    t[:3, 2] = (0.0, 0.0, -1.0)  # approach
    t[:3, 3] = (x, y, z)
    return t


def shift_x(mask: NDArray[np.bool_], n: int) -> NDArray[np.bool_]:
    """``mask`` moved by ``n`` voxels along x (what leaves the grid is dropped)."""
    out = np.zeros_like(mask)
    if n > 0:
        out[n:] = mask[:-n]
    elif n < 0:
        out[:n] = mask[-n:]
    else:
        out[:] = mask
    return out


"""The push skill: Uncertainty-Informed Push Selection (UPS, after Dengler et al. 2025 / MEM) and
push execution composed from the ``Simulator`` vocabulary.

Proposal (``PushSkill.propose``), all from the belief, never from ground truth:

1. *Hidden regions*: bird's-eye-view (BEV) columns of the shelf interior holding at least
   ``min_hidden_voxels`` voxels that are not believed free (p > ``free_threshold``) and never seen
   (``EvidentialMap.never_seen``: no ray reached them where the belief keeps that record, as
   ``cnabu-map``'s does, else semantic vacuity >= ``vacuity_threshold``), and no confidently
   occupied voxel.
2. *Seeds*: up to ``seeds`` such columns, drawn without replacement with probability proportional
   to their hidden-voxel count.
3. *Occluders*: from the shelf front (y = 0) a line is traced to each seed (straight along +y, and
   from ``trace_spread_m`` left and right); the first BEV cell holding a confidently occupied voxel
   (p >= ``confidence_threshold``, argmax class not background) is the contact with the object in
   the way. The object is that cell's 8-connected BEV component of its (argmax) class.
4. *Pushes of each occluder*: a direction mainly into the shelf (+y rotated by up to
   ``max_angle_deg``, share ``into_fraction``) or sideways, away from the seed's line of sight (+-x
   rotated by up to half that; the opposite side with probability 1/4). The line through the
   footprint's centroid (jittered by a voxel across) is followed back to where it enters the
   footprint, and the tool starts so that the leading face of the tool part at the object's height
   is ``standoff_m`` from the believed contour. Length uniform in [``min_length_m``,
   ``max_length_m``], shortened to the room the tool has before a wall. Tool tip height:
   ``min(tool_height_m, low_object_fraction * object top)``, at least ``min_tool_height_m``: 2 cm by
   default (not MEM's 8.5 cm: with this downward-pointing gripper the palm, 5-8 cm above the tip,
   would push tall objects 13.5-16.5 cm up and topple them; docs/explanation/push.md has the survey), 60 % of
   the believed height for low ones (a gelatin box is 2.8 cm tall) so the tool does not pass over.
5. *Rejection*: a candidate is dropped if the tool swept along the push leaves the shelf interior
   through a side, the back or the top (the front is open; the tool *centre* may start at most
   ``START_FRONT_MARGIN_M`` in front of the opening) or covers a wall voxel, if the tool at its
   start covers a believed-occupied voxel (p > ``occupied_threshold``), or if its approach corridor
   from in front of the shelf does. Raw candidates are drawn in up to ``ROUNDS`` rounds of
   ``2 * max_samples`` until ``max_samples`` survive; at most ``max_samples`` are kept, spread over
   the occluders round-robin.

Execution (``PushSkill.execute``): fingers closed, from in front of the shelf (y = ``approach_y_m``)
straight to the start at tool height, the push at ``speed_mps``, back along the same path out of
the shelf, park; then ``settle_s`` of physics. Success: the tool reached the end of the push within
2 cm. (MSAS measures every object's displacement and which fell or left the shelf, as for every skill.)

A ``PushAction`` holds what the skill decided (start, direction, length, height, palm); the tool's
shape comes from the run's gripper and the shelf interior from the workspace (``Workspace``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from msmem_core.interfaces import Action, Category, DecisionContext, Outcome, Simulator, Skill, Workspace
from msmem_core.map.ig import shelf_wall_mask
from msmem_core.world.gripper import GripperSpec, HandDims
from msmem_core.world.meshes import stance_ratio
from msmem_core.world.scene import ObjectClass, ShelfSpec
from msmem_push.geometry import (
    Box,
    chain_room,
    corners_extent,
    footprint_sweep_hits,
    gripper_pose,
    last_on_footprint,
    leading_half_depth,
    swept_extent,
    swept_voxels,
    tool_boxes,
)

FUNNEL_STAGES = ("drawn", "in_shelf", "collision_free")
"""The stages ``PushSkill.sample`` counts its candidates after (``propose`` reports them to the step's funnel)."""
START_FRONT_MARGIN_M = 0.05
"""A push may start at most this far in front of the shelf opening (y >= -0.05 m)."""
ROUNDS = 3
"""Sampling rounds per step: a round draws 2 * max_samples raw candidates over the occluders."""
Interior = tuple[float, float, float, float, float, float]


class PushAction(Action):
    """Push with the closed gripper: its tip at ``height_m`` above the shelf floor travels from
    ``start_m`` along ``direction`` for ``length_m`` (tool frame: see ``msmem_push.geometry``)."""

    kind: str = "push"
    category: Literal["manipulation"] = "manipulation"
    start_m: tuple[float, float]
    """Tool centre (xy) at the start of the push; its leading face is half the tool depth ahead."""
    direction: tuple[float, float]
    """Unit push direction in the horizontal plane."""
    length_m: float = Field(gt=0.0, le=1.0)
    height_m: float = Field(gt=0.0, le=1.0)
    """Tool tip height above the shelf floor."""
    palm: Literal["along", "across", "forward"] = "along"
    """Gripper yaw: closing axis (and palm) along the push or across it, pointing down; or
    ``"forward"``: pointing into the shelf, pushing straight in or sideways (``msmem_push.geometry``)."""
    hand_m: HandDims | None = None
    """With ``palm="forward"``: the hand behind the fingers (width, thickness, depth[, wrist width,
    wrist length]); None: the gripper's palm. Left out of the action's record when None."""
    omit_if_none: ClassVar[tuple[str, ...]] = ("hand_m",)
    target_class: int | None = None
    """Believed class of the object the push aims at."""
    contact_m: tuple[float, float, float] | None = None
    """Believed point of the object the trace from the shelf front met first."""

    @field_validator("direction")
    @classmethod
    def _unit(cls, v: tuple[float, float]) -> tuple[float, float]:
        n = math.hypot(v[0], v[1])
        if not math.isfinite(n) or abs(n - 1.0) > 1e-6:
            raise ValueError(f"direction must be a unit vector, has length {n:.6g}")
        return v

    @model_validator(mode="after")
    def _forward_axes(self) -> PushAction:
        if self.palm == "forward" and min(math.hypot(self.direction[0] - x, self.direction[1] - y)
                                          for x, y in ((0.0, 1.0), (1.0, 0.0), (-1.0, 0.0))) > 1e-9:
            raise ValueError(f"a 'forward' push goes along +y, +x or -x, not direction {self.direction}")
        return self

    def check_start(self, interior: Interior) -> None:
        """Raise ``ValueError`` unless the start lies inside the shelf interior (x_lo, y_lo, z_lo, x_hi,
        y_hi, z_hi), or at most ``START_FRONT_MARGIN_M`` in front of its open side."""
        x_lo, y_lo, _, x_hi, y_hi, _ = interior
        x, y = self.start_m
        if not (x_lo <= x <= x_hi and y_lo - START_FRONT_MARGIN_M <= y <= y_hi):
            raise ValueError(
                f"push start_m ({x:.3f}, {y:.3f}) lies outside the shelf interior x in [{x_lo:.3f}, {x_hi:.3f}], "
                f"y in [{y_lo - START_FRONT_MARGIN_M:.3f}, {y_hi:.3f}]"
            )

    @property
    def u(self) -> NDArray[np.float64]:
        return np.asarray(self.direction, dtype=np.float64)

    @property
    def start(self) -> NDArray[np.float64]:
        return np.asarray(self.start_m, dtype=np.float64)

    @property
    def end(self) -> NDArray[np.float64]:
        return self.start + self.length_m * self.u

    def tool(self, gripper: GripperSpec) -> tuple[Box, ...]:
        """The tool's parts (half_along, half_across, z_lo, z_hi[, centres]) in the push frame for this
        ``palm``."""
        return tool_boxes(gripper, self.palm, self.hand_m, self.u)

    def swept_indices(self, workspace: Workspace) -> NDArray[np.int64]:
        """Flat indices of the voxels the tool sweeps during the push (start to end)."""
        tool = self.tool(workspace.gripper)
        return swept_voxels(workspace.grid, self.start, self.u, self.height_m, tool, self.length_m * self.u)

    def swept_volume(self, workspace: Workspace) -> NDArray[np.bool_]:
        grid = workspace.grid
        mask = np.zeros(grid.size, dtype=bool)
        mask[self.swept_indices(workspace)] = True
        return mask.reshape(grid.shape)


class PushConfig(BaseModel):
    """Parameters of UPS and of push execution (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    gripper: GripperSpec = GripperSpec()
    """The run's gripper (filled in by the runner); the tool's shape comes from it."""
    palm: Literal["along", "across", "forward"] = "along"
    """Closing axis (and the 10 cm palm) along the push (a 2 cm wide tool) or across it, the gripper
    pointing down; or ``"forward"``: the gripper pointing into the shelf, closing axis along x, the
    hand's back up, pushing straight in (+y, a share ``into_fraction``) or sideways (+-x); directions
    stay along the shelf's axes (``max_angle_deg`` does not apply). An arm reaches into a shelf this way
    (docs/explanation/robots.md); raise ``tool_height_m`` and ``min_tool_height_m`` above half the hand's thickness."""
    hand_m: HandDims | None = None
    """With ``palm: forward``: the hand behind the fingers, (width along the closing axis, thickness,
    depth) in metres, e.g. the Panda's (0.204, 0.063, 0.066), optionally followed by the width and length
    of the arm's wrist behind it (the Panda's last link, about 0.09 and 0.1). None: the gripper's palm."""
    min_length_m: float = Field(0.05, gt=0.0, le=1.0)
    max_length_m: float = Field(0.25, gt=0.0, le=1.0)
    """Push lengths are uniform in [min_length_m, max_length_m] (MEM: 5-25 cm)."""
    tool_height_m: float = Field(0.02, gt=0.0, le=1.0)
    """Tool tip height above the shelf floor. MEM pushes ~8.5 cm above the board; here the
    gripper points down and its palm (5-8 cm above the tip) touches tall objects too: at 8.5 cm, 6 of
    40 surveyed pushes toppled the object, at 2 cm none (docs/explanation/push.md)."""
    low_object_fraction: float = Field(0.6, gt=0.0, le=1.0)
    """For objects lower than tool_height_m / this, the tip goes to this fraction of their top."""
    min_tool_height_m: float = Field(0.01, gt=0.0, le=0.2, validate_default=True)
    """The tip never goes lower than this (it would drag on the shelf floor)."""
    max_samples: int = Field(80, ge=1, le=10000)
    seeds: int = Field(24, ge=1, le=10000)
    """Hidden BEV columns drawn per step as push seeds."""
    vacuity_threshold: float = Field(0.9, gt=0.0, le=1.0)
    """Semantic vacuity at or above which a voxel counts as never seen (prior: 1; one view: 0.6)."""
    confidence_threshold: float = Field(0.9, gt=0.5, lt=1.0)
    """Expected occupancy at or above which a voxel is a confidently occupied object surface."""
    occupied_threshold: float = Field(0.5, ge=0.0, lt=1.0)
    """Expected occupancy above which a voxel is believed occupied (the tool may not start there)."""
    free_threshold: float = Field(0.2, ge=0.0, lt=0.5)
    """Expected occupancy at or below which a voxel is believed free (not a hidden region)."""
    min_hidden_voxels: int = Field(2, ge=1)
    trace_spread_m: float = Field(0.08, ge=0.0, le=1.0)
    """Besides the straight trace, seeds are traced to from this far left and right on the front."""
    into_fraction: float = Field(0.4, ge=0.0, le=1.0)
    """Share of directions mainly into the shelf; the rest push sideways."""
    max_angle_deg: float = Field(30.0, ge=0.0, le=90.0)
    standoff_m: float = Field(0.01, ge=0.0, le=0.1)
    """Gap between the tool's leading face and the believed contour at the start."""
    clearance_m: float | None = Field(None, ge=0.0, le=0.2)
    """If set, a push is shortened so that the pushed object, its believed footprint moved along the
    push, stops this far short of the next confidently occupied column of another object or a side
    or back wall; a candidate left shorter than ``min_length_m`` is dropped. None: no check (the
    object may be pushed into others, which then move or fall)."""
    max_height_ratio: float | None = Field(None, gt=0.0)
    """If set, an object whose believed height exceeds this multiple of its believed footprint's
    narrowest width is not pushed (a thin, tall object turns under an oblique push and tips over its
    thin side; measured in docs/explanation/push.md, "Falls"). None: no check."""
    class_height_ratio: float | None = Field(4.0, gt=0.0)
    """If set, an object that stands thin and tall by the shape of its believed class (``stance_ratio``:
    the class's extent along the axis standing up, the one closest to the object's believed height, over
    the narrower of its other two extents) above this ratio is neither pushed nor, with
    ``chain_clearance_m``, driven by a chain. Judged from the class's shape (``Workspace.classes``), not
    from the believed footprint as ``max_height_ratio`` is, so it holds from the first view, when a
    footprint is one face deep. Refuses a standing book (5.7) or sugar box (4.4), not a cracker box
    (3.5). Without class shapes (an empty ``Workspace.classes``) no object is judged. None: no check."""
    clear_into_unknown: bool = True
    """With ``clearance_m``: whether the pushed object may move into columns not believed free
    (unknown space, where hidden objects may stand). False: only into believed-free columns (every
    interior voxel of the column at most ``free_threshold``)."""
    chain_clearance_m: float | None = Field(0.01, ge=0.0, le=0.2)
    """If set, the *chain* a push drives is predicted and the push shortened so that no object of it is
    pressed into a side or back wall: the target's believed footprint moves along the push, every
    confidently occupied object it meets starts moving with it from that point (and so on), and the
    push ends this far before the first of them reaches a wall; a candidate left shorter than
    ``min_length_m`` is dropped. Unlike ``clearance_m`` it allows pushing into other objects, only
    not a row of them into a wall. With ``max_height_ratio`` set, a chain must also not reach a thin,
    tall object. The default since it was measured (docs/explanation/push.md, "Falls"): on ``hard25`` scenes 0-9
    push-only 0 of 10 episodes with a fall against 5 of 10, as many pushes. None: no check."""
    chain_travel_m: float | None = Field(None, gt=0.0, le=0.3)
    """With ``chain_clearance_m``: an object the chain drives (pushed by another object, not by the tool)
    moves at most this far: the push is shortened to end that far after the object starts moving. The
    tool pushes 2 cm above the board, where a pushed object slides; an object pushed by another is
    pushed wherever they touch, often high, and a long way of that tips tall objects over (docs/explanation/push.md,
    "Falls"). None: no limit."""
    trip_height_ratio: float | None = Field(3.0, gt=1.0)
    """With ``chain_clearance_m``: a moving object (the target, or one the chain drives) whose believed
    height is more than this multiple of the believed height of an object it meets stops before that
    object instead of driving it: the push is shortened to end there. A tall object pushed low trips
    over a much lower one in its way and falls (docs/explanation/push.md, "Falls"). The default, with
    ``max_pushes_per_object: 1``: together they took push-only from a fall in 4 of 20 episodes
    (``hard25`` and ``mesh25`` scenes 0-9) to 0 of 20. None: no check."""
    max_pushes_per_object: int | None = Field(1, ge=1)
    """An object the skill has pushed this many times in the episode is not pushed again. It is recognised
    by its believed class and a believed footprint (with its 8 neighbours) that holds the contact point
    of an earlier push of that class, where it started or where the push left it. A tall object pushed
    again and again ends up falling (docs/explanation/push.md, "Falls"). The default (with
    ``trip_height_ratio: 3``). None: no limit."""
    speed_mps: float = Field(0.1, gt=0.0, le=1.0)
    travel_speed_mps: float = Field(0.25, gt=0.0, le=2.0)
    """Speed of the approach and the retreat."""
    approach_y_m: float = Field(-0.08, lt=0.0, ge=-1.0)
    """The approach starts (and the retreat ends) at this y in front of the shelf opening."""
    settle_s: float = Field(0.5, ge=0.0, le=10.0)

    @field_validator("min_tool_height_m")
    @classmethod
    def _forward_clears_the_floor(cls, v: float, info: ValidationInfo) -> float:
        """With ``palm: forward`` the hand (and wrist) straddle the tip's height: a tip lower than half their
        height would put them into the shelf floor, and the skill would propose nothing there."""
        if info.data.get("palm") == "forward" and "gripper" in info.data:
            hand = info.data.get("hand_m")
            _, thick, _, *wrist = hand or (0.0, info.data["gripper"].palm_width_m, 0.0)
            half = max(thick, *wrist[:1], info.data["gripper"].finger_width_m) / 2
            if v < half:
                raise ValueError(f"{v:g} puts the hand below the shelf floor: with palm 'forward' and hand_m {hand} "
                                 f"it must be at least {half:g} (half the height of the hand and wrist)")
        return v

    @field_validator("max_length_m")
    @classmethod
    def _longer(cls, v: float, info: ValidationInfo) -> float:
        lo = info.data.get("min_length_m")
        if lo is not None and v <= lo:
            raise ValueError(f"must exceed min_length_m ({lo})")
        return v

    @field_validator("approach_y_m")
    @classmethod
    def _in_front(cls, v: float) -> float:
        if v > -START_FRONT_MARGIN_M:
            raise ValueError(f"must be at most {-START_FRONT_MARGIN_M} (in front of every push start)")
        return v


def narrowest_width_cells(cells: NDArray[np.int64]) -> float:
    """A footprint's narrowest extent (cells) over 36 directions, 5 degrees apart; ``cells`` [N, 2]."""
    a = np.radians(np.arange(0, 180, 5))
    along = cells @ np.stack([np.cos(a), np.sin(a)])  # [N, 36]
    return float((along.max(axis=0) - along.min(axis=0)).min() + 1.0)


@functools.lru_cache(maxsize=8)
def _line_steps(s: float) -> NDArray[np.float64]:
    """Distances back along a push line at which ``_candidate`` looks for the footprint (read only)."""
    out = np.arange(0.0, 0.6, s / 8)
    out.flags.writeable = False
    return out


_leading_half_depth = functools.lru_cache(maxsize=1024)(leading_half_depth)
"""``leading_half_depth`` of a (hashable) tool, remembered: a proposal asks it for the same few heights."""


class _Target:
    """An occluder met by a trace: its BEV footprint, class, contact cell and the seed behind it."""

    def __init__(self, foot: NDArray[np.bool_], cls: int, contact: NDArray[np.float64], seed: NDArray[np.float64],
                 top_z: float, key: tuple[int, int]) -> None:
        self.foot, self.cls, self.contact, self.seed, self.top_z, self.key = foot, cls, contact, seed, top_z, key
        ij = np.argwhere(foot)
        self.cells = ij

    @functools.cached_property
    def width_cells(self) -> float:
        """The footprint's narrowest extent (cells) over 36 directions, 5 degrees apart."""
        return narrowest_width_cells(self.cells)

    @functools.cached_property
    def mean_cell(self) -> NDArray[np.float64]:
        """The footprint's mean cell (grid indices)."""
        return self.cells.mean(axis=0)

    @functools.cached_property
    def own(self) -> NDArray[np.bool_]:
        """The footprint and its 8 neighbours: its believed contour, or an object touching it."""
        from scipy import ndimage
        return ndimage.binary_dilation(self.foot, structure=np.ones((3, 3), dtype=bool))


@dataclass
class _Chain:
    """What ``chain_clearance_m`` predicts chains from (``PushSkill._chain_data``)."""

    labels: NDArray[np.int32]
    wall: NDArray[np.bool_]
    fragile: set[int]
    heights: dict[int, float] = field(default_factory=dict)
    """Each label's believed height above the shelf floor (m)."""
    cells: dict[int, NDArray[np.int64]] = field(default_factory=dict)
    """Each label's cells [N, 2], filled as chains reach them (shared by all candidates of a proposal)."""
    owners: dict[tuple[int, int], set[int]] = field(default_factory=dict)
    """Per target (``_Target.key``), the labels of its footprint (filled as targets are sampled)."""
    masks: dict[tuple[Any, ...], NDArray[np.bool_]] = field(default_factory=dict)
    """``owners`` as masks over labels (``own_mask``)."""

    def cells_of(self, k: int) -> NDArray[np.int64]:
        if k not in self.cells:
            self.cells[k] = np.argwhere(self.labels == k)
        return self.cells[k]

    @functools.cached_property
    def tables(self) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
        """Per label (index, 0: none), for ``geometry.chain_room``: fragile, height (inf where none), and
        every label's cells as ``cell_ij[cell_ptr[k]:cell_ptr[k + 1]]`` (in ``cells_of``'s order)."""
        n = int(self.labels.max()) + 1
        fragile = np.zeros(n, dtype=bool)
        fragile[[k for k in self.fragile if 0 <= k < n]] = True
        heights = np.full(n, np.inf)
        for k, h in self.heights.items():
            if 0 <= k < n:
                heights[k] = h
        flat = self.labels.reshape(-1)
        order = np.argsort(flat, kind="stable")  # row-major within each label, as argwhere
        ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(flat, minlength=n), out=ptr[1:])
        ij = np.stack(np.unravel_index(order, self.labels.shape), axis=-1).astype(np.int64)
        return fragile, heights, ptr, ij

    def own_mask(self, t: _Target) -> NDArray[np.bool_]:
        """The labels of target ``t``'s footprint, as a mask over labels (cached per target)."""
        key = ("mask", *t.key)
        if key not in self.masks:
            own = np.zeros(int(self.labels.max()) + 1, dtype=bool)
            own[np.unique(self.labels[t.foot])] = True
            own[0] = False
            self.masks[key] = own
        return self.masks[key]


class PushSkill(Skill):
    category: ClassVar[Category] = "manipulation"

    def __init__(self, config: PushConfig | None = None) -> None:
        self.config = config or PushConfig()
        self.tool = tool_boxes(self.config.gripper, self.config.palm, self.config.hand_m)
        """The tool's parts (for ``palm: forward``, those of a push straight in; ``_tool`` gives any direction's)."""
        self._grid_cache: dict[Any, Any] = {}
        self._pushed: list[tuple[int, NDArray[np.float64]]] = []
        """The pushes executed in this episode: target class and contact points [2, 2] (start, end) in xy."""
        self._last_step = -1

    def _tool(self, u: NDArray[np.float64]) -> tuple[Box, ...]:
        """The tool's parts in the push frame of ``u`` (they depend on it only for ``palm: forward``)."""
        if self.config.palm != "forward":
            return self.tool
        return tool_boxes(self.config.gripper, "forward", self.config.hand_m, u)

    def track(self, ctx: DecisionContext) -> None:
        """A new episode (step 0, or a step before the last one seen) forgets the pushes of the last one
        (``max_pushes_per_object``), so that one skill can serve several episodes."""
        if ctx.step == 0 or ctx.step < self._last_step:
            self._pushed.clear()
        self._last_step = ctx.step

    # ------------------------------------------------------------------------------------ proposal
    def _grid_data(self, grid: Any, shelf: ShelfSpec) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        key = (grid, shelf)
        if key not in self._grid_cache:
            c = grid.centers()
            interior = np.all((c > shelf.interior_lower) & (c < shelf.interior_upper), axis=-1)
            self._grid_cache = {key: (interior, shelf_wall_mask(grid, shelf).ravel())}
        return self._grid_cache[key]

    def propose(self, ctx: DecisionContext) -> list[Action]:
        if not ctx.manipulation_allowed:
            return []
        stages: dict[str, int] = {}
        out = self.sample(ctx.belief, ctx.shelf, ctx.rng, ctx.workspace.classes, stages)
        for stage in FUNNEL_STAGES:  # the step record's candidate funnel (0 for stages never reached)
            ctx.funnel.count(stage, stages.get(stage, 0))
        return list(out)

    def sample(self, belief: Any, shelf: ShelfSpec, rng: np.random.Generator,
               classes: tuple[ObjectClass, ...] = (), stages: dict[str, int] | None = None) -> list[PushAction]:
        """UPS: push candidates from the belief (see the module docstring); ``classes`` are the belief's
        object classes (``Workspace.classes``), whose shapes ``class_height_ratio`` judges. ``stages``
        receives the raw candidates ``drawn`` for the occluders found (none without a hidden column and
        an occluder), those ``in_shelf`` (a start and room for ``min_length_m``: ``_candidate``) and
        those ``collision_free`` (``_valid``), before the ``max_samples`` cap."""
        cfg = self.config
        stages = {} if stages is None else stages
        grid = belief.grid
        s = grid.voxel_m
        o = grid.origin
        interior, walls = self._grid_data(grid, shelf)
        p = belief.expected_occupancy()
        cls = np.argmax(belief.eta, axis=0)
        # confident object surfaces; occupied voxels of class background are shelf boards seen in
        # the interior's boundary layer, not objects
        conf = (p >= cfg.confidence_threshold) & interior & (cls != 0)
        hidden = interior & (p > cfg.free_threshold) & belief.never_seen(cfg.vacuity_threshold)
        conf_bev = conf.any(axis=2)
        count = hidden.sum(axis=2)
        seed_mask = (count >= cfg.min_hidden_voxels) & ~conf_bev
        cells = np.argwhere(seed_mask)
        if len(cells) == 0 or not conf_bev.any():
            return []
        w = count[seed_mask].astype(np.float64)
        pick = rng.choice(len(cells), size=min(cfg.seeds, len(cells)), replace=False, p=w / w.sum())
        seeds = o[:2] + (cells[pick] + 0.5) * s
        targets = self._trace(seeds, conf, conf_bev, cls, grid, shelf)
        standing = self._standing_thin(classes, shelf.interior_box[2])
        targets = [t for t in targets if not standing(t.cls, t.top_z)]
        if cfg.max_pushes_per_object is not None and self._pushed:
            targets = [t for t in targets if self.times_pushed(t.cls, t.own, grid) < cfg.max_pushes_per_object]
        if not targets:
            return []
        occupied = (p > cfg.occupied_threshold).ravel()
        blocked = None
        if cfg.clearance_m is not None:
            blocked = self._blocked(conf_bev, grid, shelf.interior_box)
            if not cfg.clear_into_unknown:
                blocked |= (interior & (p > cfg.free_threshold)).any(axis=2)
        chain = (self._chain_data(conf, cls, grid, shelf.interior_box, standing)
                 if cfg.chain_clearance_m is not None else None)
        per_target = max(2, math.ceil(2 * cfg.max_samples / len(targets)))
        groups: list[list[PushAction]] = [[] for _ in targets]
        interior_m = shelf.interior_box
        drawn = shaped = 0
        for _ in range(ROUNDS):  # in dense shelves most sideways pushes collide: sample again
            for g, t in zip(groups, targets, strict=True):
                for _ in range(per_target):
                    a = self._candidate(t, rng, grid, interior_m, blocked, chain)
                    drawn += 1
                    if a is None:
                        continue
                    shaped += 1
                    if self._valid(a, grid, walls, occupied, interior_m):
                        g.append(a)
            if sum(len(g) for g in groups) >= cfg.max_samples:
                break
        stages.update(drawn=drawn, in_shelf=shaped, collision_free=sum(len(g) for g in groups))
        out: list[PushAction] = []
        i = 0
        while len(out) < cfg.max_samples and any(i < len(g) for g in groups):
            out += [g[i] for g in groups if i < len(g)][: cfg.max_samples - len(out)]
            i += 1
        return out

    def record_push(self, action: PushAction) -> None:
        """Remember an executed push of a believed object (``max_pushes_per_object``)."""
        if action.target_class is None or action.contact_m is None:
            return
        start = np.asarray(action.contact_m[:2], dtype=np.float64)
        end = start + max(action.length_m - self.config.standoff_m, 0.0) * action.u
        self._pushed.append((action.target_class, np.stack([start, end])))

    def times_pushed(self, cls: int, own: NDArray[np.bool_], grid: Any) -> int:
        """How many executed pushes of class ``cls`` have a contact point (start or end) in the BEV cells
        ``own`` (a believed footprint and its 8 neighbours)."""
        n = 0
        for c, pts in self._pushed:
            if c != cls:
                continue
            ij = np.floor((pts - grid.origin[:2]) / grid.voxel_m).astype(np.int64)
            ok = (ij[:, 0] >= 0) & (ij[:, 0] < own.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < own.shape[1])
            n += int(own[ij[ok, 0], ij[ok, 1]].any())
        return n

    def _trace(self, seeds: NDArray[np.float64], conf: NDArray[np.bool_], conf_bev: NDArray[np.bool_],
               cls: NDArray[np.int64], grid: Any, shelf: ShelfSpec) -> list[_Target]:
        """The first confident object on the lines from the shelf front to each seed (deduplicated)."""
        from scipy import ndimage
        cfg = self.config
        s = grid.voxel_m
        o = grid.origin
        nx, ny = grid.shape[0], grid.shape[1]
        offsets = [0.0] + ([-cfg.trace_spread_m, cfg.trace_spread_m] if cfg.trace_spread_m > 0 else [])
        labels: dict[int, tuple[NDArray[np.int32], int]] = {}
        found: dict[tuple[int, int], _Target] = {}
        steps = np.linspace(0.0, 1.0, max(2, math.ceil((shelf.depth_m + 0.2) / (s / 4))))
        zs = o[2] + (np.arange(grid.shape[2]) + 1.0) * s
        for seed in seeds:
            for off in offsets:
                front = np.array([np.clip(seed[0] + off, -shelf.width_m / 2, shelf.width_m / 2), 0.0])
                pts = front + steps[:, None] * (seed - front)
                ij = np.floor((pts - o[:2]) / s).astype(np.int64)
                ok = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
                ij = ij[ok]
                hit = np.flatnonzero(conf_bev[ij[:, 0], ij[:, 1]])
                if len(hit) == 0:
                    continue
                ci, cj = ij[hit[0]]
                col = cls[ci, cj][conf[ci, cj]]
                c = int(np.bincount(col).argmax())
                if c not in labels:
                    bev = (conf & (cls == c)).any(axis=2)
                    labels[c] = ndimage.label(bev, structure=np.ones((3, 3), dtype=bool))
                lab = labels[c][0]
                key = (c, int(lab[ci, cj]))
                if key in found:
                    continue
                foot = lab == lab[ci, cj]
                col3 = conf & (cls == c) & foot[:, :, None]
                top_z = float(zs[np.nonzero(col3.any(axis=(0, 1)))[0].max()])
                contact = np.array([o[0] + (ci + 0.5) * s, o[1] + (cj + 0.5) * s, 0.0])
                top_k = np.nonzero(col3[ci, cj])[0]
                contact[2] = o[2] + (top_k.min() + top_k.max() + 1) * s / 2
                found[key] = _Target(foot, c, contact, seed, top_z, key)
        return list(found.values())

    @staticmethod
    def _blocked(conf_bev: NDArray[np.bool_], grid: Any, interior_m: Interior) -> NDArray[np.bool_]:
        """[X, Y] BEV cells a pushed object must not enter: confidently occupied object columns and the
        cells beyond the interior's sides and back (the front is open)."""
        return conf_bev | PushSkill._wall_cells(grid, interior_m)

    @staticmethod
    def _wall_cells(grid: Any, interior_m: Interior) -> NDArray[np.bool_]:
        """[X, Y] BEV cells beyond the interior's sides and back (the front is open)."""
        x_lo, _, _, x_hi, y_hi, _ = interior_m
        c = grid.origin[:2] + (np.indices(grid.shape[:2]).transpose(1, 2, 0) + 0.5) * grid.voxel_m
        return (c[..., 0] < x_lo) | (c[..., 0] > x_hi) | (c[..., 1] > y_hi)

    def _object_room(self, t: _Target, u: NDArray[np.float64], grid: Any, blocked: NDArray[np.bool_]) -> float:
        """How far the target's footprint can move along ``u`` before it enters a blocked cell, minus
        ``clearance_m``; the target's own cells and their 8 neighbours (its believed contour, or an
        object touching it) never count."""
        s = grid.voxel_m
        obstacle = blocked & ~t.own  # the target's own cells never count
        steps = np.arange(s / 2, self.config.max_length_m + self.config.clearance_m + s, s / 2)
        moved = (t.cells[None, :, :] + 0.5) + steps[:, None, None] * u[None, None, :] / s  # [T, N, 2] in cells
        ij = np.floor(moved).astype(np.int64)
        nx, ny = obstacle.shape
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < nx) & (ij[..., 1] >= 0) & (ij[..., 1] < ny)
        hit = np.zeros(inside.shape, dtype=bool)
        hit[inside] = obstacle[ij[inside][:, 0], ij[inside][:, 1]]
        first = np.flatnonzero(hit.any(axis=1))
        free = float(steps[first[0]] - s / 2) if len(first) else np.inf
        return free - float(self.config.clearance_m)

    def _standing_thin(self, classes: tuple[ObjectClass, ...], floor_z: float) -> Callable[[int, float], bool]:
        """Whether an object of class id ``c`` whose believed top is at ``top_z`` stands thin and tall by
        its class's shape (``class_height_ratio``); never without the ratio or the class's shape."""
        ratio = self.config.class_height_ratio
        seen: dict[tuple[int, float], bool] = {}  # tops are voxel-quantised: each (class, top) once

        def judge(c: int, top_z: float) -> bool:
            if ratio is None or not 1 <= c <= len(classes):
                return False
            if (c, top_z) not in seen:  # a mesh class hashes in about 0.3 ms (stance_ratio's cache)
                seen[c, top_z] = stance_ratio(classes[c - 1], top_z - floor_z) > ratio
            return seen[c, top_z]

        return judge

    def _chain_data(self, conf: NDArray[np.bool_], cls: NDArray[np.int64], grid: Any, interior_m: Interior,
                    standing: Callable[[int, float], bool]) -> _Chain:
        """Object label per BEV cell (the 8-connected components of each class's confident columns, 0 where
        none, numbered across classes), the cells beyond the interior's sides and back, and the labels
        of thin, tall objects a chain must not reach: with ``max_height_ratio`` those whose believed
        height is above that multiple of the footprint's narrowest width, and those ``standing`` judges
        thin by their class's shape (``class_height_ratio``)."""
        from scipy import ndimage
        labels = np.zeros(conf.shape[:2], dtype=np.int32)
        fragile: set[int] = set()
        heights: dict[int, float] = {}
        n = 0
        ratio, s = self.config.max_height_ratio, grid.voxel_m
        zs = np.arange(conf.shape[2])
        for c in np.unique(cls[conf]):
            col = conf & (cls == c)
            lab, k = ndimage.label(col.any(axis=2), structure=np.ones((3, 3), dtype=bool))
            free = labels == 0  # a column two classes share keeps the first label
            labels[free & (lab > 0)] = lab[free & (lab > 0)] + n
            top = np.where(col, zs[None, None, :] + 1, 0).max(axis=2)  # voxels up to the top, per column
            for i in range(1, k + 1):
                foot = lab == i
                top_z = grid.origin[2] + top[foot].max() * s
                heights[i + n] = float(top_z - interior_m[2])
                if standing(int(c), float(top_z)) or (ratio is not None and
                                                      top_z - interior_m[2] > ratio * narrowest_width_cells(
                                                          np.argwhere(foot)) * s):
                    fragile.add(i + n)
            n += k
        return _Chain(labels, self._wall_cells(grid, interior_m), fragile, heights)

    def _chain_room(self, t: _Target, u: NDArray[np.float64], grid: Any, chain: _Chain, cap: float = np.inf,
                    floor_z: float = 0.0) -> float:
        """:meth:`_chain_room_reference` in one numba pass (``geometry.chain_room``; a test compares them)."""
        cfg = self.config
        s = grid.voxel_m
        far = min(cfg.max_length_m, cap) + float(cfg.chain_clearance_m or 0.0) + s
        steps = np.arange(s / 2, far, s / 2)
        fragile, heights, ptr, ij = chain.tables
        return float(chain_room(
            t.cells, float(t.top_z - floor_z), np.asarray(u, dtype=np.float64), steps, s, chain.labels, chain.wall,
            chain.own_mask(t), fragile, heights, ptr, ij, float(cfg.chain_clearance_m or 0.0),
            float(cfg.trip_height_ratio or 0.0), cfg.trip_height_ratio is not None, float(cfg.chain_travel_m or 0.0),
            cfg.chain_travel_m is not None))

    def _chain_room_reference(self, t: _Target, u: NDArray[np.float64], grid: Any, chain: _Chain,
                              cap: float = np.inf, floor_z: float = 0.0) -> float:
        """How far the target can be pushed along ``u`` before an object of the chain it drives enters a
        wall cell or meets a thin, tall object (or, with ``trip_height_ratio``, a moving object meets a
        much lower one), minus ``chain_clearance_m``; ``floor_z`` is the shelf floor's height. Each moving object's
        footprint is swept along ``u``; an object it meets starts moving when the target has travelled
        as far as that contact (the earliest over the objects that meet it); every object moves the
        rest of the push."""
        cfg = self.config
        labels, wall, fragile = chain.labels, chain.wall, chain.fragile
        s = grid.voxel_m
        # only a room below ``cap`` (the travel the push may have anyway) changes the push: look no further
        far = min(cfg.max_length_m, cap) + float(cfg.chain_clearance_m or 0.0) + s
        steps = np.arange(s / 2, far, s / 2)
        start: dict[int, float] = {}  # object label -> target travel at which it starts moving
        if t.key not in chain.owners:
            chain.owners[t.key] = set(np.unique(labels[t.foot]).tolist()) - {0}
        own = chain.owners[t.key]  # the target (its component)
        queue: list[tuple[float, int]] = [(0.0, 0)]
        room = np.inf
        while queue:
            queue.sort()
            e, k = queue.pop(0)
            if e >= room:
                break
            cells = t.cells if k == 0 else chain.cells_of(k)  # 0: the target itself
            height = t.top_z - floor_z if k == 0 else chain.heights.get(k, 0.0)
            at_wall, first = footprint_sweep_hits(cells, u, steps, s, labels, wall)
            if at_wall >= 0:
                room = min(room, e + float(steps[at_wall] - s / 2))
            for j in np.flatnonzero(first >= 0).tolist():
                if j in own or j == k:
                    continue
                d = e + float(steps[first[j]] - s / 2)
                trips = (cfg.trip_height_ratio is not None
                         and height > cfg.trip_height_ratio * chain.heights.get(j, np.inf))
                if j in fragile or trips:  # a thin, tall object would be pushed or trip the mover: stop before it
                    room = min(room, d)
                elif d < start.get(j, np.inf) and d < room:
                    start[j] = d
                    queue = [(q, i) for q, i in queue if i != j] + [(d, j)]
                    if cfg.chain_travel_m is not None:  # a driven object moves at most this far
                        room = min(room, d + cfg.chain_travel_m + float(cfg.chain_clearance_m or 0.0))
        return room - float(cfg.chain_clearance_m or 0.0)

    def _candidate(self, t: _Target, rng: np.random.Generator, grid: Any, interior_m: Interior,
                   blocked: NDArray[np.bool_] | None = None, chain: _Chain | None = None) -> PushAction | None:
        cfg = self.config
        s = grid.voxel_m
        o = grid.origin
        centre = o[:2] + (t.mean_cell + 0.5) * s
        # the forward tool pushes exactly along the shelf's axes (its parts stay boxes of the push frame)
        forward = cfg.palm == "forward"
        max_a = math.radians(cfg.max_angle_deg)
        if rng.random() < cfg.into_fraction:
            ang = math.pi / 2 + (0.0 if forward else rng.uniform(-max_a, max_a))
            q = np.array([centre[0] + rng.uniform(-s, s), centre[1]])
        else:
            away = -1.0 if t.seed[0] > centre[0] else 1.0
            side = away if rng.random() < 0.75 else -away
            ang = (0.0 if side > 0 else math.pi) + (0.0 if forward else rng.uniform(-max_a / 2, max_a / 2))
            q = np.array([centre[0], centre[1] + rng.uniform(-s, s)])
        u = np.array([math.cos(ang), math.sin(ang)])
        if forward:
            u = np.round(u)
        # follow the line through the object's centre back (against u) to where it enters the footprint
        ts = _line_steps(s)
        last = last_on_footprint(float(q[0]), float(q[1]), float(u[0]), float(u[1]), ts, float(o[0]), float(o[1]), s,
                                 t.foot)
        if last < 0:
            return None
        t_entry = ts[last] + s / 8
        height = max(cfg.min_tool_height_m, min(cfg.tool_height_m, cfg.low_object_fraction * t.top_z))
        tool = self._tool(u)
        half_depth = _leading_half_depth(tool, height, t.top_z)
        start = q - (t_entry + cfg.standoff_m + half_depth) * u
        x_lo, y_lo, _, x_hi, y_hi, _ = interior_m
        if not (x_lo <= start[0] <= x_hi and y_lo - START_FRONT_MARGIN_M <= start[1] <= y_hi):
            return None
        # longest push whose tool stays inside the shelf (the wall test in _valid is then rarely hit)
        cx_lo, cx_hi, _, cy_hi = corners_extent(start, u, tool)
        room = np.inf
        if u[0] > 1e-9:
            room = min(room, float((x_hi - cx_hi) / u[0]))
        elif u[0] < -1e-9:
            room = min(room, float((cx_lo - x_lo) / -u[0]))
        if u[1] > 1e-9:  # in front of the shelf is open
            room = min(room, float((y_hi - cy_hi) / u[1]))
        hi_len = min(cfg.max_length_m, room)
        if cfg.max_height_ratio is not None and t.top_z - interior_m[2] > cfg.max_height_ratio * t.width_cells * s:
            return None
        if blocked is not None:  # the object moves once the tool has closed the standoff gap
            hi_len = min(hi_len, self._object_room(t, u, grid, blocked) + cfg.standoff_m)
        if chain is not None and hi_len >= cfg.min_length_m:
            hi_len = min(hi_len, self._chain_room(t, u, grid, chain, hi_len - cfg.standoff_m, interior_m[2])
                         + cfg.standoff_m)
        if hi_len < cfg.min_length_m:
            return None
        return PushAction(
            start_m=(float(start[0]), float(start[1])),
            direction=(float(u[0]), float(u[1])),
            length_m=float(rng.uniform(cfg.min_length_m, hi_len)),
            height_m=float(height),
            palm=cfg.palm,
            hand_m=cfg.hand_m if cfg.palm == "forward" else None,
            target_class=t.cls,
            contact_m=tuple(float(v) for v in t.contact),
        )

    def _valid(self, a: PushAction, grid: Any, walls: NDArray[np.bool_], occupied: NDArray[np.bool_],
               interior_m: Interior) -> bool:
        """Inside the shelf, no wall voxel swept, no believed-occupied voxel at the start or on the approach."""
        x_lo, _, z_lo, x_hi, y_hi, z_hi = interior_m
        tool = self._tool(a.u)
        lo, hi = swept_extent(a.start, a.u, a.height_m, tool, a.length_m * a.u)
        if lo[0] < x_lo or hi[0] > x_hi or hi[1] > y_hi or lo[2] < z_lo or hi[2] > z_hi:  # front is open
            return False
        if occupied[swept_voxels(grid, a.start, a.u, a.height_m, tool)].any():  # the most common rejection
            return False
        if walls[swept_voxels(grid, a.start, a.u, a.height_m, tool, a.length_m * a.u)].any():
            return False
        approach = np.array([a.start[0], self.config.approach_y_m])
        corridor = swept_voxels(grid, approach, a.u, a.height_m, tool, a.start - approach)
        return not (occupied[corridor].any() or walls[corridor].any())

    # ----------------------------------------------------------------------------------- execution
    def waypoints(self, action: Action) -> NDArray[np.float64]:
        """The gripper poses [3, 4, 4] of a push: in front of the shelf (``approach_y_m``), at the start,
        at the end (it returns the same way)."""
        a = action if isinstance(action, PushAction) else PushAction.model_validate(action.model_dump())
        approach = np.array([a.start[0], self.config.approach_y_m])
        return np.stack([gripper_pose(xy, a.height_m, a.u, a.palm) for xy in (approach, a.start, a.end)])

    def tool_path(self, action: Action, workspace: Workspace) -> NDArray[np.float64]:
        return self.waypoints(action)

    def execute(self, sim: Simulator, action: Action, ctx: DecisionContext) -> Outcome:
        cfg = self.config
        a = action if isinstance(action, PushAction) else PushAction.model_validate(action.model_dump())
        a.check_start(ctx.shelf.interior_box)
        approach, start, end = self.waypoints(a)
        sim.move_gripper([approach, start], opening_m=0.0, speed_mps=cfg.travel_speed_mps)
        reached = sim.move_gripper([end], speed_mps=cfg.speed_mps)
        sim.move_gripper([start, approach], speed_mps=cfg.travel_speed_mps)
        sim.park_gripper()
        if cfg.settle_s > 0:
            sim.step(cfg.settle_s)
        self.record_push(a)
        miss = float(np.linalg.norm(reached[:2, 3] - a.end))
        return Outcome(success=miss < 0.02, info={"tool_end_error_m": miss})

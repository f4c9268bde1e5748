"""The grasp skill: Uncertainty-informed Grasp Selection (UGS, paper sec. UGS) and grasp execution
composed from the ``Simulator`` vocabulary.

Every step (``GraspSkill.track``, called by MSAS before proposals, also when manipulation is not
allowed): FPP of the current belief from the views visited since the last manipulation (before the
first manipulation also one virtual front camera per viewpoint grid; after one, only cameras that
really looked, since the rest of the belief may be an effect model's unconfirmed prediction)
(``fpp.frontier_points``, ``num_points`` points) -> per-point
evidential grasps (FE-vMF with the shipped weights; if none are installed, the geometric fallback of
``msmem_grasp.geometric``, logged once as a warning and recorded in every action's ``predictor``;
weights named in ``weights`` are loaded when the skill is built and never fall back)
-> FE-UMGF buffer update (``msmem_grasp.fusion``). A manipulation (``ctx.last_manipulation``) clears
the buffer, and nothing is fused until a view has been taken after it. Nothing is ever read from
ground truth.

Executable grasps (``GraspSkill.propose``, only when manipulation is allowed), from the fused buffer:

1. *Evidence*: E[q] >= ``min_affordance`` and uncertainty 2/S <= ``max_uncertainty``; the
   ``preselect`` best by E[q] go on.
2. *Pose*: approach a = mu_a_hat projected orthogonal to mu_b (eq. proj); centre c + (w/2) b with the
   fused width w; frame (b, a x b, a) (``fevmf.executable_grasp``); fingers opened to
   ``w + opening_margin_m`` (at most the gripper's 8 cm).
3. *Reachable from the open front*: the approach may not point out of the shelf or up
   (a_y >= -sin 15 deg, a_z <= sin 15 deg). The gripper comes from ``outside_y_m`` in front of the
   shelf: straight in (+y) to the pre-grasp pose (the first of ``approach_distances_m`` back along
   a that is free), then along a to the grasp. A top-down grasp thus enters above the objects in
   front of the target; a grasp from the front slides in. After closing it lifts and retreats
   straight out of the front (-y) to ``retreat_y_m``, where the object is past the shelf. The lift is
   ``lift_m`` (3 cm), raised (up to ``max_lift_m`` and the room under the shelf top) to the lowest
   height at which the object and the gripper leave without meeting a believed object, if any; where
   the shelf top leaves less room than ``lift_m``, it is that room, down to ``min_lift_m`` (by default
   0: the object slides out), and only for an object the fingers open ``short_lift_margin_m`` (2 cm)
   wider than.
4. *Collision-free in the belief*: the gripper's fingers and palm (``GripperSpec`` boxes, shrunk
   by ``tolerance_m``; on the way in to the pre-grasp pose as they are, ``move_in_clearance_m``), at
   the grasp and swept along the approach path (sampled every half voxel),
   may not touch a voxel that is believed occupied (p > 0.5), unknown (vacuity >= 0.9 and
   |p - 0.5| < 0.1), a shelf board, or outside the grid other than in front of the shelf. On the
   final stretch along a and at the grasp, the target's own region (its class's connected component
   at the contact, clipped to the opening box, ``planning.Objects.region``) is exempt: the fingers
   slide along it and close on it (its voxels reach up to a voxel beyond its surface). The lift and the retreat are
   not tested against objects (what they disturb is the effect model's prediction) but the lifted
   target's believed top and the gripper must stay ``clearance_m`` under the shelf top.
   The tests run in one numba kernel (``planning.sweep_hits``, stopping at the first blocked
   point): the test at the grasp for all preselected candidates at once, before the loop over them
   (steps 4-5); the approach paths only for the candidates that pass it, one at a time.
5. *Diversity*: at most ``max_per_object`` grasps per believed object (component), the ``top_k``
   best by E[q].

Execution (``GraspSkill.execute``): open, approach (travel speed to the pre-grasp, slow along a),
close (``set_gripper(0)``: the fingers stop on contact and keep squeezing with the gripper's
force), lift, retreat out of the shelf front, then ``held_object()``: the grasp succeeded only if
an object is still between both fingers, held by friction alone (no attachment constraint). On
success the object is taken out of the workspace (``remove_object``). Open, park, settle. The
outcome reports the removed object (MSAS measures the other objects' displacement and which fell or
left the shelf, as for every skill).

A ``GraspAction`` holds what the skill decided (pose, width, opening, approach and retreat); the
gripper it is executed with and the shelf come from the workspace (``Workspace``). Stages of
``track`` are spans (``FPP (frontier points)``, ``FE-vMF inference`` or ``geometric grasp
predictor``, ``FE-UMGF fusion``) that a tracer such as ``msmem perf step`` times.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from msmem_core.interfaces import Action, Category, DecisionContext, Outcome, Simulator, Skill, Workspace
from msmem_core.map.belief import EvidentialMap
from msmem_core.util.trace import span
from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import F64
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec, HandDims
from msmem_core.world.scene import ObjectClass, Part, ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig
from msmem_grasp.fpp import FPPConfig, frontier_points, virtual_front_views
from msmem_grasp.fusion import FusionConfig, GraspBuffer, GraspHypotheses
from msmem_grasp.geometric import GeometricConfig, predict_geometric
from msmem_grasp.planning import (
    Objects,
    blocked_mask,
    carried_way,
    clear_under_top,
    fill_down,
    gripper_points,
    gripper_points_batch,
    mark_swept,
    path_offsets,
    segment_paths,
    sweep_hits,
    swept_indices,
    way_out_meets,
)

log = logging.getLogger("msmem.grasp")
FUNNEL_STAGES = ("fused", "confident", "preselected", "turned", "from_front", "on_object", "free_at_grasp",
                 "collision_free", "under_top", "clear_exit")
"""The stages ``GraspSkill.executable`` counts the candidates after (``propose`` reports them to the step's funnel).
Each count is at most the one before, except ``turned``: the preselected grasps with their turned twins
(``turn_to``; ``roll: both`` doubles it)."""
Vec3 = tuple[float, float, float]
_SIN15 = math.sin(math.radians(15.0))
_WARNED: set[str] = set()


TURN_DEG = 45.0
"""A grasp is turned towards a direction only if its turned approach comes within this of it."""
APPROACH_BATCH = 64
"""Candidates whose ways in ``GraspSkill.executable`` plans at once (in test order, as they are reached)."""
TILT_DEG = (20.0, 40.0)
"""How far below horizontal the ``sides-down`` approaches point."""
TURN_DIRECTIONS: dict[str, tuple[tuple[float, float, float], ...]] = {
    "front": ((0.0, 1.0, 0.0),), "sides": ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)),
    "sides-down": tuple((x * math.cos(math.radians(t)), 0.0, -math.sin(math.radians(t)))
                        for t in TILT_DEG for x in (1.0, -1.0))}
"""The approach directions ``GraspConfig.turn_to`` names: straight into the shelf; along the shelf either way;
along the shelf and tilted down by each of ``TILT_DEG``."""


def turn_about(b: F64, direction: tuple[float, float, float] | F64) -> tuple[F64, NDArray[np.bool_]]:
    """Grasps with closing axes ``b`` [N, 3] turned about them to approach as nearly along the unit
    ``direction`` as each axis allows: the direction with its component along b taken out, normalised.
    Returns (approaches [N, 3], turned [N]): only where that approach is within ``TURN_DEG`` of the
    direction (the closing axis at least 45 deg off it) is a grasp turned; its other rows are zero."""
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    d = np.asarray(direction, dtype=np.float64)
    t = d[None, :] - (b @ d)[:, None] * b
    n = np.linalg.norm(t, axis=-1, keepdims=True)  # = the turned approach's component along the direction
    ok = n[:, 0] >= math.cos(math.radians(TURN_DEG)) - 1e-12
    out = np.zeros_like(b)
    out[ok] = t[ok] / n[ok]
    return out, ok


class GraspAction(Action):
    """Grasp with the parallel-jaw gripper at ``pose`` (``GripperSpec`` frame: x = closing axis b,
    z = approach a, origin between the fingertips), fingers opened to ``opening_m``; reached through
    ``approach_m`` (gripper origins, orientation of ``pose``), then lift and retreat through ``retreat_m``."""

    kind: str = "grasp"
    category: Literal["manipulation"] = "manipulation"
    pose: tuple[tuple[float, float, float, float], ...]
    """4x4 gripper pose at the grasp (row-major)."""
    width_m: float = Field(gt=0.0, le=0.3)
    """Believed object width between the contacts."""
    opening_m: float = Field(gt=0.0, le=0.3)
    contact_m: Vec3
    """The grasp's contact point (FE-UMGF cluster centre)."""
    target_class: int | None = None
    """Believed class of the object at the contact."""
    approach_m: tuple[Vec3, ...] = ()
    """Gripper origins before the grasp, from outside the shelf to the pre-grasp pose."""
    retreat_m: tuple[Vec3, ...] = ()
    """Gripper origins after closing: the lift, then out of the shelf front."""
    affordance: float = Field(0.0, ge=0.0, le=1.0)
    """Fused E[q]."""
    uncertainty: float = Field(1.0, ge=0.0, le=1.0)
    """Fused 2/S."""
    predictor: str = ""
    """What predicted the grasp evidence: ``fe-vmf:<weights>`` or ``geometric``."""
    hand_m: HandDims | None = None
    """The hand (and wrist) behind the fingers in place of the gripper's palm (``GraspConfig.hand_m``);
    left out of the action's record when None."""
    omit_if_none: ClassVar[tuple[str, ...]] = ("hand_m",)

    @field_validator("pose")
    @classmethod
    def _rigid(cls, v: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
        m = np.asarray(v, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError("pose must be a finite 4x4 matrix")
        r = m[:3, :3]
        if np.abs(r.T @ r - np.eye(3)).max() > 1e-5 or np.linalg.det(r) < 0 or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise ValueError("pose must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        return v

    @property
    def matrix(self) -> F64:
        return np.asarray(self.pose, dtype=np.float64)

    def at(self, origin: Vec3 | F64) -> F64:
        """The grasp's orientation at another gripper origin."""
        m = self.matrix.copy()
        m[:3, 3] = origin
        return m

    def swept_indices(self, workspace: Workspace) -> NDArray[np.int64]:
        """Flat voxel indices the workspace's gripper covers: open along the approach, closed to the
        width while lifting and retreating (the grasped object's own sweep is not included)."""
        return np.flatnonzero(self._swept_mask(workspace.grid, workspace.gripper))

    def swept_volume(self, workspace: Workspace) -> NDArray[np.bool_]:
        return self._swept_mask(workspace.grid, workspace.gripper).reshape(workspace.grid.shape)

    def _swept_mask(self, grid: GridSpec, gripper: GripperSpec) -> NDArray[np.bool_]:
        """The flat grid mask of ``swept_indices``."""
        s = grid.voxel_m
        r = self.matrix[:3, :3]
        grasp = self.matrix[:3, 3]
        app = path_offsets(np.array([*self.approach_m, grasp]), s / 2)
        ret = path_offsets(np.array([grasp, *self.retreat_m]), s / 2)
        mask = np.zeros(grid.size, dtype=bool)
        mark_swept(mask, grid, r, gripper_points(gripper, self.opening_m, s / 2, hand_m=self.hand_m), app)
        mark_swept(mask, grid, r, gripper_points(gripper, self.width_m, s / 2, hand_m=self.hand_m), ret)
        return mask


def narrowest_width_m(part: Part) -> float | None:
    """The narrowest horizontal width of a solid part standing as in its object frame: a box's shorter
    side, a cylinder's diameter (the part turned about the vertical only); None for a mesh piece or a
    tilted part."""
    qx, qy, _, _ = part.quat_xyzw
    if part.kind == "convex" or abs(qx) > 1e-9 or abs(qy) > 1e-9:
        return None
    return float(min(part.size_m[:2])) if part.kind == "box" else 2.0 * float(part.size_m[0])


def too_wide(cls: ObjectClass, opening_m: float) -> bool:
    """Whether every part of ``cls`` is a solid box or cylinder wider at its narrowest than ``opening_m``
    (``GraspConfig.wider_than_opening``)."""
    widths = [narrowest_width_m(p) for p in cls.parts]
    return bool(widths) and all(w is not None and w > opening_m for w in widths)


class GraspConfig(BaseModel):
    """Parameters of UGS and of grasp execution (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    gripper: GripperSpec = GripperSpec()
    """The run's gripper (filled in by the runner)."""
    camera: CameraConfig = CameraConfig()
    """The run's camera (FPP casts its rays)."""
    viewpoints: ViewpointConfig = ViewpointConfig()
    """The run's viewpoints (filled in by the runner): the virtual front cameras are theirs."""
    seed: int = 0
    """Seed of the FPP point sampling (the run's seed; each step draws its own from it)."""
    predictor: Literal["auto", "fe-vmf", "geometric"] = "auto"
    """auto: FE-vMF with the shipped weights if they load, else the geometric fallback (said once); named
    ``weights`` must load. fe-vmf: the weights must load. geometric: always the fallback."""
    weights: Path | None = None
    """FE-vMF weights (None: the shipped ``msmem_grasp/weights/fe_vmf.pt``). Weights named here are
    loaded when the skill is built; weights that do not load (hash, format, non-finite tensors) refuse
    the run, naming the file and the reason."""
    num_points: int = Field(3072, ge=16, le=100_000)
    """FPP points per step (the paper samples 1e4 on a GPU; FE-vMF's training clouds have 4096)."""
    ray_stride_px: int = Field(4, ge=1, le=64)
    """FPP casts every n-th pixel of each camera."""
    fusion: FusionConfig = FusionConfig()
    after_manipulation: Literal["clear", "confirm"] = "clear"
    """What a manipulation does to the FE-UMGF buffer. clear: it is emptied (grasps fused on the
    geometry before it are no evidence about the scene now). confirm: the first update after it keeps
    only the grasps its view's predictions match (the paper's fusion; docs/explanation/grasp.md)."""
    geometric: GeometricConfig = GeometricConfig()
    min_affordance: float = Field(0.5, ge=0.0, le=1.0)
    """Grasps with a lower fused E[q] are not executed."""
    max_uncertainty: float = Field(0.5, gt=0.0, le=1.0)
    """Grasps with 2/S above this are not executed (a single fresh FE-vMF prediction has S >= 2)."""
    preselect: int = Field(300, ge=1)
    """Best grasps by E[q] that are checked for reachability and collisions."""
    top_k: int = Field(40, ge=1)
    """Executable grasps proposed per step."""
    max_per_object: int = Field(4, ge=1)
    """At most this many proposals per believed object."""
    opening_margin_m: float = Field(0.02, ge=0.0, le=0.1)
    """Fingers open to the fused width plus this (at most the gripper's opening)."""
    min_width_m: float = Field(0.015, ge=0.0)
    """Narrower fused widths (edges, handles) are not executed."""
    tolerance_m: float = Field(0.003, ge=0.0, le=0.01)
    """The gripper's boxes are shrunk by this in the collision test (voxelisation slack)."""
    approach_distances_m: tuple[float, ...] = (0.03, 0.05, 0.08)
    """The pre-grasp pose is the first of these distances back along the approach that is free."""
    move_in_clearance_m: float | None = Field(0.0, ge=0.0, le=0.03)
    """The open gripper's boxes are grown by this (instead of shrunk by ``tolerance_m``) in the test of
    its way in, straight into the shelf to the pre-grasp pose, where it passes over and beside the objects
    in front at full travel speed; None: shrunk by ``tolerance_m`` as in every other test. A tilted
    gripper under the shelf top has a few millimetres between a box's top edge and the board: with the
    shrunk boxes a finger corner that catches the edge, or a palm that meets the board, passes the test.
    0 (the default): the boxes as they are (docs/lab/2026-12-06-tilted-grasps)."""
    outside_y_m: float = Field(-0.12, lt=0.0, ge=-1.0)
    """The approach starts this far in front of the shelf opening (y = 0)."""
    lift_m: float = Field(0.03, ge=0.0, le=0.2)
    """Lift after closing (at least); raised up to ``max_lift_m`` (and the room under the shelf top)
    when that lets the object leave without meeting a believed object."""
    max_lift_m: float = Field(0.10, ge=0.0, le=0.5)
    min_lift_m: float = Field(0.0, ge=0.0, le=0.2)
    """Where the room under the shelf top is less than ``lift_m``, the lift shrinks to that room
    (whole voxels) down to this; at ``lift_m`` or above such grasps are not proposed. At 0 (the
    default) an object nearly as tall as the shelf (a 26 cm bottle under a 28 cm top) slides out held
    just above the floor, or along it, if ``short_lift_margin_m`` allows (docs/explanation/grasp.md,
    "Tall objects")."""
    short_lift_margin_m: float | None = Field(0.02, ge=0.0, le=0.08)
    """A grasp lifted less than ``lift_m`` is proposed only when the fingers can open at least this much
    wider than the grasped width (``width + short_lift_margin_m`` within the gripper's opening); None:
    any width. Such grasps are near the top of an object tall for the shelf, where the fingers come
    down over it with little room. Chosen on ``tune10`` with ``min_lift_m`` 0: against the 3 cm
    minimum lift, grasp candidates at 62-70 % of the allowed steps instead of 31 %, twice the objects
    taken out, 2-D semantic mIoU +0.026 (grasp-only) and +0.031 (``ours``) per scene, 2 episodes of 10
    with a fall instead of none; against any width, +0.026 and +0.051 and 2 falls instead of 3 and 4."""
    wider_than_opening: Literal["keep", "skip"] = "skip"
    """Candidates on a believed object whose class is too wide for the fingers everywhere: every part a
    solid upright box or cylinder wider at its narrowest than the gripper's maximum opening (of the
    built-in classes the wood block, 8.5 cm; the tuna and master chef cans; the pudding box). No
    horizontal closing spans such a part, so such a grasp slips or stops on it. ``skip`` (the default)
    drops them before the collision tests (a class whose shape is not known, or with a mesh or tilted
    part, is kept); ``keep`` proposes them as any other. No grasp on the wood block held in the committed
    step records (5 touched it, 2 more closed on nothing where it had stood); on ``tune10`` ``skip``
    changes no episode, in Table I the four that grasped the wood block, each then holding every grasp
    (docs/lab/2026-12-06-failed-grasps)."""
    exit_margin_m: float = Field(0.02, ge=0.0, le=0.1)
    """The grasped object's own component (``planning.Objects``), at any height in the columns within this
    of the footprint of the part the fingers hold (its region), is carried out with it: it must fit under
    the shelf top and does not stop it on its way out (``GraspSkill._carried``; docs/explanation/grasp.md, "Where grasp
    candidates go")."""
    blocked_exit: Literal["lift_m", "skip"] = "skip"
    """When no lift up to ``max_lift_m`` carries the grasped object out of the front without meeting a
    believed-occupied voxel of another object: ``skip`` (the default, chosen on ``tune10``) does not
    propose the grasp; ``lift_m`` proposes it anyway, at the minimum lift (what it drags along is the
    effect model's prediction). docs/explanation/grasp.md, "Grasps that drag a
    neighbour out"."""
    retreat_y_m: float = Field(-0.30, lt=0.0, ge=-2.0)
    """The gripper retreats to this y: the largest object (16 cm) is then past the opening."""
    clearance_m: float = Field(0.005, ge=0.0, le=0.05)
    """The lifted target's believed top stays this far under the shelf top."""
    occupied_threshold: float = Field(0.5, ge=0.0, lt=1.0)
    """Expected occupancy above which a voxel is believed occupied (objects, collisions)."""
    unknown_vacuity: float = Field(0.9, gt=0.0, le=1.0)
    """A voxel is unknown (the gripper may not enter it) with semantic vacuity at or above this ..."""
    unknown_band: float = Field(0.1, ge=0.0, le=0.5)
    """... and expected occupancy within this of 0.5."""
    travel_speed_mps: float = Field(0.25, gt=0.0, le=2.0)
    """Speed from in front of the shelf to the pre-grasp pose."""
    approach_speed_mps: float = Field(0.05, gt=0.0, le=1.0)
    """Speed along the approach from the pre-grasp pose to the grasp."""
    lift_speed_mps: float = Field(0.05, gt=0.0, le=1.0)
    retreat_speed_mps: float = Field(0.1, gt=0.0, le=1.0)
    """Speed of the retreat out of the shelf with the object."""
    settle_s: float = Field(0.5, ge=0.0, le=10.0)
    """Physics after parking (objects come to rest before MSAS reads their poses)."""
    max_object_radius_m: float = Field(0.10, gt=0.0, le=1.0)
    """The target's region reaches at most this far across the closing axis (same-class neighbours
    touching it stay out)."""
    hand_m: HandDims | None = None
    """An arm's hand behind the fingers, in place of the gripper's palm in every collision test and
    swept volume: (width along the closing axis, thickness, depth along the approach[, wrist width,
    wrist length]); the Panda's is (0.204, 0.063, 0.066). None: the gripper's palm."""
    min_height_m: float = Field(0.0, ge=0.0, le=0.5)
    """Grasps centred lower than this above the shelf floor are not proposed: a hand pointing into the
    shelf needs half its thickness and the arm's collision margin (the Panda: 0.045)."""
    max_approach_deg: float = Field(180.0, gt=0.0, le=180.0)
    """Largest angle between a grasp's approach and straight into the shelf (+y); 180: any approach the
    open front allows (step 3). An arm whose hand cannot come from above in the shelf needs a small
    one (docs/explanation/robots.md)."""
    turn_to: tuple[Literal["front", "sides", "sides-down"], ...] = ("front", "sides", "sides-down")
    """Each grasp is also proposed turned about its closing axis to approach from these directions (right
    after it): ``front`` straight into the shelf (+y), ``sides`` along the shelf either way (+x, -x),
    horizontal, ``sides-down`` the same tilted down by 20 and by 40 deg (past the neighbours beside the
    target; the open gripper is then taller on its way in: see ``move_in_clearance_m``). The same contacts,
    width and evidence, reached another way; the collision, reach and exit
    tests keep what fits. A grasp is turned towards a direction only if its turned approach comes within
    45 deg of it (its closing axis at least 45 deg off it). Empty: the predicted approaches only. Chosen on
    ``tune10`` (grasp-only and ``ours``, 40 steps): ``front`` and ``sides`` against none, 41 of 43 grasps
    held against 32 of 41, two episodes of 20 with a fall against four, 2-D semantic mIoU +0.020 and
    +0.015 per scene; ``sides-down`` added (with ``move_in_clearance_m`` 0), grasp candidates at 93-95 %
    of the allowed steps against 68-75 %, 71 of 73 grasps took their object out, no episode with a fall,
    2-D semantic mIoU +0.165 and +0.139 per scene (docs/lab/2026-12-06-tilted-grasps).
    docs/explanation/grasp.md, "Grasps turned about their closing axis"."""
    twins: Literal["interleaved", "last", "first"] = "interleaved"
    """Where the turned twins stand in the order the tests after ``free_at_grasp`` take (and so which fill
    ``max_per_object`` and ``top_k``): ``interleaved``, each right after its grasp, best E[q] first;
    ``last``, after every grasp as predicted, so that every grasp proposed without twins is proposed with
    them; ``first``, before every grasp as predicted. docs/explanation/grasp.md."""
    funnel: Literal["until-full", "every-candidate"] = "until-full"
    """How far the tests after ``free_at_grasp`` go. until-full: a candidate is planned only while its object
    has fewer than ``max_per_object`` proposals and fewer than ``top_k`` are found, so ``collision_free``,
    ``under_top`` and ``clear_exit`` count the candidates tested. every-candidate: every candidate goes
    through every test, so that each count says what its test removed (slower; the proposals are the same)."""
    roll: Literal["as-predicted", "back-up", "both"] = "as-predicted"
    """``back-up``: a grasp whose gripper y axis (approach x closing axis) points down is turned 180 deg
    about its approach (the same grasp: the fingers swap), so the hand's back, where an arm's wrist
    camera rides, faces up. ``both``: every grasp is proposed as predicted and turned (the turned one
    right after it), and the robot's reach check keeps the one its arm can follow."""


@dataclass
class Candidates:
    """Grasps of the buffer that passed the evidence, reach and width tests (``GraspSkill.candidates``)."""

    grasps: GraspHypotheses
    width: F64
    opening: F64
    poses: F64
    """[N, 4, 4] gripper poses at the grasp."""
    objects: Objects
    label: NDArray[np.int64]
    """Believed object (component) at each contact; <= 0: none."""
    blocked: NDArray[np.bool_]
    """Flat mask of voxels the gripper may not enter."""
    p: NDArray[np.floating]
    """Expected occupancy."""
    top: float
    """Highest z the lifted object and gripper may reach."""
    twin: NDArray[np.bool_]
    """Which candidates are turned twins (``turn_to``)."""


class GraspSkill(Skill):
    category: ClassVar[Category] = "manipulation"

    def __init__(self, config: GraspConfig | None = None) -> None:
        self.config = config or GraspConfig()
        self.buffer = GraspBuffer(self.config.fusion)
        self._model: Any = None
        self._predictor: str | None = None
        self._tracked: tuple[int, EvidentialMap] | None = None
        """(step, belief) of the last FE-UMGF update."""
        self._manipulated = -1
        """``last_manipulation`` of the context the buffer was built under."""
        self._confirm = False
        """The next update confirms the buffer (``after_manipulation: confirm``)."""
        if self.config.predictor != "geometric" and (self.config.weights is not None
                                                     or self.config.predictor == "fe-vmf"):
            _ = self.predictor  # weights the user asked for load now, before any episode, or refuse the run

    # ------------------------------------------------------------------------------ prediction
    @property
    def predictor(self) -> str:
        """``fe-vmf:<weights file>`` or ``geometric`` (loads the weights on first use)."""
        if self._predictor is None:
            cfg = self.config
            if cfg.predictor == "geometric":
                self._predictor = "geometric"
            else:
                from msmem_grasp.weights import SHIPPED_WEIGHTS, WeightsError, load_fe_vmf

                path = cfg.weights or SHIPPED_WEIGHTS
                try:
                    self._model = load_fe_vmf(path)
                    self._predictor = f"fe-vmf:{Path(path).name}"
                except WeightsError as e:
                    if cfg.predictor == "fe-vmf" or cfg.weights is not None:
                        why = "named in its weights parameter" if cfg.weights is not None else "predictor: fe-vmf"
                        raise WeightsError(f"grasp skill: FE-vMF weights {path} ({why}) cannot be used, no fallback: "
                                           f"{e}") from e
                    if str(path) not in _WARNED:  # once per process and weights file
                        _WARNED.add(str(path))
                        log.warning("grasp skill: no usable FE-vMF weights (%s); using the untrained geometric "
                                    "fallback predictor (msmem_grasp.geometric) on the belief", e)
                    self._predictor = "geometric"
        return self._predictor

    def predict(self, belief: EvidentialMap, shelf: ShelfSpec, views: F64, seed: int) -> GraspHypotheses:
        """Per-point evidential grasps on the FPP cloud of ``belief`` seen from ``views`` [V, 4, 4]."""
        cfg = self.config
        fpp = FPPConfig(num_points=cfg.num_points, ray_stride_px=cfg.ray_stride_px, camera=cfg.camera, seed=seed)
        with span("FPP (frontier points)"):
            cloud = frontier_points(belief, views, fpp, shelf=shelf)
        if not len(cloud):
            return GraspHypotheses.empty()
        if self.predictor == "geometric":
            with span("geometric grasp predictor"):
                return predict_geometric(belief, cloud, shelf, cfg.gripper, cfg.geometric)
        from msmem_grasp.weights import predict_cloud

        with span("FE-vMF inference"):
            return GraspHypotheses.from_prediction(cloud.points, predict_cloud(self._model, cloud))

    def track(self, ctx: DecisionContext) -> None:
        """FE-UMGF step: fuse this step's predictions into the buffer (once per step)."""
        if self._tracked is not None and self._tracked[0] == ctx.step and self._tracked[1] is ctx.belief:
            return
        manipulated = ctx.last_manipulation
        if ctx.step == 0 or (self._tracked is not None and ctx.step < self._tracked[0]):
            self.buffer.clear()  # a new episode
            self._manipulated = -1
            self._confirm = False
        if manipulated != self._manipulated:
            # the scene changed physically: grasps fused on the geometry before it are not evidence
            # about the scene now (pushed objects and their neighbours moved as no model foresaw)
            if self.config.after_manipulation == "clear":
                self.buffer.clear()
            else:
                self._confirm = True
            self._manipulated = manipulated
        self._tracked = (int(ctx.step), ctx.belief)
        visited = sorted(v for v in ctx.visited if 0 <= v < len(ctx.viewpoints))
        views = np.asarray(ctx.viewpoints)[visited].reshape(-1, 4, 4)
        if manipulated < 0:  # nothing predicted in the belief: the virtual front cameras see real evidence
            views = np.concatenate([views, virtual_front_views(self.config.viewpoints)])
        elif not visited:
            # no view since the manipulation: the belief is the effect model's prediction, and grasps
            # planned on predicted geometry fail (docs/results.md); wait for a real view
            return
        seed = int(np.random.default_rng([self.config.seed, int(ctx.step)]).integers(2**31))
        new = self.predict(ctx.belief, ctx.shelf, views, seed)
        with span("FE-UMGF fusion"):
            self.buffer.update(new, ctx.belief, confirm=self._confirm)
            self._confirm = False

    # -------------------------------------------------------------------------------- proposal
    def propose(self, ctx: DecisionContext) -> list[Action]:
        self.track(ctx)
        if not ctx.manipulation_allowed:
            return []
        stages: dict[str, int] = {}
        out = self.executable(ctx.belief, ctx.shelf, stages, ctx.workspace.classes)
        for stage in FUNNEL_STAGES:  # the step record's candidate funnel: every stage, 0 after the one that left none
            ctx.funnel.count(stage, stages.get(stage, 0))
        return list(out)

    def candidates(self, belief: EvidentialMap, shelf: ShelfSpec,
                   stages: dict[str, int] | None = None) -> Candidates | None:
        """Steps 1-2 of the module docstring: the buffer's grasps that pass the evidence, reach and
        width tests, best E[q] first, with their poses and what the collision tests need. ``stages``
        receives the grasps left after each test (``fused``, ``confident``, ``preselected``, ``turned``: with
        their turned twins, ``from_front``)."""
        cfg = self.config
        grip = cfg.gripper
        stages = {} if stages is None else stages
        h = self.buffer.hypotheses()
        stages["fused"] = len(h)
        if not len(h):
            return None
        q, chi = h.affordance, h.uncertainty
        idx = np.flatnonzero((q >= cfg.min_affordance) & (chi <= cfg.max_uncertainty))
        stages["confident"] = len(idx)
        idx = idx[np.argsort(-q[idx], kind="stable")][: cfg.preselect]
        stages["preselected"] = len(idx)
        g = h.subset(idx)
        a, _ = g.approach()
        b = g.mu_b
        twin = np.zeros(len(g), dtype=bool)
        if cfg.turn_to:  # each grasp, then its turned twins where it has them
            dirs = [d for name in dict.fromkeys(cfg.turn_to) for d in TURN_DIRECTIONS[name]]
            turned = [turn_about(b, d) for d in dirs]
            rows = np.concatenate([a[:, None], np.stack([t for t, _ in turned], axis=1)], axis=1).reshape(-1, 3)
            has = np.concatenate([np.ones((len(g), 1), dtype=bool), np.stack([ok for _, ok in turned], axis=1)],
                                 axis=1).reshape(-1)
            which = np.repeat(np.arange(len(g)), 1 + len(dirs))[has]
            twin = np.tile(np.arange(1 + len(dirs)) > 0, len(g))[has]
            a = rows[has]
            g, b = g.subset(which), b[which]
        stages["turned"] = len(g) * (2 if cfg.roll == "both" else 1)
        keep = (a[:, 1] >= -_SIN15) & (a[:, 2] <= _SIN15) & (g.width >= cfg.min_width_m)
        if cfg.max_approach_deg < 180.0:
            keep &= a[:, 1] >= math.cos(math.radians(cfg.max_approach_deg)) - 1e-12
        if cfg.min_height_m > 0.0:  # the grasp's centre: the contact moved half the width along b
            keep &= g.contact[:, 2] + 0.5 * np.minimum(g.width, grip.max_opening_m) * b[:, 2] >= cfg.min_height_m
        g, a, b, twin = g.subset(keep), a[keep], b[keep], twin[keep]
        stages["from_front"] = len(g) * (2 if cfg.roll == "both" else 1)
        if not len(g):
            return None
        grid = belief.grid
        width = np.minimum(g.width, grip.max_opening_m)
        from msmem_grasp.fevmf import executable_grasp  # torch: imported on use

        objects = Objects.of(belief, shelf.interior_box, cfg.occupied_threshold)
        poses = np.asarray(executable_grasp(g.contact, a, b, width))
        if cfg.roll == "back-up":  # the same grasp turned about its approach: x and y change sign
            down = poses[:, 2, 1] < -1e-9
            poses[down, :3, :2] *= -1.0
        elif cfg.roll == "both":
            twice = np.repeat(np.arange(len(g)), 2)
            g, b, width, poses, twin = g.subset(twice), b[twice], width[twice], poses[twice], twin[twice]
            poses[1::2, :3, :2] *= -1.0
        return Candidates(
            grasps=g, width=width, opening=np.minimum(width + cfg.opening_margin_m, grip.max_opening_m),
            poses=poses,
            objects=objects, label=objects.label_at(grid, g.contact + 0.5 * grid.voxel_m * b),
            blocked=blocked_mask(belief, shelf, cfg.occupied_threshold, cfg.unknown_vacuity, cfg.unknown_band).ravel(),
            p=belief.expected_occupancy(), top=float(shelf.interior_upper[2] - cfg.clearance_m), twin=twin,
        )

    def action(self, c: Candidates, i: int, approach: F64, lift_m: float, shelf: ShelfSpec) -> GraspAction:
        """Candidate ``i`` as an action: its pose, the approach, then the lift and the retreat out of the front."""
        cfg = self.config
        pose = c.poses[i]
        lab = int(c.label[i])
        lift = pose[:3, 3] + np.array([0.0, 0.0, lift_m])
        retreat = (tuple(map(float, lift)), (float(lift[0]), float(min(cfg.retreat_y_m, lift[1])), float(lift[2])))
        return GraspAction(
            pose=tuple(tuple(float(v) for v in row) for row in pose),
            width_m=float(c.width[i]), opening_m=float(c.opening[i]),
            contact_m=tuple(float(v) for v in c.grasps.contact[i]),  # type: ignore[arg-type]
            target_class=int(c.objects.classes[lab]),
            approach_m=tuple(tuple(float(v) for v in p) for p in approach),  # type: ignore[misc]
            retreat_m=retreat, affordance=float(np.clip(c.grasps.affordance[i], 0, 1)),
            uncertainty=float(np.clip(c.grasps.uncertainty[i], 0, 1)), predictor=self.predictor, hand_m=cfg.hand_m,
        )

    def executable(self, belief: EvidentialMap, shelf: ShelfSpec, stages: dict[str, int] | None = None,
                   classes: tuple[ObjectClass, ...] = ()) -> list[GraspAction]:
        """The executable grasps of the fused buffer (steps 1-5 of the module docstring), best first;
        ``classes``: the belief's object classes (``Workspace.classes``), whose shapes give a grasped
        object's height where the belief does not (``_lift``).

        ``stages`` receives the grasps left after each step: those of ``candidates``, then ``on_object``
        (a believed object at the contact), ``free_at_grasp`` (the open gripper at the grasp touches no
        blocked voxel), ``collision_free`` (nor on its way in), ``under_top`` (the lifted object and
        gripper fit under the shelf top) and ``clear_exit`` (they leave the shelf: ``_lift``). With
        ``funnel: every-candidate`` every candidate is tested, also once ``top_k`` are found or its object
        has ``max_per_object``, so that the counts say what each test removes; by default (``until-full``)
        the tests after ``free_at_grasp`` run only while its object and the list have room."""
        cfg = self.config
        stages = {} if stages is None else stages
        c = self.candidates(belief, shelf, stages)
        if c is None:
            return []
        grid = belief.grid
        s = grid.voxel_m
        n = len(c.grasps)
        # the open gripper's points of every candidate, rotated as the grasp holds them
        pts = gripper_points_batch(cfg.gripper, c.opening, s / 2, cfg.tolerance_m, cfg.hand_m)
        local = np.matmul(pts, c.poses[:, :3, :3].transpose(0, 2, 1))  # pts[i] @ R_i.T, one BLAS call per i
        # first test of step 4 for all candidates at once: the open gripper at the grasp
        at_grasp = sweep_hits(grid, c.blocked, c.objects.labels, local, c.poses[:, :3, 3], np.arange(n + 1),
                              np.arange(n), c.label, c.poses, c.opening, cfg.max_object_radius_m)
        on_object = c.label > 0
        if cfg.wider_than_opening == "skip" and classes:
            wide = np.array([too_wide(classes[k - 1], cfg.gripper.max_opening_m) if 1 <= k <= len(classes) else False
                             for k in c.objects.classes], dtype=bool)
            on_object &= ~wide[c.label]
        stages["on_object"] = int(on_object.sum())
        stages["free_at_grasp"] = int((on_object & ~at_grasp).sum())
        stages["collision_free"] = stages["under_top"] = stages["clear_exit"] = 0
        out: list[GraspAction] = []
        per_object: dict[int, int] = {}
        every = cfg.funnel == "every-candidate"
        free = self.test_order(c, np.flatnonzero(on_object & ~at_grasp))
        grown = None
        if cfg.move_in_clearance_m is not None and len(free):  # the way in is tested with grown boxes
            grown = np.zeros((n, *gripper_points(cfg.gripper, 0.0, s / 2, -cfg.move_in_clearance_m, cfg.hand_m).shape))
        approaches: dict[int, F64] = {}
        planned: set[int] = set()
        occupied_objects = None  # what may stop a carried object (_carried), once
        for pos, i in enumerate(free):  # candidates in order of E[q] (``twins``)
            lab = int(c.label[i])
            full = per_object.get(lab, 0) >= cfg.max_per_object or len(out) >= cfg.top_k
            if full and not every:
                continue  # it would not be proposed: the tests below are the skill's costliest
            if int(i) not in planned:  # the ways in of the next candidates still to be tested, batched
                chunk = np.array([j for j in free[pos:] if every or per_object.get(int(c.label[j]), 0)
                                  < cfg.max_per_object][:APPROACH_BATCH], dtype=np.int64)
                if grown is not None:
                    points = gripper_points_batch(cfg.gripper, c.opening[chunk], s / 2, -cfg.move_in_clearance_m,
                                                  cfg.hand_m)
                    grown[chunk] = np.matmul(points, c.poses[chunk, :3, :3].transpose(0, 2, 1))
                approaches.update(self._plan_approaches(grid, c, local, chunk, grown))
                planned.update(chunk.tolist())
            pose = c.poses[i]
            approach = approaches.get(int(i))
            if approach is None:
                continue
            stages["collision_free"] += 1
            region = c.objects.region(grid, lab, pose, c.opening[i], cfg.max_object_radius_m)
            if occupied_objects is None:
                occupied_objects = self.believed_objects(c.p, c.objects)
            lift_m = self._lift(grid, c.p, c.objects, lab, region, pose, float(c.width[i]), c.top, stages,
                                self._class_shape(classes, int(c.objects.classes[lab])), occupied_objects)
            if lift_m is None:
                continue  # the lifted object or gripper would hit the shelf top, or its way out is blocked
            stages["clear_exit"] += 1
            if full:
                continue
            out.append(self.action(c, i, approach, lift_m, shelf))
            per_object[lab] = per_object.get(lab, 0) + 1
        return out

    def test_order(self, c: Candidates, idx: NDArray[np.int64]) -> NDArray[np.int64]:
        """Candidates ``idx`` of ``c`` (in E[q] order) in the order the tests take them (``twins``): as
        they are, or the turned twins after or before the grasps as predicted."""
        if self.config.twins == "interleaved":
            return idx
        ahead = c.twin[idx] if self.config.twins == "first" else ~c.twin[idx]
        return np.concatenate([idx[ahead], idx[~ahead]])

    def _plan_approaches(self, grid: GridSpec, c: Candidates, local: F64, idx: NDArray[np.int64],
                         local_in: F64 | None = None) -> dict[int, F64]:
        """The ways in of candidates ``idx`` of ``c`` (``local``: their open grippers' points, rotated;
        ``local_in``: the same for the way in to the pre-grasp pose, ``local`` if None):
        in front of the shelf, then the pre-grasp pose ``d`` back along a, for the first d of
        ``approach_distances_m`` at which the open gripper touches no blocked voxel. On the way in and at
        the pre-grasp pose anything blocked counts; on the final stretch along a the target's region
        (``Objects.region``) does not; the test at the grasp itself is done before, in :meth:`executable`.
        Batched: one kernel call per leg and distance. Returns candidate -> gripper origins [2, 3];
        candidates with no free way in are absent."""
        cfg = self.config
        s = grid.voxel_m
        out: dict[int, F64] = {}
        rest = np.asarray(idx, dtype=np.int64)
        for d in cfg.approach_distances_m:
            if not len(rest):
                break
            poses = c.poses[rest]
            grasp = poses[:, :3, 3]
            pre = grasp - d * poses[:, :3, 2]
            outside = pre.copy()
            outside[:, 1] = np.minimum(cfg.outside_y_m, pre[:, 1])
            # in front of the shelf to the pre-grasp pose, anything blocked counts; then, for those that
            # pass, on to the grasp, where the target's region does not
            ok = np.zeros(len(rest), dtype=bool)
            path, ptr = segment_paths(outside, pre, s / 2)
            none = np.zeros(len(rest), np.int64)
            first = ~sweep_hits(grid, c.blocked, c.objects.labels, local if local_in is None else local_in, path, ptr,
                                rest, none, poses, c.opening[rest], cfg.max_object_radius_m)
            f = np.flatnonzero(first)
            path, ptr = segment_paths(pre[f], grasp[f], s / 2)
            ok[f] = ~sweep_hits(grid, c.blocked, c.objects.labels, local, path, ptr, rest[f], c.label[rest[f]],
                                poses[f], c.opening[rest[f]], cfg.max_object_radius_m)
            for j in np.flatnonzero(ok):
                out[int(rest[j])] = np.stack([outside[j], pre[j]])
            rest = rest[~ok]
        return out

    def _lift(self, grid: GridSpec, p: NDArray[np.floating], objects: Objects, label: int, region: NDArray[np.int64],
              pose: F64, width: float, top: float, stages: dict[str, int] | None = None,
              extents: tuple[float, float, float] | None = None,
              occupied_objects: NDArray[np.bool_] | None = None) -> float | None:
        """The lift: ``lift_m`` if at that height the grasped object (the body ``_carried`` carries, its
        sides one voxel in) and the closed gripper, carried straight out of the front, meet no voxel in
        its way (``_carried``: of another believed object); else one voxel above the lowest height (in
        whole voxels, up to ``max_lift_m`` and the room under the shelf top) at which they do not;
        ``lift_m`` if there is none (None with ``blocked_exit: skip``). Where ``lift_m`` would bring the
        body's or the gripper's top closer than ``clearance_m`` to the shelf top, the room there is (in
        whole voxels) takes its place as the least lift; None if that is under ``min_lift_m``, if there
        is no room, or if the fingers lack ``short_lift_margin_m`` around the grasped width for such a
        short lift (else ``stages["under_top"]``, if given, counts one). With its class's ``extents``, the body stands
        at least as tall as the smallest of them that its believed top reaches (less a voxel): an
        object whose top the views have not seen is as tall as its class."""
        cfg = self.config
        s = grid.voxel_m
        pts = gripper_points(cfg.gripper, width, s / 2, cfg.tolerance_m, cfg.hand_m)
        r = pose[:3, :3]
        grip_top = float((pts @ r.T)[:, 2].max()) + pose[2, 3]
        if occupied_objects is None:
            occupied_objects = self.believed_objects(p, objects)
        # _carried's body and way in one pass, with the body's sides one voxel in (core, below)
        body, occupied, core = carried_way(grid, p, objects, label, region, cfg.geometric.free_threshold,
                                           cfg.exit_margin_m, occupied_objects)
        heights = body % grid.shape[2]
        obj_top = float(grid.origin[2] + (heights.max() + 0.5) * s) + s / 2 if len(body) else pose[2, 3]
        if extents is not None:
            floor = float(grid.origin[2] + s * heights.min()) if len(body) else 0.0
            taller = [e for e in extents if floor + e >= obj_top - s - 1e-9]
            obj_top = max(obj_top, floor + min(taller)) if taller else obj_top
        room = top - max(grip_top, obj_top)
        low = min(cfg.lift_m, s * math.floor(room / s + 1e-9))  # the least lift: lift_m, or what the room allows
        if room < 0 or low < min(cfg.min_lift_m, cfg.lift_m) - 1e-9:
            return None
        if (cfg.short_lift_margin_m is not None and low < cfg.lift_m - 1e-9
                and width + cfg.short_lift_margin_m > cfg.gripper.max_opening_m + 1e-9):
            return None  # a short lift, near the shelf top: only with the fingers' full margin around the object
        if stages is not None:
            stages["under_top"] = stages.get("under_top", 0) + 1
        # core: its sides one voxel in (a voxel both of whose x neighbours are the body's): a neighbour whose
        # voxels overlap the body's silhouette by one voxel is within the voxels' slack of it, not in its way
        first = max(0, math.ceil(low / s - 1e-9))
        last = min(int(np.floor(min(room, cfg.max_lift_m) / s + 1e-9)), first + 20)
        for k in range(first, max(first, last) + 1):
            if way_out_meets(grid, core, k, occupied):
                continue
            lifted = pose[:3, 3] + np.array([0.0, 0.0, k * s])
            out = lifted.copy()
            out[1] = min(cfg.retreat_y_m, lifted[1])
            if occupied[swept_indices(grid, r, pts, path_offsets(np.stack([pose[:3, 3], lifted, out]), s / 2))].any():
                continue
            # one voxel more where there is room: the voxels' heights are only known to a voxel
            return max(low, min((k + 1) * s, room)) if k > first else low
        return low if cfg.blocked_exit == "lift_m" else None

    @staticmethod
    def _class_shape(classes: tuple[ObjectClass, ...], cls: int) -> tuple[float, float, float] | None:
        """The extents (``class_extents_m``) of class id ``cls`` among ``classes`` (id 1 first); None
        when its shape is not known."""
        if not 1 <= cls <= len(classes):
            return None
        from msmem_core.world.meshes import class_extents_m

        return class_extents_m(classes[cls - 1])

    def believed_objects(self, p: NDArray[np.floating], objects: Objects) -> NDArray[np.bool_]:
        """Flat mask of the believed-occupied voxels of believed objects (what may stop a carried object)."""
        return (p.reshape(-1) > self.config.occupied_threshold) & (objects.labels.reshape(-1) > 0)

    def _carried(self, grid: GridSpec, p: NDArray[np.floating], objects: Objects, label: int,
                 region: NDArray[np.int64], occupied_objects: NDArray[np.bool_] | None = None
                 ) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """What leaves the shelf with a grasp of ``region`` (of component ``label``) and what may stop it:
        (flat indices of the carried body, flat mask of the voxels in its way). ``occupied_objects``:
        :meth:`believed_objects` of ``p`` and ``objects``, if the caller has it.

        The body: the region, the hidden voxels below it (``planning.fill_down``) and the voxels of its
        own component in the columns within ``exit_margin_m`` of its footprint, at any height: the
        object beyond the region the fingers close on (a front grasp's region stops 10 cm above the
        grasp; believed objects are up to about 2 cm fatter than the width a grasp measures). A
        touching object of the same class further in front is not carried. In the way: believed-
        occupied voxels of believed objects (``Objects``: components of an object class) outside the
        body, except those under its top in its own columns and in the columns its footprint surrounds:
        nothing else stands there (on the default belief they are the object's own voxels of another
        class). Believed-occupied voxels whose class is background are no object's, as in ``Objects``:
        on the default belief they are mostly objects' surface voxels, the grasped one's own included,
        that rays labelled background."""
        cfg = self.config
        body = fill_down(grid, p, objects.labels, region, label, cfg.geometric.free_threshold)
        way = (self.believed_objects(p, objects) if occupied_objects is None else occupied_objects).copy()
        if len(body):
            body = objects.carried(grid, label, body, cfg.exit_margin_m)
            # under its top in its own columns, and in the columns it surrounds, nothing else stands: the
            # belief's voxels there are its own (of another class), not in its way
            clear_under_top(grid, body, way)
        way[body] = False
        return body, way

    # ------------------------------------------------------------------------------- execution
    def tool_path(self, action: Action, workspace: Workspace) -> NDArray[np.float64]:
        """The approach points, the grasp and the retreat points, at the grasp's orientation."""
        a = action if isinstance(action, GraspAction) else GraspAction.model_validate(action.model_dump())
        return np.stack([a.at(p) for p in a.approach_m] + [a.matrix] + [a.at(p) for p in a.retreat_m])

    def execute(self, sim: Simulator, action: Action, ctx: DecisionContext) -> Outcome:
        cfg = self.config
        a = action if isinstance(action, GraspAction) else GraspAction.model_validate(action.model_dump())
        grasp = a.matrix
        if a.approach_m:
            sim.move_gripper([a.at(p) for p in a.approach_m], opening_m=a.opening_m, speed_mps=cfg.travel_speed_mps)
        reached = sim.move_gripper([grasp], opening_m=a.opening_m, speed_mps=cfg.approach_speed_mps)
        closed = sim.set_gripper(0.0)
        touching = sim.held_object()
        if a.retreat_m:
            sim.move_gripper([a.at(a.retreat_m[0])], speed_mps=cfg.lift_speed_mps)
            sim.move_gripper([a.at(p) for p in a.retreat_m[1:]], speed_mps=cfg.retreat_speed_mps)
        held = sim.held_object()
        removed = []
        if held is not None:
            sim.remove_object(held)
            removed.append(held)
        sim.set_gripper(cfg.gripper.max_opening_m)
        sim.park_gripper()
        if cfg.settle_s > 0:
            sim.step(cfg.settle_s)
        return Outcome(
            success=held is not None,
            removed=removed,
            info={"held": held, "touching_after_close": touching, "closed_opening_m": closed,
                  "pose_error_m": float(np.linalg.norm(reached[:3, 3] - grasp[:3, 3])), "predictor": a.predictor},
        )

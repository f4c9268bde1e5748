"""Builders for plugin unit tests: a small workspace, beliefs from boxes or from a scene, a fast IG
service, a valid ``DecisionContext`` and one MSAS decision.

Everything is small on purpose (2 cm voxels, four viewpoints, a 32 x 24 camera for IG), so a test
that decides with a skill of its own runs in well under a second::

    from msmem_core.testing import belief_with_boxes, decision_context, default_workspace, one_decision

    ws = default_workspace()
    belief = belief_with_boxes(ws.grid, [((-0.05, 0.03, 0.0), (0.05, 0.08, 0.09), 9)])
    ctx = decision_context(belief, step=3, manipulation_allowed=True)
    actions = MySkill().propose(ctx)
    decision = one_decision([("mine", MySkill(), MyEffect()), ("view", ViewSkill())], belief)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from msmem_core.interfaces import DecisionContext, EffectModel, Skill, Term, Workspace
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGService
from msmem_core.msas import BoundSkill, Decision, Objective, decide
from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import yaw_quat
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.meshes import part_mesh_own_frame
from msmem_core.world.scene import ObjectSpec, Part, SceneSpec, ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints
from msmem_core.world.voxelize import voxelize

Vec3 = tuple[float, float, float]
Box = tuple[Vec3, Vec3, int]
"""An object box for ``belief_with_boxes``: (lower corner, upper corner, class id), metres."""

EVIDENCE = 20.0
"""Evidence the builders add where they make the belief confident (p = 21/22 ~ 0.95, like a few views)."""
IG_CAMERA = CameraConfig(width_px=32, height_px=24)
"""The small camera of ``small_ig`` (IG rays only; skills that render use the run's camera)."""
SKILL_SPECS_WITH_NAME = "a BoundSkill, or a (name, skill) or (name, skill, effect model) tuple"


# ------------------------------------------------------------------------------------------ workspace
def default_workspace(voxel_m: float = 0.02, shelf: ShelfSpec | None = None,
                      gripper: GripperSpec | None = None) -> Workspace:
    """The default shelf (76 x 38 x 28 cm interior) on a grid of ``voxel_m`` around its interior
    (one voxel of margin), with the default gripper. 2 cm voxels: 40 x 21 x 16 voxels."""
    shelf = shelf or ShelfSpec()
    grid = GridSpec.around_box(shelf.interior_lower, shelf.interior_upper, voxel_m, 1)
    return Workspace(grid, shelf, gripper or GripperSpec())


def small_viewpoints(shelf: ShelfSpec | None = None, per_axis: int = 2) -> NDArray[np.float64]:
    """``per_axis``**2 viewpoints in front of the shelf, all aimed at its middle ([V, 4, 4]);
    with the default 2: four views."""
    return generate_viewpoints(ViewpointConfig(targets_x_m=(0.0,), grid=per_axis), shelf or ShelfSpec())


def small_ig(workspace: Workspace | None = None, viewpoints: NDArray[np.float64] | None = None,
             camera: CameraConfig | None = None) -> IGService:
    """An IG service over ``viewpoints`` (default ``small_viewpoints``) with a 32 x 24 camera: fast
    enough to build per test."""
    ws = workspace or default_workspace()
    views = small_viewpoints(ws.shelf) if viewpoints is None else viewpoints
    return IGService(ws.grid, camera or IG_CAMERA, views, ws.shelf)


def conformance_scene() -> SceneSpec:
    """Three well separated objects on the shelf floor: a tall box, a small box and a rotated box
    (a sugar box and a potted meat can at the back corners, a foam brick at the front in the middle)."""
    return SceneSpec(
        name="conformance",
        objects=(
            ObjectSpec(id=0, class_name="sugar_box", position_m=(-0.22, 0.22, 0.0)),
            ObjectSpec(id=1, class_name="foam_brick", position_m=(0.0, 0.12, 0.0)),
            ObjectSpec(
                id=2, class_name="potted_meat_can", position_m=(0.22, 0.22, 0.0), quat_xyzw=tuple(yaw_quat(0.5))
            ),
        ),
    )


# -------------------------------------------------------------------------------------------- beliefs
def _box_mask(grid: GridSpec, lo: Sequence[float], hi: Sequence[float]) -> NDArray[np.bool_]:
    """Voxels whose centre lies inside the box (lo, hi)."""
    c = grid.centers()
    return np.all((c > np.asarray(lo, dtype=np.float64)) & (c < np.asarray(hi, dtype=np.float64)), axis=-1)


def belief_with_boxes(
    grid: GridSpec,
    boxes: Sequence[Box],
    *,
    evidence: float = EVIDENCE,
    free: Literal["elsewhere", "none"] | Sequence[tuple[Vec3, Vec3]] = "elsewhere",
) -> EvidentialMap:
    """A belief with confident objects: voxels whose centre is inside a box ``(lo, hi, class_id)`` get
    ``evidence`` of occupancy and of that class (later boxes win where they overlap).

    ``free`` says what is known free (``evidence`` of free and of background): ``"elsewhere"`` every
    voxel outside the boxes, ``"none"`` nothing (the rest stays the prior: p = 0.5, vacuity 1), or a
    list of ``(lo, hi)`` boxes (voxels inside an object box stay the object's).
    """
    if evidence <= 0:
        raise ValueError(f"evidence must be > 0, got {evidence}")
    b = EvidentialMap.empty(grid)
    objects = np.zeros(grid.shape, dtype=bool)
    for lo, hi, cls in boxes:
        if not 0 < cls < b.num_classes:
            raise ValueError(f"class id {cls} of box {lo}..{hi} is not an object class (1..{b.num_classes - 1})")
        m = _box_mask(grid, lo, hi)
        objects |= m
        b.alpha[m], b.beta[m], b.eta[:, m] = 1.0 + evidence, 1.0, 1.0
        b.eta[cls, m] = 1.0 + evidence
    if free == "elsewhere":
        known_free = ~objects
    elif free == "none":
        known_free = np.zeros(grid.shape, dtype=bool)
    else:
        known_free = np.zeros(grid.shape, dtype=bool)
        for lo, hi in free:
            known_free |= _box_mask(grid, lo, hi)
        known_free &= ~objects
    b.beta[known_free] = 1.0 + evidence
    b.eta[0, known_free] = 1.0 + evidence
    return b


def belief_of_scene(
    scene: SceneSpec,
    grid: GridSpec,
    *,
    evidence: float = EVIDENCE,
    known: tuple[Vec3, Vec3] | None = None,
) -> EvidentialMap:
    """The belief of an observer who has seen ``scene``'s objects exactly (ground-truth voxels and
    classes, ``msmem_core.world.voxelize``): confident occupied with the object's class, confident
    free elsewhere. With ``known = (lo, hi)`` only voxels inside that box are known; the rest stays
    the prior (e.g. the front of the shelf seen, the back hidden)."""
    occ, cls = voxelize(scene.objects, grid)
    b = EvidentialMap.empty(grid)
    region = np.ones(grid.shape, dtype=bool) if known is None else _box_mask(grid, *known)
    occupied, free = occ & region, ~occ & region
    b.alpha[occupied], b.eta[:, occupied] = 1.0 + evidence, 1.0
    b.eta[cls[occupied].astype(np.int64), *np.nonzero(occupied)] = 1.0 + evidence
    b.beta[free] = 1.0 + evidence
    b.eta[0, free] = 1.0 + evidence
    return b


# ------------------------------------------------------------------------------------- decision context
def decision_context(
    belief: EvidentialMap | None = None,
    step: int = 1,
    *,
    manipulation_allowed: bool = True,
    workspace: Workspace | None = None,
    ig: IGService | None = None,
    visited: set[int] | None = None,
    seed: int = 0,
    tau_chi: float = 0.5,
    last_manipulation: int = -1,
) -> DecisionContext:
    """A valid ``DecisionContext`` for ``belief`` (default: the prior) at ``step``.

    ``workspace`` defaults to the belief's grid in the default shelf (``default_workspace``), ``ig``
    to ``small_ig`` over four viewpoints (``ctx.viewpoints`` are the IG service's), ``visited`` to
    the first view, ``rng`` to a generator seeded with ``seed``.
    """
    if workspace is None:
        workspace = default_workspace() if belief is None else Workspace(belief.grid, ShelfSpec())
    if belief is None:
        belief = EvidentialMap.empty(workspace.grid)
    if belief.grid != workspace.grid:
        raise ValueError("the belief's grid differs from the workspace's grid")
    ig = ig or small_ig(workspace)
    if ig.grid != workspace.grid:
        raise ValueError("the IG service's grid differs from the workspace's grid")
    return DecisionContext(step, belief, ig, ig.viewpoints, {0} if visited is None else set(visited), workspace,
                           np.random.default_rng(seed), manipulation_allowed, tau_chi, last_manipulation)


# ----------------------------------------------------------------------------------------- one decision
def _bound(s: BoundSkill | tuple[str, Skill] | tuple[str, Skill, EffectModel]) -> BoundSkill:
    if isinstance(s, BoundSkill):
        bound = s
    elif isinstance(s, tuple) and len(s) in (2, 3) and isinstance(s[0], str):
        bound = BoundSkill(*s)
    else:
        raise TypeError(f"one_decision: each skill must be {SKILL_SPECS_WITH_NAME}, got {type(s).__name__}")
    if not isinstance(bound.skill, Skill):
        raise TypeError(f"one_decision: skill {bound.name!r} is a {type(bound.skill).__name__}, not a "
                        "msmem_core.interfaces.Skill")
    if bound.skill.category == "manipulation" and not isinstance(bound.effect_model, EffectModel):
        raise TypeError(f"one_decision: manipulation skill {bound.name!r} needs an EffectModel as the third item "
                        f"(got {type(bound.effect_model).__name__})")
    return bound


def default_objective() -> Objective:
    """The built-in ``ig`` term (weight 1) built through the plugin manager: what every preset uses."""
    from msmem_core.plugins import get_plugin_manager

    return Objective([("ig", 1.0, get_plugin_manager().build("objective-term", "ig"))])


def one_decision(
    skills: Sequence[BoundSkill | tuple[str, Skill] | tuple[str, Skill, EffectModel]],
    belief: EvidentialMap | None = None,
    objective: Objective | Term | Sequence[tuple[str, float, Term]] | None = None,
    *,
    step: int = 1,
    manipulation_allowed: bool = True,
    ctx: DecisionContext | None = None,
    **context: Any,
) -> Decision:
    """One MSAS decision (``msmem_core.msas.decide``) with your skills, as an episode makes it.

    ``skills``: ``BoundSkill``\\ s or ``(name, skill)`` / ``(name, skill, effect_model)`` tuples (a
    manipulation skill needs its effect model). ``objective``: an ``Objective``, one ``Term``
    (weight 1), a list of ``(name, weight, term)``, or None for the built-in ``ig`` term.
    The context is ``decision_context(belief, step, manipulation_allowed=..., **context)`` (keyword
    arguments such as ``workspace``, ``visited``, ``seed``), or ``ctx`` as given. Returns the
    ``Decision``: ``.skill.name``, ``.action``, ``.value``, ``.terms``, ``.candidates`` (per skill),
    ``.best`` (per skill).
    """
    bound = [_bound(s) for s in skills]
    if objective is None:
        objective = default_objective()
    elif isinstance(objective, Term):
        objective = Objective([(type(objective).__name__, 1.0, objective)])
    elif not isinstance(objective, Objective):
        objective = Objective(list(objective))
    if ctx is None:
        ctx = decision_context(belief, step, manipulation_allowed=manipulation_allowed, **context)
    return decide(ctx, bound, objective)


__all__ = [
    "EVIDENCE",
    "IG_CAMERA",
    "Box",
    "belief_of_scene",
    "belief_with_boxes",
    "conformance_scene",
    "decision_context",
    "default_objective",
    "default_workspace",
    "one_decision",
    "small_ig",
    "small_viewpoints",
]


def convex_copy(part: Part) -> Part:
    """The same solid as a ``convex`` part (the hull of its mesh, as a mesh class's pieces are), at the
    same pose: for checking that convex pieces behave as the primitive they span."""
    v = np.asarray(part_mesh_own_frame(part).vertices)
    return Part(kind="convex", vertices_m=tuple(map(tuple, v)), position_m=part.position_m, quat_xyzw=part.quat_xyzw)

"""The interfaces plugins implement: Simulator, Robot, Skill, BeliefModel (two roles) and objective
Term, and what they are given: the ``Workspace`` (grid, shelf, gripper, robot) and, at each MSAS step,
the ``DecisionContext``.

Core code depends only on these; it never imports a simulator library or a plugin package.
"""

from __future__ import annotations

import itertools
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, model_serializer

from msmem_core.errors import UserError
from msmem_core.map.belief import BeliefDelta, DeltaBeliefs, EvidentialMap
from msmem_core.world.camera import Observation
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.scene import NUM_CLASSES, ObjectClass, ShelfSpec

if TYPE_CHECKING:
    from msmem_core.map.ig import IGField, IGService
    from msmem_core.world.scene import SceneSpec

Category = Literal["perception", "manipulation"]
GRIPPER_ID = -1
"""Id that ``Simulator.contacts`` uses for the gripper."""
SHELF_ID = -2
"""Id that ``Simulator.contacts`` uses for the shelf."""


# ------------------------------------------------------------------------------------------- workspace
@dataclass(frozen=True)
class Workspace:
    """The physical setting actions are planned, predicted and executed in: the belief's voxel grid,
    the shelf, the run's gripper and robot. Fixed over an episode. Actions do not carry it: effect
    models and ``Action.swept_volume`` receive it."""

    grid: GridSpec
    shelf: ShelfSpec
    gripper: GripperSpec = field(default_factory=GripperSpec)
    num_classes: int = NUM_CLASSES
    """Classes of the belief (background and every object class of the scene)."""
    robot: Robot | None = None
    """The run's robot (config ``robot``): what the camera and the gripper can reach. None: no arm,
    everything is reachable (as the ``floating`` robot)."""
    classes: tuple[ObjectClass, ...] = ()
    """The belief's object classes, ``classes[i]`` being class id ``i + 1``: their shapes are what the
    robot knows of its classes (a skill may judge an object by its believed class's shape). Empty:
    no shapes known."""

    @property
    def interior_box(self) -> tuple[float, float, float, float, float, float]:
        """The shelf interior as (x_lo, y_lo, z_lo, x_hi, y_hi, z_hi)."""
        return self.shelf.interior_box


# --------------------------------------------------------------------------------------------- actions
class Action(BaseModel):
    """A candidate action. JSON-serialisable; skills subclass it with their own parameters (what the
    skill decided, never the workspace: that comes with the context)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: str
    """Name of the skill that proposed it."""
    category: Category
    target_object: int | None = None
    """Object the action manipulates, as believed by the skill (never read from ground truth)."""
    omit_if_none: ClassVar[tuple[str, ...]] = ()
    """Fields left out of the action's record while they are None: fields added after records were
    written (records, golden episodes and bench fingerprints stay as they were)."""

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out: dict[str, Any] = handler(self)
        for name in self.omit_if_none:
            if getattr(self, name) is None:
                out.pop(name, None)
        return out

    def swept_volume(self, workspace: Workspace) -> NDArray[np.bool_]:
        """Voxels of ``workspace.grid`` the gripper passes through; empty for perception actions."""
        return np.zeros(workspace.grid.shape, dtype=bool)


class PerceptionAction(Action):
    """An action that observes from one of the run's viewpoints, named by its index: MSAS scores it by
    that view's information gain and counts the view as visited once it is executed. Every action
    of a perception skill must be one."""

    category: Literal["perception"] = "perception"
    view: int = Field(ge=0)
    """Index into the run's viewpoints (``DecisionContext.viewpoints``)."""


@dataclass
class Outcome:
    """What executing an action did.

    A skill reports ``success``, a perception action's ``observation``, the objects it took out of
    the workspace (``removed``) and its own details (``info``). The displacement of the objects and
    which fell or left are measured by MSAS around every manipulation (``msas.execute_measured``),
    the same way for every skill; a skill leaves them empty.
    """

    success: bool = True
    observation: Observation | None = None
    """A perception action's frame, integrated by the observation model."""
    displacement_m: dict[int, float] = field(default_factory=dict)
    """XY displacement of every object still in the workspace, caused by the action (set by MSAS)."""
    fell_or_left: list[int] = field(default_factory=list)
    """Objects that fell over, vanished or left the shelf (set by MSAS; manipulation stops for the episode)."""
    removed: list[int] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    """The skill's own details; for a manipulation MSAS adds ``moved``: objects displaced > 5 mm."""


# ------------------------------------------------------------------------------------------- simulator
@dataclass(frozen=True)
class Contact:
    """A contact between two bodies (object ids, ``GRIPPER_ID`` or ``SHELF_ID``)."""

    body_a: int
    body_b: int
    position_m: tuple[float, float, float]
    normal_force_n: float


@dataclass(frozen=True)
class Capabilities:
    name: str
    physics: bool = True
    renders_depth: bool = True
    renders_labels: bool = True
    snapshot: bool = True
    notes: str = ""


class Simulator(ABC):
    """A physics backend, in a robot-agnostic vocabulary. Skills compose these; there is no push/grasp.

    Poses are 4x4 matrices in the world frame (z up). The gripper follows ``GripperSpec``.
    """

    @abstractmethod
    def reset(self, scene: SceneSpec) -> None:
        """Build the shelf and the scene's objects, park the gripper out of view, let objects settle."""

    @abstractmethod
    def observe(self, camera_to_world: NDArray[np.float64]) -> Observation:
        """Render depth (z-depth, metres) and class labels from a camera-to-world pose (OpenCV frame)."""

    @abstractmethod
    def move_gripper(
        self, waypoints: Sequence[NDArray[np.float64]], opening_m: float | None = None, speed_mps: float = 0.1
    ) -> NDArray[np.float64]:
        """Drive the gripper through the poses under physics (objects react); return the final pose."""

    @abstractmethod
    def set_gripper(self, opening_m: float) -> float:
        """Open or close the fingers (closing stops at contact); return the reached opening."""

    @abstractmethod
    def park_gripper(self) -> None:
        """Move the gripper out of the workspace and out of every camera's view."""

    @abstractmethod
    def gripper_pose(self) -> NDArray[np.float64]:
        """Current gripper pose (gripper frame of ``GripperSpec``)."""

    @abstractmethod
    def contacts(self) -> list[Contact]:
        """Current contacts involving the gripper or objects."""

    @abstractmethod
    def held_object(self) -> int | None:
        """The object touched by both fingers, if any."""

    @abstractmethod
    def remove_object(self, object_id: int) -> None:
        """Take an object out of the workspace."""

    @abstractmethod
    def object_poses(self) -> dict[int, NDArray[np.float64]]:
        """Pose of every object still in the workspace."""

    @abstractmethod
    def step(self, seconds: float) -> None:
        """Advance physics by this much simulated time."""

    @abstractmethod
    def snapshot(self) -> Any:
        """An opaque token of the full physical state."""

    @abstractmethod
    def restore(self, token: Any) -> None:
        """Return to a snapshot's state exactly (objects removed since then come back)."""

    @abstractmethod
    def capabilities(self) -> Capabilities: ...

    def attach_robot(self, robot: Robot) -> None:
        """Build ``robot``'s arm into the world from the next ``reset`` on and drive it by joint control:
        the gripper calls above then move the arm's hand, and ``observe`` puts the arm where its wrist
        camera takes the view. The loop calls it for a robot with an arm. A backend that cannot load the
        robot refuses here, in one line naming what is missing (this default)."""
        raise UserError(f"simulator {self.capabilities().name!r} cannot drive robot {robot.model().name!r}: it "
                        "does not load robots from URDF; use the pybullet simulator, or robot: {name: floating}")

    def robot_notes(self) -> list[str]:
        """What the attached arm could not do since the last call (e.g. a move to a pose it cannot reach,
        which is then not made), one line each; the loop puts them in the step record."""
        return []

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the backend's resources."""


# ----------------------------------------------------------------------------------------------- robot
@dataclass(frozen=True)
class RobotModel:
    """What a robot is: its description, where its base stands and its joints (all in the world frame,
    which is the shelf's: x along the shelf, y into it from its open front at y = 0, z up from its floor)."""

    name: str
    """The robot's registered name."""
    urdf: str | None
    """Path of its URDF (None: no arm, as the ``floating`` robot)."""
    base_pose: NDArray[np.float64]
    """4x4 pose of the robot's base in the shelf (world) frame."""
    joint_names: tuple[str, ...] = ()
    """The joints IK solves for, in order (a ``Reach``'s ``joints`` follow it)."""
    joint_lower: tuple[float, ...] = ()
    """Lower joint limits (rad or m), from the URDF."""
    joint_upper: tuple[float, ...] = ()
    """Upper joint limits (rad or m), from the URDF."""
    flange_link: str | None = None
    """The link whose pose ``Robot.ik`` reaches; the camera mount is relative to it."""
    finger_joints: tuple[str, ...] = ()
    """The hand's finger joints: a simulator that drives the arm opens and closes them. Prismatic (metres,
    the opening being their sum), unless ``finger_gearing`` makes them a linkage."""
    finger_gearing: tuple[float, ...] = ()
    """For a linkage hand (a Robotiq 2F-85): each finger joint's position per unit of the first one's, which
    drives it; the opening is then ``finger_opening``'s function of the first joint. Empty: prismatic fingers."""
    finger_opening: tuple[tuple[float, float], ...] = ()
    """With ``finger_gearing``: (position of the first finger joint, opening in metres) pairs, the positions
    increasing; the opening between them is interpolated."""
    finger_pads: tuple[str, ...] = ()
    """The two links that hold an object between them (empty: the finger joints' child links)."""
    home: tuple[float, ...] = ()
    """A configuration (``joint_names`` order) out of the shelf, where a simulator parks the arm."""


@dataclass(frozen=True)
class Reach:
    """A reachability answer: a verified joint configuration, or why there is none."""

    reachable: bool
    """The pose is reached within tolerance, inside the joint limits, without collisions."""
    joints: tuple[float, ...] | None = None
    """The configuration (``RobotModel.joint_names`` order) when reachable; () for a robot without joints."""
    position_error_m: float = 0.0
    """Distance between the asked flange position and the forward kinematics of the answer (of the best
    attempt when unreachable)."""
    orientation_error_deg: float = 0.0
    """Angle between the asked flange orientation and the answer's (of the best attempt when unreachable)."""
    collisions: tuple[str, ...] = ()
    """What the best attempt hit, e.g. ``panda_hand-top`` (link and shelf board)."""
    reason: str = ""
    """One line when unreachable."""


class Robot(ABC):
    """An arm that carries the camera and the gripper: its model, inverse kinematics with a verified
    reachability answer, collision checks against the shelf, and the camera mount.

    The shelf (``ShelfSpec``) is passed to every call: it is the scene's, and fixed over an episode, so
    implementations may build their collision geometry once per shelf.
    """

    @abstractmethod
    def model(self) -> RobotModel:
        """URDF, base pose relative to the shelf, joint names and limits."""

    @abstractmethod
    def camera_mount(self) -> NDArray[np.float64]:
        """4x4 camera-to-flange pose of the wrist camera (camera frame in the OpenCV convention)."""

    @abstractmethod
    def ik(self, flange_pose: NDArray[np.float64], shelf: ShelfSpec) -> Reach:
        """A configuration whose flange is at ``flange_pose`` (4x4, world), within the joint limits,
        checked by forward kinematics and free of collisions with the shelf; else why not."""

    @abstractmethod
    def collisions(self, joints: Sequence[float], shelf: ShelfSpec) -> list[str]:
        """What the arm in configuration ``joints`` touches or comes too close to (``link-board``
        names); empty: collision-free."""

    arm: ClassVar[bool] = True
    """False for a robot without an arm (``floating``): the loop then checks no tool path."""

    def tool_mount(self) -> NDArray[np.float64]:
        """4x4 pose of the gripper frame (``GripperSpec``'s: origin between the fingertips, z the approach
        axis) in the flange frame. Identity unless the robot's hand says otherwise."""
        return np.eye(4)

    def reach_path(self, tool_poses: NDArray[np.float64], shelf: ShelfSpec, step_m: float = 0.02) -> Reach:
        """Whether the gripper can move through the poses ``tool_poses`` [W, 4, 4] (gripper frame, world) in
        order: every waypoint, and points at most ``step_m`` apart on the straight segments between them
        (with the orientation of the segment's end), reached collision-free by ``ik``. The answer is
        the last configuration, or the first failure with its waypoint in ``reason``. Robots with
        joint-space paths (e.g. seeded from the previous answer) override it."""
        poses = densify(np.asarray(tool_poses, dtype=np.float64), step_m)
        inv = np.linalg.inv(self.tool_mount())
        reach = Reach(True, ())
        for k, t in enumerate(poses):
            reach = self.ik(t @ inv, shelf)
            if not reach.reachable:
                return Reach(False, None, reach.position_error_m, reach.orientation_error_deg, reach.collisions,
                             f"path point {k} of {len(poses)}: {reach.reason}")
        return reach

    def use_obstacles(self, boxes: NDArray[np.float64] | None) -> None:
        """Boxes [N, 2, 3] (lower and upper world corners) of believed-occupied space that the arm's links
        behind its hand must not touch along ``reach_path``, until the next call (None: none). Before
        checking a decision's manipulation candidates, MSAS gives the belief's (``GridSpec.column_boxes``
        of expected occupancy > 0.5). The hand and what the skill's tool covers are the skill's to check
        (``Skill.tool_path``'s swept volume). The base class ignores them."""
        return None

    def reach_camera(self, camera_to_world: NDArray[np.float64], shelf: ShelfSpec) -> Reach:
        """``ik`` of the flange pose that puts the wrist camera at ``camera_to_world``."""
        return self.ik(np.asarray(camera_to_world, dtype=np.float64) @ np.linalg.inv(self.camera_mount()), shelf)

    def reachable_views(self, viewpoints: NDArray[np.float64], shelf: ShelfSpec) -> NDArray[np.bool_]:
        """[V] which camera poses ``viewpoints`` [V, 4, 4] the wrist camera reaches collision-free. The view
        skill asks at every step: implementations cache the answer per shelf and viewpoint set."""
        return np.array([self.reach_camera(t, shelf).reachable for t in viewpoints], dtype=bool)

    def link_points(self, joints: Sequence[float]) -> NDArray[np.float64]:
        """[L, 3] world positions along the arm in configuration ``joints``, from the base to the hand
        (link frame origins, in chain order, passing the flange), for drawing the arm: the step records
        keep them and the report draws them. Empty (the default) for a robot that does not say."""
        return np.zeros((0, 3))

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the robot's resources (e.g. its kinematics client)."""


def densify(poses: NDArray[np.float64], step_m: float) -> NDArray[np.float64]:
    """The poses [W, 4, 4] with points inserted on each straight segment so that consecutive positions are
    at most ``step_m`` apart; inserted points take the orientation of their segment's end."""
    if len(poses) < 2:
        return poses
    out = [poses[0]]
    for a, b in itertools.pairwise(poses):
        n = max(1, int(np.ceil(np.linalg.norm(b[:3, 3] - a[:3, 3]) / step_m)))
        for f in np.arange(1, n + 1) / n:
            t = b.copy()
            t[:3, 3] = a[:3, 3] + f * (b[:3, 3] - a[:3, 3])
            out.append(t)
    return np.stack(out)


# ---------------------------------------------------------------------------------------- belief model
@dataclass
class Prediction:
    """Predicted beliefs after K candidate actions, in one sparse form: per candidate, the voxels whose
    evidence the action changes and their new evidence (a ``BeliefDelta``: flat indices, sorted and
    unique, with the new alpha, beta and eta there). Every voxel a change does not list keeps the
    evidence of ``base``, the belief the prediction was made from. Objective terms score the changes
    (only changed voxels can differ); the loop applies the chosen one.
    """

    base: EvidentialMap
    changes: list[BeliefDelta]
    """One change per candidate, listing only voxels whose evidence differs from ``base``
    (``BeliefDelta.against`` drops the others)."""
    excluded: list[NDArray[np.int64]] | None = None
    """Per candidate, flat voxel indices a disturbance term (CDC) ignores: a grasp's intended removal
    (the whole grasped object); None: none."""

    @classmethod
    def from_beliefs(cls, base: EvidentialMap, beliefs: Sequence[EvidentialMap],
                     excluded: list[NDArray[np.int64]] | None = None) -> Prediction:
        """The sparse form of K full predicted maps (for effect models that predict whole maps)."""
        c = base.num_classes
        a0, b0, e0 = base.alpha.reshape(-1), base.beta.reshape(-1), base.eta.reshape(c, -1)
        changes = []
        for b in beliefs:
            a, bb, e = b.alpha.reshape(-1), b.beta.reshape(-1), b.eta.reshape(c, -1)
            idx = np.flatnonzero((a != a0) | (bb != b0) | np.any(e != e0, axis=0))
            changes.append(BeliefDelta(idx, a[idx].copy(), bb[idx].copy(), e[:, idx].copy()))
        return cls(base, changes, excluded)

    def __len__(self) -> int:
        return len(self.changes)

    def belief(self, k: int) -> EvidentialMap:
        """Candidate ``k``'s predicted belief as a full map."""
        return self.changes[k].apply(self.base)

    @property
    def beliefs(self) -> DeltaBeliefs:
        """All K predicted beliefs as full maps, each built when it is accessed."""
        return DeltaBeliefs(self.base, self.changes)

    @cached_property
    def changed(self) -> NDArray[np.bool_]:
        """[K, X, Y, Z] masks of the changed voxels (a dense view of ``changes``, for inspection)."""
        out = np.zeros((len(self.changes), self.base.grid.size), dtype=bool)
        for k, d in enumerate(self.changes):
            out[k, d.idx] = True
        return out.reshape(len(self.changes), *self.base.grid.shape)

    def excluded_among(self, k: int) -> NDArray[np.bool_] | None:
        """Which of candidate ``k``'s changed voxels (``changes[k].idx``) are excluded; None: none are."""
        if self.excluded is None:
            return None
        return np.isin(self.changes[k].idx, self.excluded[k])


class BeliefModel(ABC):  # noqa: B024 - a plugin implements one or both roles, so neither is abstract
    """Base of belief models; a plugin implements one or both roles."""

    roles: ClassVar[frozenset[str]] = frozenset()
    classes: tuple[str, ...] | None = None
    """The class names a learned model takes (index = class id, ``background`` first): those it was
    trained on, or the scene classes its class map maps onto them; None: any. The runner refuses a
    scene whose classes (``SceneSpec.class_names``) differ."""
    trained_classes: tuple[str, ...] | None = None
    """For a model that maps a scene's classes onto the ones it was trained on (``classes`` being the
    scene's): the trained ones, which the runner names when the map does not fit; None: no map."""


class ObservationModel(BeliefModel):
    """sigma_o: integrate an observation into the belief."""

    roles: ClassVar[frozenset[str]] = frozenset({"observe"})

    @abstractmethod
    def update(self, belief: EvidentialMap, observation: Observation) -> EvidentialMap: ...

    def disturbed(self, region: NDArray[np.bool_], cap: float) -> None:
        """A manipulation disturbed ``region`` ([X, Y, Z]): MSAS capped the belief's evidence there at
        alpha + beta <= ``cap`` (``EvidentialMap.capped``), so that later views can overturn it. A model
        that keeps evidence of its own between updates (``cnabu-map``'s record of the episode's rays)
        may cap it there too; otherwise its next update restores what the cap took where that evidence
        rules (``cnabu-map``: ``disturbed_rays``). A model that keeps none, like the default here, does
        nothing."""

    def failed_manipulation(self, region: NDArray[np.bool_], cap: float) -> None:
        """As ``disturbed``, after a manipulation that reported failure (a grasp that held nothing, a push
        stopped short): the belief stayed as it was before the action, capped in ``region`` at ``cap``,
        and what stood there may have moved without the prediction saying where. The default calls
        ``disturbed``, so a model that only implements ``disturbed`` is told either way."""
        self.disturbed(region, cap)


class EffectModel(BeliefModel):
    """sigma_p / sigma_g: predict the belief after manipulation actions, batched."""

    roles: ClassVar[frozenset[str]] = frozenset({"effect"})

    @abstractmethod
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        """The belief after each action, predicted from ``belief`` (the returned ``base``) in
        ``workspace`` (the grid, the shelf interior, the gripper the actions are executed with)."""


# -------------------------------------------------------------------------------------- decision context
@dataclass
class Funnel:
    """How many of each skill's candidates are left after each stage of one step's proposals, in order
    (``DecisionContext.funnel``; the step record's ``funnel``). A skill reports its own stages from
    ``propose``, in the order they filter (``ctx.funnel.count("collision_free", n)``; the stage names
    are its own); MSAS (``msas.decide``) sets ``skill`` before asking each one and adds its own stages
    after the skill's: ``proposed`` (the actions returned), with an arm ``reach_checked`` and
    ``reachable`` (only candidates that could win are checked, best first), and ``chosen`` (1 if the
    step's action is this skill's). A skill not asked at a step (a manipulation skill while
    manipulation is not allowed) has no entry."""

    counts: dict[str, dict[str, int]] = field(default_factory=dict)
    """``counts[skill][stage]``: the candidates of ``skill`` (its name in config) left after ``stage``."""
    skill: str = ""
    """The skill being asked; its ``count`` calls go to ``counts[skill]``."""

    def count(self, stage: str, n: int) -> None:
        """``n`` of the current skill's candidates are left after ``stage`` (reported in stage order; a
        stage reported twice keeps the last count)."""
        if n < 0:
            raise ValueError(f"stage {stage!r} of skill {self.skill!r}: a candidate count cannot be negative ({n})")
        self.counts.setdefault(self.skill, {})[stage] = int(n)

    def stages(self, skill: str) -> dict[str, int]:
        """The stage counts of ``skill`` (empty if it was not asked)."""
        return dict(self.counts.get(skill, {}))


@dataclass
class DecisionContext:
    """What skills, effect models and objective terms see at one MSAS step. ``field`` (the IG view of
    the belief) is computed once, on first use."""

    step: int
    belief: EvidentialMap
    ig: IGService
    viewpoints: NDArray[np.float64]
    """Camera-to-world poses of the run's viewpoints, [V, 4, 4]; a ``PerceptionAction.view`` indexes them."""
    visited: set[int]
    """Views taken since the last manipulation (at the first step: the start view)."""
    workspace: Workspace
    rng: np.random.Generator
    """The episode's seeded generator: every random choice of a skill or term draws from it."""
    manipulation_allowed: bool
    tau_chi: float
    last_manipulation: int = -1
    """Step of the episode's last executed manipulation (-1: none yet); ``visited`` holds only the
    views taken since then, and the belief outside them may be an effect model's prediction."""
    cache: dict[Any, Any] = field(default_factory=dict)
    """Per-step scratch space terms share (e.g. the IG sweep of every view)."""
    funnel: Funnel = field(default_factory=Funnel)
    """Candidates left after each stage of every skill's proposal (``Funnel.count``); the step record's ``funnel``."""

    @property
    def grid(self) -> GridSpec:
        return self.workspace.grid

    @property
    def shelf(self) -> ShelfSpec:
        return self.workspace.shelf

    @property
    def gripper(self) -> GripperSpec:
        return self.workspace.gripper

    @cached_property
    def field(self) -> IGField:
        return self.ig.prepare(self.belief)


# ----------------------------------------------------------------------------------------------- skill
class Skill(ABC):
    """Proposes candidate actions from the belief and executes a chosen one with the Simulator vocabulary."""

    category: ClassVar[Category] = "perception"
    """``perception``: proposes ``PerceptionAction`` views, scored by two-step IG; ``manipulation``: its
    actions are predicted by the effect model bound to it in config and scored by the IG of the best view
    after the prediction, plus the manipulation terms (semantic entropy, CDC). Set it on the class."""

    @abstractmethod
    def propose(self, ctx: DecisionContext) -> list[Action]:
        """Candidates for this step, from the belief only (a perception skill's are ``PerceptionAction``)."""

    @abstractmethod
    def execute(self, sim: Simulator, action: Action, ctx: DecisionContext) -> Outcome:
        """Carry out one of this skill's actions with the Simulator vocabulary (see ``Outcome`` for
        what MSAS measures itself)."""

    def tool_path(self, action: Action, workspace: Workspace) -> NDArray[np.float64] | None:
        """The gripper poses [W, 4, 4] (``GripperSpec`` frame, world) that executing ``action`` moves
        through, in order, so that the loop can drop the candidates the run's robot cannot follow
        (``Robot.reach_path``). None (the default): the skill does not say, nothing is checked."""
        return None

    def track(self, ctx: DecisionContext) -> None:  # noqa: B027 - optional hook
        """Called once per step before any proposal, also when this skill may not act: skills that
        accumulate evidence over the episode (the grasp skill's FE-UMGF buffer) update it here."""


# ------------------------------------------------------------------------------------------ objective
@dataclass
class CandidateBatch:
    """One skill's candidates with what the objective terms need to score them."""

    skill: str
    category: Category
    actions: list[Action]
    prediction: Prediction | None = None
    """Effect-model prediction, for manipulation candidates."""
    view_indices: NDArray[np.int64] | None = None
    """Viewpoint index per candidate, for perception candidates."""


class Term(ABC):
    """One additive term of the objective; ``score`` returns one value per candidate."""

    applies_to: ClassVar[frozenset[Category]] = frozenset({"perception", "manipulation"})

    @abstractmethod
    def score(self, ctx: DecisionContext, batch: CandidateBatch) -> NDArray[np.float64]: ...

    def refine(self, ctx: DecisionContext, batch: CandidateBatch,
               indices: NDArray[np.int64]) -> NDArray[np.float64] | None:
        """Exact values for ``indices`` when ``score`` approximated them (e.g. screened at a coarser
        ray density), else None. MSAS refines a skill's best candidate until its winner is exact."""
        return None

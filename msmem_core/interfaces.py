"""The interfaces plugins implement: Simulator, Skill, BeliefModel (two roles) and objective Term.

Core code depends only on these; it never imports a simulator library or a plugin package.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from msmem_core.world.camera import Observation

if TYPE_CHECKING:
    from msmem_core.map.belief import EvidentialMap
    from msmem_core.world.grid import GridSpec
    from msmem_core.world.scene import SceneSpec

Category = Literal["perception", "manipulation"]
GRIPPER_ID = -1
"""Id that ``Simulator.contacts`` uses for the gripper."""
SHELF_ID = -2
"""Id that ``Simulator.contacts`` uses for the shelf."""


# --------------------------------------------------------------------------------------------- actions
class Action(BaseModel):
    """A candidate action. JSON-serialisable; skills subclass it with their own parameters."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: str
    """Name of the skill that proposed it."""
    category: Category
    target_object: int | None = None
    """Object the action manipulates, as believed by the skill (never read from ground truth)."""

    def swept_volume(self, grid: GridSpec) -> NDArray[np.bool_]:
        """Voxels the gripper passes through; empty for perception actions."""
        return np.zeros(grid.shape, dtype=bool)


@dataclass
class Outcome:
    """What executing an action did."""

    success: bool = True
    observation: Observation | None = None
    """A perception action's frame, integrated by the observation model."""
    displacement_m: dict[int, float] = field(default_factory=dict)
    """XY displacement of every object caused by the action."""
    fell_or_left: list[int] = field(default_factory=list)
    """Objects that fell over or left the shelf (manipulation stops for the episode)."""
    removed: list[int] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)


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

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the backend's resources."""


# ---------------------------------------------------------------------------------------- belief model
@dataclass
class Prediction:
    """Predicted beliefs after K candidate actions and the voxels each changes."""

    beliefs: Sequence[EvidentialMap]
    """One belief per action (a list, or a lazy ``DeltaBeliefs`` of sparse changes)."""
    changed: NDArray[np.bool_]
    """[K, X, Y, Z] voxels whose evidence differs from the prior belief."""
    excluded: NDArray[np.bool_] | None = None
    """[K, X, Y, Z] voxels a disturbance term (CDC) ignores: a grasp's intended removal (the grasped
    object's region); None: none."""


class BeliefModel(ABC):  # noqa: B024 - a plugin implements one or both roles, so neither is abstract
    """Base of belief models; a plugin implements one or both roles."""

    roles: ClassVar[frozenset[str]] = frozenset()


class ObservationModel(BeliefModel):
    """sigma_o: integrate an observation into the belief."""

    roles: ClassVar[frozenset[str]] = frozenset({"observe"})

    @abstractmethod
    def update(self, belief: EvidentialMap, observation: Observation) -> EvidentialMap: ...


class EffectModel(BeliefModel):
    """sigma_p / sigma_g: predict the belief after manipulation actions, batched."""

    roles: ClassVar[frozenset[str]] = frozenset({"effect"})

    @abstractmethod
    def predict(self, belief: EvidentialMap, actions: Sequence[Action]) -> Prediction: ...


# ----------------------------------------------------------------------------------------------- skill
class Skill(ABC):
    """Proposes candidate actions from the belief and executes a chosen one with the Simulator vocabulary."""

    category: ClassVar[Category] = "perception"

    @abstractmethod
    def propose(self, ctx: Any) -> list[Action]:
        """Candidates for this step (``ctx`` is ``msmem_core.msas.DecisionContext``)."""

    @abstractmethod
    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome: ...

    def track(self, ctx: Any) -> None:  # noqa: B027 - optional hook
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
    def score(self, ctx: Any, batch: CandidateBatch) -> NDArray[np.float64]: ...

    def refine(self, ctx: Any, batch: CandidateBatch, indices: NDArray[np.int64]) -> NDArray[np.float64] | None:
        """Exact values for ``indices`` when ``score`` approximated them (e.g. screened at a coarser
        ray density), else None. MSAS refines a skill's best candidate until its winner is exact."""
        return None

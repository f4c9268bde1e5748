"""Multi-Skill Action Selection (MSAS): score every skill's candidates with one objective, act, repeat."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.interfaces import Action, CandidateBatch, EffectModel, ObservationModel, Outcome, Simulator, Skill, Term

if TYPE_CHECKING:
    from msmem_core.belief import EvidentialMap
    from msmem_core.config import MSASConfig
    from msmem_core.grid import GridSpec
    from msmem_core.gripper import GripperSpec
    from msmem_core.ig import IGField, IGService
    from msmem_core.scene import ShelfSpec


@dataclass
class DecisionContext:
    """What skills and terms see at one step. ``field`` (the IG view of the belief) is computed once."""

    step: int
    belief: EvidentialMap
    ig: IGService
    viewpoints: NDArray[np.float64]
    visited: set[int]
    grid: GridSpec
    shelf: ShelfSpec
    gripper: GripperSpec
    rng: np.random.Generator
    manipulation_allowed: bool
    tau_chi: float
    cache: dict[str, Any] = field(default_factory=dict)

    @cached_property
    def field(self) -> IGField:
        return self.ig.prepare(self.belief)


@dataclass
class BoundSkill:
    """A skill with its name and, for manipulation, the effect model predicting its outcome."""

    name: str
    skill: Skill
    effect_model: EffectModel | None = None

    def batch(self, ctx: DecisionContext, actions: list[Action]) -> CandidateBatch:
        if self.skill.category == "perception":
            views = np.array([getattr(a, "view", -1) for a in actions], dtype=np.int64)
            return CandidateBatch(self.name, "perception", actions, view_indices=views)
        if self.effect_model is None:
            raise RuntimeError(f"manipulation skill {self.name!r} has no effect model")
        return CandidateBatch(self.name, "manipulation", actions, prediction=self.effect_model.predict(ctx.belief, actions))


@dataclass
class Objective:
    """Weighted sum of term plugins; a term scores only the categories it applies to."""

    terms: list[tuple[str, float, Term]]

    def score(self, ctx: DecisionContext, batch: CandidateBatch) -> tuple[NDArray[np.float64], dict[str, NDArray[np.float64]]]:
        total = np.zeros(len(batch.actions))
        parts: dict[str, NDArray[np.float64]] = {}
        for name, weight, term in self.terms:
            if batch.category in term.applies_to:
                parts[name] = np.asarray(term.score(ctx, batch), dtype=np.float64)
                total += weight * parts[name]
        return total, parts


@dataclass
class Decision:
    skill: str
    action: Action
    value: float
    terms: dict[str, float]
    candidates: dict[str, int]
    """Number of candidates each skill proposed."""
    best: dict[str, float]
    """Best objective value of each skill that proposed something."""
    batch: CandidateBatch
    index: int


def decide(ctx: DecisionContext, skills: list[BoundSkill], objective: Objective) -> Decision:
    """Best action over all skills by the objective (ties go to the skill listed first)."""
    best: Decision | None = None
    counts: dict[str, int] = {}
    values: dict[str, float] = {}
    for bound in skills:
        bound.skill.track(ctx)  # every step, also when the skill may not act (e.g. FE-UMGF's grasp buffer)
        if bound.skill.category == "manipulation" and not ctx.manipulation_allowed:
            continue
        actions = bound.skill.propose(ctx)
        counts[bound.name] = len(actions)
        if not actions:
            continue
        batch = bound.batch(ctx, actions)
        total, parts = objective.score(ctx, batch)
        i = int(np.argmax(total))
        values[bound.name] = float(total[i])
        if best is None or total[i] > best.value:
            terms = {k: float(v[i]) for k, v in parts.items()}
            best = Decision(bound.name, actions[i], float(total[i]), terms, counts, values, batch, i)
    if best is None:
        raise RuntimeError("no skill proposed an action")
    best.candidates, best.best = counts, values
    return best


StepCallback = Callable[[int, Decision, Outcome, "EvidentialMap"], None]


def run_msas(
    sim: Simulator,
    belief: EvidentialMap,
    observe_model: ObservationModel,
    skills: list[BoundSkill],
    objective: Objective,
    make_ctx: Callable[[int, EvidentialMap, set[int], bool], DecisionContext],
    cfg: MSASConfig,
    steps: int,
    on_step: StepCallback,
) -> EvidentialMap:
    """The MSAS loop of the paper: T_max actions; after a manipulation the belief becomes the effect
    model's prediction, visited views are cleared and the manipulation's associated best view is
    executed (both count towards T_max). Manipulation stops for good once an object falls or leaves."""
    visited: set[int] = set()
    manipulation_ok, just_manipulated = True, False
    lo, hi = cfg.manipulation_window
    for step in range(steps):
        # right after a manipulation only views compete: the argmax is its associated next-best view
        allowed = manipulation_ok and lo <= step <= hi and not just_manipulated
        ctx = make_ctx(step, belief, visited, allowed)
        decision = decide(ctx, skills, objective)
        skill = next(b for b in skills if b.name == decision.skill).skill
        outcome = skill.execute(sim, decision.action, ctx)
        just_manipulated = decision.batch.prediction is not None
        if outcome.observation is not None:
            belief = observe_model.update(belief, outcome.observation)
            visited.add(int(getattr(decision.action, "view", -1)))
        elif just_manipulated:
            belief = decision.batch.prediction.beliefs[decision.index]  # type: ignore[union-attr]
            visited.clear()
            manipulation_ok = manipulation_ok and not outcome.fell_or_left
        on_step(step, decision, outcome, belief)
    return belief

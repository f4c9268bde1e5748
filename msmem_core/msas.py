"""Multi-Skill Action Selection (MSAS): score every skill's candidates with one objective, act, repeat.

The episode's rules live here: the start view, which views count as visited, when manipulation is
allowed, what the belief becomes after an action, and the outcome bookkeeping every manipulation gets
(displacement, objects that fell over or left the shelf). Every stage of a step is a span
(``msmem_core.util.trace``) that a tracer given to ``run_msas`` or ``decide`` observes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, overload

import numpy as np
from numpy.typing import NDArray

from msmem_core.config import FALL_TILT_DEG
from msmem_core.errors import PluginError
from msmem_core.interfaces import (
    Action,
    CandidateBatch,
    DecisionContext,
    EffectModel,
    ObservationModel,
    Outcome,
    PerceptionAction,
    Simulator,
    Skill,
    Term,
    Workspace,
)
from msmem_core.map.belief import EvidentialMap
from msmem_core.util.trace import Tracer, span, tracing

if TYPE_CHECKING:
    from msmem_core.config import MSASConfig
    from msmem_core.map.belief import EvidentialMap
    from msmem_core.map.ig import IGService
    from msmem_core.world.scene import ShelfSpec

MOVED_M = 0.005
"""An object displaced more than this by a manipulation is listed in its outcome's ``info["moved"]``."""


@dataclass
class BoundSkill:
    """A skill with its name and, for manipulation, the effect model predicting its outcome."""

    name: str
    skill: Skill
    effect_model: EffectModel | None = None

    def batch(self, ctx: DecisionContext, actions: list[Action]) -> CandidateBatch:
        """The candidates with what terms score: view indices, or the effect model's prediction
        (span ``predict``, info ``ctx`` and ``actions``; result: the ``Prediction``)."""
        if self.skill.category == "perception":
            views = []
            for a in actions:
                if not isinstance(a, PerceptionAction):
                    raise PluginError(
                        f"perception skill {self.name!r} proposed a {type(a).__name__} ({a.kind!r}) without a view "
                        "index: a perception skill's actions must be msmem_core.interfaces.PerceptionAction, which "
                        "names the viewpoint it observes from (`view`). A skill is a perception skill unless its "
                        "class says `category = \"manipulation\"` (then an effect model predicts its actions)")
                views.append(a.view)
            return CandidateBatch(self.name, "perception", actions, view_indices=np.array(views, dtype=np.int64))
        if self.effect_model is None:
            raise RuntimeError(f"manipulation skill {self.name!r} has no effect model")
        with span("predict", self.name, ctx=ctx, actions=actions) as s:
            prediction = self.effect_model.predict(ctx.belief, actions, ctx.workspace)
            if s:
                s.result = prediction
        if prediction.base is not ctx.belief or len(prediction) != len(actions):
            raise PluginError(f"the effect model of skill {self.name!r} ({type(self.effect_model).__name__}) must "
                              f"return one change per action ({len(prediction)} for {len(actions)}) relative to the "
                              "belief it was given (Prediction.base)")
        return CandidateBatch(self.name, "manipulation", actions, prediction=prediction)


@dataclass
class Objective:
    """Weighted sum of term plugins; a term scores only the categories it applies to."""

    terms: list[tuple[str, float, Term]]

    def score(self, ctx: DecisionContext,
              batch: CandidateBatch) -> tuple[NDArray[np.float64], dict[str, NDArray[np.float64]]]:
        """Every applicable term's values (span ``term`` each, info ``term`` and ``batch``) and their weighted sum."""
        total = np.zeros(len(batch.actions))
        parts: dict[str, NDArray[np.float64]] = {}
        for name, weight, term in self.terms:
            if batch.category in term.applies_to:
                with span("term", batch.skill, term=name, batch=batch) as s:
                    parts[name] = np.asarray(term.score(ctx, batch), dtype=np.float64)
                    if s:
                        s.result = parts[name]
                total += weight * parts[name]
        return total, parts

    @overload
    def best(self, ctx: DecisionContext, batch: CandidateBatch, admissible: None = None,
             stop_at: float | None = None) -> tuple[int, float, dict[str, float], int]: ...

    @overload
    def best(self, ctx: DecisionContext, batch: CandidateBatch, admissible: Callable[[int], bool] | None,
             stop_at: float | None = None) -> tuple[int, float, dict[str, float], int] | None: ...

    def best(self, ctx: DecisionContext, batch: CandidateBatch,
             admissible: Callable[[int], bool] | None = None,
             stop_at: float | None = None) -> tuple[int, float, dict[str, float], int] | None:
        """Argmax of the objective over a batch with the winner scored exactly.

        Terms may approximate (screen) in ``score``; the current argmax is refined through
        ``Term.refine`` (span ``refine``, info ``term``, ``batch`` and ``indices``) until it is a
        candidate every term scored exactly, so the value compared across skills is always exact.
        With ``admissible``, an exactly scored argmax it refuses is left out and the next one taken
        (None when it refuses them all); with ``stop_at`` too, an argmax whose exact value is at most
        ``stop_at`` (it cannot win) is returned without asking ``admissible``.
        Returns (index, value, term values, refinements made).
        """
        total, parts = self.score(ctx, batch)
        refined = 0
        while True:
            if admissible is not None and not np.isfinite(total).any():
                return None
            i = int(np.argmax(total))
            changed = False
            for name, weight, term in self.terms:
                if name not in parts:
                    continue
                with span("refine", batch.skill, term=name, batch=batch, indices=[i]) as s:
                    exact = term.refine(ctx, batch, np.array([i]))
                    if s:
                        s.result = exact
                if exact is not None:
                    total[i] += weight * (float(exact[0]) - parts[name][i])
                    parts[name][i] = float(exact[0])
                    changed = True
            if not changed:
                if admissible is None or (stop_at is not None and total[i] <= stop_at) or admissible(i):
                    return i, float(total[i]), {k: float(v[i]) for k, v in parts.items()}, refined
                total[i] = -np.inf
                continue
            refined += 1


@dataclass
class Decision:
    skill: BoundSkill
    """The skill whose action won (``skill.name`` is its name in config)."""
    action: Action
    value: float
    terms: dict[str, float]
    candidates: dict[str, int]
    """Number of candidates each skill proposed."""
    best: dict[str, float]
    """Best objective value of each skill that proposed something."""
    batch: CandidateBatch
    index: int
    unreachable: dict[str, int] = field(default_factory=dict)
    """Per skill whose candidates were checked against the run's robot (a manipulation skill, with an
    arm): how many of those checked the robot cannot follow (``Skill.tool_path``, ``Robot.reach_path``)."""
    reach_checked: dict[str, int] = field(default_factory=dict)
    """Per such skill, how many candidates were checked: only those that could win are (``decide``)."""
    funnel: dict[str, dict[str, int]] = field(default_factory=dict)
    """Per skill asked to propose, its candidates left after each stage (``interfaces.Funnel``)."""


def decide(ctx: DecisionContext, skills: list[BoundSkill], objective: Objective,
           tracer: Tracer | None = None) -> Decision:
    """Best action over all skills by the objective (ties go to the skill listed first).

    With a robot that has an arm, a manipulation candidate must have a tool path the robot can follow
    (``Robot.reach_path``). Only the candidates that could win are checked, best first: the skill's
    exactly scored argmax, if it beats the best value so far, is checked; one the robot cannot follow
    is left out and the next taken (``Objective.best``'s ``admissible``, given by a ``ReachFilter``). A
    skill's best value that cannot win is reported unchecked.

    Every skill asked to propose has its candidate funnel in ``Decision.funnel`` (``ctx.funnel``: the
    skill's own stages, then ``proposed``, with an arm ``reach_checked`` and ``reachable``, and ``chosen``).

    Spans (reported to ``tracer``, or to the active one): ``decide`` (info ``ctx``; result: the
    ``Decision``) and inside it, per skill, ``track``, ``propose`` (result: the actions), ``predict``
    (``BoundSkill.batch``), ``score`` (info ``batch``; result: ``Objective.best``'s tuple) with
    its ``term``, ``refine`` and ``reach`` spans.
    """
    with tracing(tracer), span("decide", ctx=ctx) as top:
        best: Decision | None = None
        counts: dict[str, int] = {}
        values: dict[str, float] = {}
        unreachable: dict[str, int] = {}
        checked: dict[str, int] = {}
        obstacles = BeliefObstacles(ctx)
        for bound in skills:
            with span("track", bound.name, ctx=ctx):
                bound.skill.track(ctx)  # every step, also when the skill may not act (e.g. FE-UMGF's buffer)
            if bound.skill.category == "manipulation" and not ctx.manipulation_allowed:
                continue
            ctx.funnel.skill = bound.name
            with span("propose", bound.name, ctx=ctx) as s:
                actions = bound.skill.propose(ctx)
                if s:
                    s.result = actions
            ctx.funnel.count("proposed", len(actions))
            counts[bound.name] = len(actions)
            if not actions:
                continue
            reach = ReachFilter.of(bound, actions, ctx, obstacles)
            batch = bound.batch(ctx, actions)
            with span("score", bound.name, ctx=ctx, batch=batch) as s:
                scored = objective.best(ctx, batch, None if reach is None else reach.admissible,
                                        None if best is None else best.value)
                if s:
                    s.result = scored
            if reach is not None:
                checked[bound.name], unreachable[bound.name] = reach.checked, reach.unreachable
                ctx.funnel.count("reach_checked", reach.checked)
                ctx.funnel.count("reachable", reach.checked - reach.unreachable)
            if scored is None:  # the robot can follow none of them
                continue
            i, value, terms, _ = scored
            values[bound.name] = value
            if best is None or value > best.value:
                best = Decision(bound, actions[i], value, terms, counts, values, batch, i)
        if best is None:
            raise RuntimeError("no skill proposed an action")
        best.candidates, best.best, best.unreachable, best.reach_checked = counts, values, unreachable, checked
        for name in counts:
            ctx.funnel.skill = name
            ctx.funnel.count("chosen", int(name == best.skill.name))
        best.funnel = {name: ctx.funnel.stages(name) for name in counts}
        if top:
            top.result = best
        return best


class BeliefObstacles:
    """Gives the run's robot the belief's occupied space as obstacles (``Robot.use_obstacles`` with the
    ``GridSpec.column_boxes`` of expected occupancy > 0.5): once per decision, when first needed."""

    def __init__(self, ctx: DecisionContext) -> None:
        self.ctx = ctx
        self.given = False

    def give(self) -> None:
        """Set the obstacles up, unless this decision already did."""
        robot = self.ctx.workspace.robot
        if self.given or robot is None:
            return
        belief = self.ctx.belief
        robot.use_obstacles(belief.grid.column_boxes(belief.expected_occupancy() > 0.5))
        self.given = True


@dataclass
class ReachFilter:
    """Whether the run's robot can follow the tool path of each of one skill's candidates at one
    decision (``reachable_actions``), asked candidate by candidate as ``Objective.best``'s
    ``admissible``, so that only candidates that could win are checked (span ``reach`` each)."""

    name: str
    """The skill's name in config."""
    skill: Skill
    actions: list[Action]
    ctx: DecisionContext
    obstacles: BeliefObstacles
    """The decision's obstacle set-up, given to the robot before the first check."""
    checked: int = 0
    """Candidates checked so far."""
    unreachable: int = 0
    """Checked candidates the robot cannot follow."""

    @classmethod
    def of(cls, bound: BoundSkill, actions: list[Action], ctx: DecisionContext,
           obstacles: BeliefObstacles) -> ReachFilter | None:
        """The filter of a skill's candidates; None when they are not checked (no robot with an arm, or
        a perception skill: its views are the skill's to check)."""
        robot = ctx.workspace.robot
        if robot is None or not robot.arm or bound.skill.category != "manipulation":
            return None
        return cls(bound.name, bound.skill, actions, ctx, obstacles)

    def admissible(self, i: int) -> bool:
        """Whether the robot can follow candidate ``i``'s tool path (a candidate without one is admissible)."""
        self.obstacles.give()
        with span("reach", self.name, ctx=self.ctx):
            ok = bool(reachable_actions(self.skill, [self.actions[i]], self.ctx.workspace))
        self.checked += 1
        self.unreachable += not ok
        return ok


def reachable_actions(skill: Skill, actions: list[Action], workspace: Workspace) -> list[Action]:
    """The ``actions`` whose tool path (``skill.tool_path``) the workspace's robot can follow; actions
    without a path are kept."""
    robot = workspace.robot
    if robot is None:
        return actions
    kept = []
    for a in actions:
        path = skill.tool_path(a, workspace)
        if path is None or robot.reach_path(path, workspace.shelf).reachable:
            kept.append(a)
    return kept


def bev_confidence(belief: EvidentialMap, interior: NDArray[np.bool_], power: float = 1.8) -> NDArray[np.float64]:
    """MEM's 2-D (bird's-eye) class confidence ``[X, Y]`` after a 5x5 median filter.

    Per column the class distribution of its highest believed-occupied voxel (expected occupancy
    > 0.5) inside the shelf interior, or, in a column with none, the mean distribution over its
    interior voxels (so an observed empty column is confidently background and an unseen one is
    not). Probabilities are sharpened as ``p^power`` and renormalised ([MEM]), the max taken.
    """
    from scipy.ndimage import distance_transform_edt, median_filter

    probs = belief.class_probs().astype(np.float64)  # [C, X, Y, Z]
    occ = (belief.expected_occupancy() > 0.5) & interior
    nz = interior.shape[2]
    top = nz - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    has_top = np.asarray(occ.any(axis=2))
    at_top = np.take_along_axis(probs, top[None, :, :, None], axis=3)[..., 0]
    n_in = np.maximum(interior.sum(axis=2), 1)
    mean = (probs * interior[None]).sum(axis=3) / n_in
    col = np.where(has_top[None], at_top, mean)
    q = col**power
    total = q.sum(axis=0, keepdims=True)
    conf = np.divide(q, total, out=np.zeros_like(q), where=total > 0).max(axis=0)
    cols = interior.any(axis=2)
    if cols.any() and not cols.all():  # cells off the shelf take their nearest shelf cell's value,
        _, (ix, iy) = distance_transform_edt(~cols, return_indices=True)  # so the filter sees only the shelf
        conf = conf[ix, iy]
    return median_filter(conf, size=5, mode="nearest")


def mapped_fraction(belief: EvidentialMap, interior: NDArray[np.bool_], conf_cutoff: float) -> float:
    """Fraction of the shelf's BEV cells whose (filtered) class confidence exceeds ``conf_cutoff``."""
    cols = interior.any(axis=2)
    return float((bev_confidence(belief, interior)[cols] > conf_cutoff).mean())


def disturbed_region(changed: NDArray[np.bool_], margin_voxels: int) -> NDArray[np.bool_]:
    """[X, Y, Z]: ``changed`` dilated by ``margin_voxels`` (26-neighbourhood)."""
    from scipy import ndimage

    if margin_voxels <= 0:
        return changed
    return ndimage.binary_dilation(changed, structure=np.ones((3, 3, 3), dtype=bool), iterations=margin_voxels)


def cap_evidence(belief: EvidentialMap, changed: NDArray[np.bool_], cap: float, margin_voxels: int) -> EvidentialMap:
    """``belief`` with the evidence of ``changed`` (dilated by ``margin_voxels``) shrunk towards the prior
    (``EvidentialMap.capped``): where alpha + beta > cap, alpha - 1, beta - 1 and eta - 1 are scaled by
    (cap - 2) / (alpha + beta - 2). Expected occupancy moves towards 0.5 but stays on its side of it and
    the class argmax is kept, except with ``cap`` 2, which resets those voxels to the prior."""
    return belief.capped(disturbed_region(changed, margin_voxels), cap)


# ---------------------------------------------------------------------------------------- outcomes
def displacements(before: dict[int, NDArray[np.float64]], after: dict[int, NDArray[np.float64]]) -> dict[int, float]:
    """XY displacement (m) of every object present in both pose sets."""
    return {i: float(np.linalg.norm(after[i][:2, 3] - before[i][:2, 3])) for i in before if i in after}


def fallen_or_left(before: dict[int, NDArray[np.float64]], after: dict[int, NDArray[np.float64]], shelf: ShelfSpec,
                   tilt_deg: float = FALL_TILT_DEG, removed: Iterable[int] = ()) -> list[int]:
    """Objects (other than ``removed``) that vanished, whose up axis tilted more than ``tilt_deg``, or
    whose origin left the shelf interior (sides, back, front; or dropped 2 cm below its floor)."""
    lo, hi = shelf.interior_lower, shelf.interior_upper
    gone = set(removed)
    out = []
    for i, t0 in before.items():
        if i in gone:
            continue
        t1 = after.get(i)
        if t1 is None:
            out.append(i)
            continue
        tilt = math.degrees(math.acos(float(np.clip(t0[:3, 2] @ t1[:3, 2], -1.0, 1.0))))
        pos = t1[:3, 3]
        outside = not (lo[0] <= pos[0] <= hi[0] and lo[1] <= pos[1] <= hi[1]) or pos[2] < lo[2] - 0.02
        if tilt > tilt_deg or outside:
            out.append(i)
    return out


def execute_measured(skill: Skill, sim: Simulator, action: Action, ctx: DecisionContext,
                     fall_tilt_deg: float = FALL_TILT_DEG) -> Outcome:
    """``skill.execute`` with the bookkeeping every manipulation gets, done here once for all skills:
    ``sim.object_poses()`` before and after give the outcome's ``displacement_m``, ``fell_or_left``
    (``fallen_or_left``: the objects the skill removed are not counted) and ``info["moved"]``.
    Perception actions are executed as they are. Reads ``ctx.shelf`` only."""
    if action.category != "manipulation":
        return skill.execute(sim, action, ctx)
    before = sim.object_poses()
    outcome = skill.execute(sim, action, ctx)
    after = sim.object_poses()
    outcome.displacement_m = displacements(before, after)
    outcome.fell_or_left = fallen_or_left(before, after, ctx.shelf, fall_tilt_deg, outcome.removed)
    outcome.info["moved"] = [i for i, d in outcome.displacement_m.items() if d > MOVED_M]
    return outcome


# -------------------------------------------------------------------------------------------- the loop
StepCallback = Callable[[int, Decision, Outcome, EvidentialMap], None]


def run_msas(
    sim: Simulator,
    observe_model: ObservationModel,
    skills: list[BoundSkill],
    objective: Objective,
    ig: IGService,
    workspace: Workspace,
    cfg: MSASConfig,
    steps: int,
    start_view: int,
    seed: int,
    on_step: StepCallback,
    on_start: Callable[[EvidentialMap], None] | None = None,
    tracer: Tracer | None = None,
) -> EvidentialMap:
    """One episode of MSAS on a reset simulator; returns the final belief.

    The belief starts from the prior and the observation from ``start_view`` (``on_start`` sees it); the
    first decision counts that view as visited. Then ``steps`` (T_max) actions: every skill proposes,
    the objective picks (``decide``, on a ``DecisionContext`` whose ``rng`` is seeded with ``seed``),
    the action is executed (``execute_measured``, span ``execute``: info ``ctx``, ``sim`` and
    ``decision``; result: the ``Outcome``), and ``on_step`` sees the step. A view is integrated by the
    observation model and counted as visited. After a manipulation the belief becomes the effect model's
    prediction (capped where it changed by ``cfg.disturbed_evidence_cap``); after one that reports
    failure it stays as it was, capped where the prediction would have changed it
    (``cfg.failed_manipulation_cap``); the observation model is told the capped region
    (``ObservationModel.disturbed``, or ``failed_manipulation`` after a failure), for evidence it keeps
    of its own. Either way visited views are cleared, and the next step may only choose a view, the
    manipulation's associated best view (both count towards T_max). Manipulation is allowed, in a run
    with a manipulation skill, in ``cfg.manipulation_window``, not once ``cfg.mapped_fraction`` of the
    BEV cells are mapped (``mapped_fraction``), and never again after an object fell over or left the shelf (tilt over
    ``cfg.fall_tilt_deg``). ``tracer`` sees every span of the episode.
    """
    from msmem_core.world.voxelize import interior_mask

    rng = np.random.default_rng(seed)
    with tracing(tracer):
        belief = observe_model.update(EvidentialMap.empty(workspace.grid, workspace.num_classes),
                                     sim.observe(ig.viewpoints[start_view]))
        if on_start is not None:
            on_start(belief)
        visited: set[int] = set()
        interior: NDArray[np.bool_] | None = None
        # a run without a manipulation skill never allows manipulation (the views then compete only among themselves)
        manipulation_ok = any(b.skill.category == "manipulation" for b in skills)
        just_manipulated, last_manipulation = False, -1
        lo, hi = cfg.manipulation_window
        for step in range(steps):
            # right after a manipulation only views compete: the argmax is its associated next-best view
            allowed = manipulation_ok and lo <= step <= hi and not just_manipulated
            if allowed and cfg.mapped_fraction < 1.0:
                if interior is None:
                    interior = interior_mask(workspace.shelf, workspace.grid)
                allowed = mapped_fraction(belief, interior, cfg.conf_cutoff) < cfg.mapped_fraction
            seen = visited | {start_view} if step == 0 else set(visited)
            ctx = DecisionContext(step, belief, ig, ig.viewpoints, seen, workspace, rng, allowed, cfg.tau_chi,
                                  last_manipulation)
            decision = decide(ctx, skills, objective)
            with span("execute", decision.skill.name, ctx=ctx, sim=sim, decision=decision) as s:
                outcome = execute_measured(decision.skill.skill, sim, decision.action, ctx, cfg.fall_tilt_deg)
                if s:
                    s.result = outcome
            prediction = decision.batch.prediction
            just_manipulated = prediction is not None
            if outcome.observation is not None:
                with span("observe", decision.skill.name, ctx=ctx):
                    belief = observe_model.update(belief, outcome.observation)
                if isinstance(decision.action, PerceptionAction):
                    visited.add(decision.action.view)
            elif prediction is not None:
                if outcome.success:
                    belief, cap = prediction.belief(decision.index), cfg.disturbed_evidence_cap
                else:  # the prediction is that of success: keep the belief, doubt where it would have changed
                    cap = cfg.failed_manipulation_cap
                if cap is not None:
                    changed = np.zeros(workspace.grid.size, dtype=bool)
                    changed[prediction.changes[decision.index].idx] = True
                    region = disturbed_region(changed.reshape(workspace.grid.shape), cfg.disturbed_margin_voxels)
                    belief = belief.capped(region, cap)
                    tell = observe_model.disturbed if outcome.success else observe_model.failed_manipulation
                    tell(region, cap)  # for evidence the model keeps of its own
                visited.clear()
                last_manipulation = step
                manipulation_ok = manipulation_ok and not outcome.fell_or_left
            on_step(step, decision, outcome, belief)
    return belief

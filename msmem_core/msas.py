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
    from msmem_core.config import MSASConfig
    from msmem_core.map.belief import EvidentialMap
    from msmem_core.map.ig import IGField, IGService
    from msmem_core.world.grid import GridSpec
    from msmem_core.world.gripper import GripperSpec
    from msmem_core.world.scene import ShelfSpec


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
    last_manipulation: int = -1
    """Step of the episode's last executed manipulation (-1: none yet); ``visited`` holds only the
    views taken since then, and the belief outside them may be an effect model's prediction."""

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
        prediction = self.effect_model.predict(ctx.belief, actions)
        return CandidateBatch(self.name, "manipulation", actions, prediction=prediction)


@dataclass
class Objective:
    """Weighted sum of term plugins; a term scores only the categories it applies to."""

    terms: list[tuple[str, float, Term]]

    def score(self, ctx: DecisionContext,
              batch: CandidateBatch) -> tuple[NDArray[np.float64], dict[str, NDArray[np.float64]]]:
        total = np.zeros(len(batch.actions))
        parts: dict[str, NDArray[np.float64]] = {}
        for name, weight, term in self.terms:
            if batch.category in term.applies_to:
                parts[name] = np.asarray(term.score(ctx, batch), dtype=np.float64)
                total += weight * parts[name]
        return total, parts

    def best(self, ctx: DecisionContext, batch: CandidateBatch) -> tuple[int, float, dict[str, float], int]:
        """Argmax of the objective over a batch with the winner scored exactly.

        Terms may approximate (screen) in ``score``; the current argmax is refined through
        ``Term.refine`` until it is a candidate every term scored exactly, so the value compared
        across skills is always exact. Returns (index, value, term values, refinements made).
        """
        total, parts = self.score(ctx, batch)
        refined = 0
        while True:
            i = int(np.argmax(total))
            changed = False
            for name, weight, term in self.terms:
                if name not in parts:
                    continue
                exact = term.refine(ctx, batch, np.array([i]))
                if exact is not None:
                    total[i] += weight * (float(exact[0]) - parts[name][i])
                    parts[name][i] = float(exact[0])
                    changed = True
            if not changed:
                return i, float(total[i]), {k: float(v[i]) for k, v in parts.items()}, refined
            refined += 1


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
        i, value, terms, _ = objective.best(ctx, batch)
        values[bound.name] = value
        if best is None or value > best.value:
            best = Decision(bound.name, actions[i], value, terms, counts, values, batch, i)
    if best is None:
        raise RuntimeError("no skill proposed an action")
    best.candidates, best.best = counts, values
    return best


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


StepCallback = Callable[[int, Decision, Outcome, "EvidentialMap"], None]


def cap_evidence(belief: EvidentialMap, changed: NDArray[np.bool_], cap: float, margin_voxels: int) -> EvidentialMap:
    """``belief`` with the evidence of ``changed`` (dilated by ``margin_voxels``) shrunk towards the prior:
    where alpha + beta > cap, alpha - 1, beta - 1 and eta - 1 are scaled by (cap - 2) / (alpha + beta - 2).
    Expected occupancy moves towards 0.5 but stays on its side of it and the class argmax is kept,
    except with ``cap`` 2, which resets those voxels to the prior."""
    from scipy import ndimage

    region = changed if margin_voxels <= 0 else ndimage.binary_dilation(
        changed, structure=np.ones((3, 3, 3), dtype=bool), iterations=margin_voxels)
    idx = np.flatnonzero(region)
    a, b = belief.alpha.reshape(-1)[idx], belief.beta.reshape(-1)[idx]
    s = a + b
    big = s > cap
    idx, a, b, s = idx[big], a[big], b[big], s[big]
    f = ((cap - 2.0) / (s - 2.0)).astype(np.float32)
    out = belief.copy()
    out.alpha.reshape(-1)[idx] = 1.0 + f * (a - 1.0)
    out.beta.reshape(-1)[idx] = 1.0 + f * (b - 1.0)
    eta = out.eta.reshape(belief.num_classes, -1)
    eta[:, idx] = 1.0 + f[None] * (eta[:, idx] - 1.0)
    return out


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
    executed (both count towards T_max). Manipulation stops for good once an object falls or leaves,
    and is not allowed once ``cfg.mapped_fraction`` of the BEV cells are mapped (``mapped_fraction``)."""
    from msmem_core.world.groundtruth import interior_mask

    visited: set[int] = set()
    interior: NDArray[np.bool_] | None = None
    manipulation_ok, just_manipulated, last_manipulation = True, False, -1
    lo, hi = cfg.manipulation_window
    for step in range(steps):
        # right after a manipulation only views compete: the argmax is its associated next-best view
        allowed = manipulation_ok and lo <= step <= hi and not just_manipulated
        if allowed and cfg.mapped_fraction < 1.0:
            if interior is None:
                probe = make_ctx(step, belief, visited, False)
                interior = interior_mask(probe.shelf, probe.grid)
            allowed = mapped_fraction(belief, interior, cfg.conf_cutoff) < cfg.mapped_fraction
        ctx = make_ctx(step, belief, visited, allowed)
        ctx.last_manipulation = last_manipulation
        decision = decide(ctx, skills, objective)
        skill = next(b for b in skills if b.name == decision.skill).skill
        outcome = skill.execute(sim, decision.action, ctx)
        just_manipulated = decision.batch.prediction is not None
        if outcome.observation is not None:
            belief = observe_model.update(belief, outcome.observation)
            visited.add(int(getattr(decision.action, "view", -1)))
        elif just_manipulated:
            prediction = decision.batch.prediction
            belief = prediction.beliefs[decision.index]  # type: ignore[union-attr]
            if cfg.disturbed_evidence_cap is not None:
                belief = cap_evidence(belief, prediction.changed[decision.index],  # type: ignore[union-attr]
                                      cfg.disturbed_evidence_cap, cfg.disturbed_margin_voxels)
            visited.clear()
            last_manipulation = step
            manipulation_ok = manipulation_ok and not outcome.fell_or_left
        on_step(step, decision, outcome, belief)
    return belief

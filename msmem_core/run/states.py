"""Mid-episode decision states, for measuring one MSAS decision outside an episode.

``msmem perf step`` and evaluations of belief models (``msmem eval belief-models --threshold-check``)
decide on the belief an episode would have after a number of views: ``mid_episode_state`` takes the
start view and seeded random views in the episode's simulator, integrates them with its observation
model and lets every skill track every step as in ``run_msas``; ``decision_context`` is the context
of the next step; ``clone_skills`` copies skills with their state, so a decision can be repeated.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from msmem_core.interfaces import DecisionContext
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGService
from msmem_core.msas import BoundSkill
from msmem_core.run.runner import Episode


@dataclass
class EpisodeState:
    """A mid-episode state: the belief, the skills after tracking every earlier step, visited views."""

    belief: EvidentialMap
    skills: list[BoundSkill]
    visited: set[int]
    """The views ``run_msas`` counts as visited at ``step`` (the start view only at step 0)."""
    step: int
    views: list[int]
    """The views observed, in order (the start view first)."""


def clone_skills(skills: list[BoundSkill]) -> list[BoundSkill]:
    """Deep copies of the skills (their state, e.g. a grasp buffer) sharing effect models and any
    torch module (weights are read-only)."""
    out = []
    for b in skills:
        memo = {id(v): v for v in vars(b.skill).values() if hasattr(v, "state_dict")}
        out.append(BoundSkill(b.name, copy.deepcopy(b.skill, memo), b.effect_model))
    return out


def visited_at(order: list[int], step: int) -> set[int]:
    """What ``run_msas`` counts as visited at ``step`` after observing ``order`` (the start view
    first): the views taken since, and the start view at step 0 only."""
    return set(order[1 : step + 1]) | ({order[0]} if step == 0 else set())


def decision_context(ep: Episode, belief: EvidentialMap, visited: set[int], step: int, allowed: bool = True,
                     seed: int = 0, ig: IGService | None = None) -> DecisionContext:
    """The context of a decision at ``step`` on ``belief`` (no manipulation yet), its ``rng`` seeded
    from the run's seed, ``seed`` and ``step``; ``ig`` replaces the episode's IG service."""
    cfg = ep.cfg
    return DecisionContext(step, belief, ig or ep.ig, ep.viewpoints, set(visited), ep.workspace,
                           np.random.default_rng([cfg.seed, seed, step]), allowed, cfg.msas.tau_chi)


def mid_episode_state(ep: Episode, views: int, seed: int) -> EpisodeState:
    """The start view and ``views - 1`` seeded random views, observed in the episode's (reset)
    simulator and integrated by its observation model; every skill tracks every step as in
    ``run_msas`` (on copies of the episode's skills). The returned state is that of step
    ``views - 1`` (the belief holds ``views`` views)."""
    if views < 1:
        raise ValueError("views must be >= 1")
    rng = np.random.default_rng(seed)
    start = ep.start_view
    others = np.setdiff1d(np.arange(len(ep.viewpoints)), [start])
    order = [start, *(int(v) for v in rng.choice(others, size=views - 1, replace=False))]
    skills = clone_skills(ep.skills)
    belief = ep.observe_model.update(EvidentialMap.empty(ep.ig.grid, ep.scene.num_classes),
                                    ep.sim.observe(ep.viewpoints[start]))
    for step in range(views - 1):
        ctx = decision_context(ep, belief, visited_at(order, step), step, allowed=False)
        for b in skills:
            b.skill.track(ctx)
        belief = ep.observe_model.update(belief, ep.sim.observe(ep.viewpoints[order[step + 1]]))
    step = views - 1
    return EpisodeState(belief, skills, visited_at(order, step), step, order)

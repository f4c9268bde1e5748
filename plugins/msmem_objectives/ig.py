"""Objective term ``ig``: the information-gain part of OIG (paper eq. OIG).

Views: IG(v | belief), and for the argmax view the greedy second step max_v' IG(v' | after v) is
added ([MEM]'s two-step view value). Manipulations: max_v IG(v | predicted belief), computed
incrementally (``IGService.view_ig_delta``): per view, only the rays crossing a candidate's changed
voxels are re-scored, which equals a full re-score of every predicted belief. By default the
candidates are first screened at a quarter of the rays (every 2nd ray in u and v, as [MEM] screens
at a coarser density) and the 8 best re-scored at full density. With a robot that cannot reach every
view (``ctx.workspace.robot``), the second view and the best view after a manipulation are chosen among
the views it reaches, as the view skill's candidates are.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import CandidateBatch, DecisionContext, Term
from msmem_core.map.ig import IGDelta


class IGTermConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    two_step: bool = True
    """Add the greedy second view's IG to the best view's value."""
    incremental: bool = True
    """Score manipulation candidates by re-scoring only the rays their changes touch (exact);
    False re-scores every predicted belief in full (the reference, many times slower)."""
    screen_ray_step: int = Field(2, ge=1, le=16)
    """Screen manipulation candidates with every n-th IG ray in both image axes (1: no screening).
    The ``finalists`` best by the screened value are re-scored at full density, so the values
    compared with the view branch are at the same density as views (docs/explanation/push.md, "Objective terms")."""
    finalists: int = Field(8, ge=1)
    """Candidates re-scored at full density after screening."""


def reachable_mask(ctx: DecisionContext) -> NDArray[np.bool_] | None:
    """[V] the views the run's robot reaches (cached by the robot); None when it reaches them all."""
    robot = ctx.workspace.robot
    if robot is None:
        return None
    mask = np.asarray(robot.reachable_views(ctx.viewpoints, ctx.shelf), dtype=bool)
    return None if mask.all() else mask


def best_view(values: NDArray[np.float64], mask: NDArray[np.bool_] | None) -> NDArray[np.float64]:
    """Per row of ``values`` [K, V], the largest value over the views in ``mask`` (all views: None)."""
    if mask is None or not mask.any():
        return values.max(axis=1)
    return values[:, mask].max(axis=1)


def ig_deltas(ctx: DecisionContext, batch: CandidateBatch) -> list[IGDelta]:
    """The IG-field change of each manipulation candidate (from its ``Prediction.changes``)."""
    assert batch.prediction is not None
    return ctx.ig.belief_deltas(ctx.field, batch.prediction.changes)


def _manipulation_state(ctx: DecisionContext, batch: CandidateBatch, cfg: IGTermConfig) -> dict[str, Any]:
    """Per-batch cache: the candidates' values, which of them are exact, and their IG deltas."""
    assert batch.prediction is not None
    key = ("manipulation_ig", id(batch.prediction), cfg.incremental, cfg.screen_ray_step, cfg.finalists)
    if key in ctx.cache:
        return ctx.cache[key]
    state: dict[str, Any] = {"deltas": None, "mask": reachable_mask(ctx)}
    mask = state["mask"]
    if not cfg.incremental:
        fields = [ctx.ig.prepare(b, before=ctx.field) for b in batch.prediction.beliefs]
        out = best_view(np.asarray(ctx.ig.view_ig(fields), dtype=np.float64), mask)
        exact = np.ones(len(out), dtype=bool)
    else:
        deltas = state["deltas"] = ig_deltas(ctx, batch)
        exact = np.ones(len(deltas), dtype=bool)
        if cfg.screen_ray_step > 1 and len(deltas) > cfg.finalists:
            coarse = best_view(ctx.ig.view_ig_delta(ctx.field, deltas, ray_step=cfg.screen_ray_step), mask)
            top = np.argsort(-coarse, kind="stable")[: cfg.finalists]
            full = best_view(ctx.ig.view_ig_delta(ctx.field, [deltas[i] for i in top]), mask)
            ratio = float(np.median(full / np.maximum(coarse[top], 1e-12)))
            out = np.minimum(coarse * ratio, full.min())
            out[top] = full
            exact[:] = False
            exact[top] = True
        else:
            out = best_view(ctx.ig.view_ig_delta(ctx.field, deltas), mask)
    state["values"], state["exact"] = out, exact
    ctx.cache[key] = state
    return state


def manipulation_ig(ctx: DecisionContext, batch: CandidateBatch,
                    config: IGTermConfig | None = None) -> NDArray[np.float64]:
    """``max_v IG(v | predicted belief)`` per manipulation candidate [K] (cached per batch in ``ctx.cache``).

    With screening (``screen_ray_step > 1`` and more than ``finalists`` candidates), the finalists
    get their exact full-density value; every other candidate gets its screened value times the
    median full/screened ratio of the finalists, capped at the lowest finalist value, so the
    screening order stands and no non-finalist out-scores a finalist on IG. A screened candidate
    that still wins the objective (through other terms) is re-scored exactly by :meth:`IGTerm.refine`
    before it is compared with other skills.
    """
    return _manipulation_state(ctx, batch, config or IGTermConfig())["values"].copy()


class IGTerm(Term):
    def __init__(self, config: IGTermConfig | None = None) -> None:
        self.config = config or IGTermConfig()

    def score(self, ctx: DecisionContext, batch: CandidateBatch) -> NDArray[np.float64]:
        if batch.category == "perception":
            assert batch.view_indices is not None
            if "view_ig" not in ctx.cache:  # one sweep per step, shared with other terms; ig.sweep keeps
                # it (and where each ray stopped) for this field, so the manipulation branch reuses it
                ctx.cache["view_ig"] = np.asarray(ctx.ig.sweep(ctx.field), dtype=np.float64)
            ig = ctx.cache["view_ig"]
            scores = ig[batch.view_indices]
            if self.config.two_step and len(scores):
                mask = reachable_mask(ctx)
                out_of_reach = set() if mask is None else set(np.flatnonzero(~mask).tolist())
                v1, _ig1, _v2, ig2 = ctx.ig.best_two_step(ctx.field, set(ctx.visited) | out_of_reach, first=ig)
                scores[batch.view_indices == v1] += ig2
            return scores
        if not batch.actions:
            return np.zeros(0)
        return manipulation_ig(ctx, batch, self.config)

    def refine(self, ctx: DecisionContext, batch: CandidateBatch,
               indices: NDArray[np.int64]) -> NDArray[np.float64] | None:
        """Exact (full-density) values of screened manipulation candidates; None when all are exact."""
        if batch.category != "manipulation":
            return None
        state = _manipulation_state(ctx, batch, self.config)
        todo = [int(i) for i in indices if not state["exact"][i]]
        if not todo:
            return None
        full = best_view(ctx.ig.view_ig_delta(ctx.field, [state["deltas"][i] for i in todo]), state["mask"])
        state["values"][todo] = full
        state["exact"][todo] = True
        return state["values"][np.asarray(indices)].copy()

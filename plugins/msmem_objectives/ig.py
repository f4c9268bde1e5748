"""Objective term ``ig``: the information-gain part of OIG (paper eq. OIG).

Views: IG(v | belief), and at steps where manipulation is allowed, for the argmax view the greedy
second step max_v' IG(v' | after v) is added ([MEM]'s two-step view value; elsewhere the argmax view
wins either way). Manipulations: max_v IG(v | predicted belief), computed incrementally
(``IGService.view_ig_delta``): per view, only the rays crossing a candidate's changed voxels are
re-scored, which equals a full re-score of every predicted belief. By default every candidate is
first screened at a quarter of the rays (every 2nd ray in u and v, as [MEM] screens at a coarser
density): the 64 best views and the 8 best manipulation candidates are scored again at full density,
the manipulation candidates over their own 16 best screened views, and the second view is screened
the same way. The action chosen is always valued at full density. With a robot that cannot reach
every view (``ctx.workspace.robot``), the second view and the best view after a manipulation are
chosen among the views it reaches, as the view skill's candidates are.
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
    """Add the greedy second view's IG to the best view's value, at the steps where manipulation is
    allowed: only there does a view compete with another kind of action."""
    two_step_always: bool = False
    """Add it at every step. Where manipulation is not allowed the best view wins with or without it,
    so this changes only the values recorded, and costs a second IG sweep per step."""
    incremental: bool = True
    """Score manipulation candidates by re-scoring only the rays their changes touch (exact);
    False re-scores every predicted belief in full (the reference, many times slower)."""
    screen_ray_step: int = Field(2, ge=1, le=16)
    """Screen manipulation candidates with every n-th IG ray in both image axes (1: no screening).
    The ``finalists`` best by the screened value are re-scored at full density, so the values
    compared with the view branch are at the same density as views (docs/explanation/push.md, "Objective terms")."""
    finalists: int = Field(8, ge=1)
    """Candidates re-scored at full density after screening."""
    finalist_views: int = Field(16, ge=0)
    """A screened manipulation candidate is re-scored at full density over its own ``finalist_views``
    best views by the screening (the union over the finalists), not over every view (0: every view)."""
    screen_views: bool = True
    """Screen the view candidates too, and the second view of ``two_step``, as manipulation candidates
    are (with ``view_finalists``): the view that wins is always scored at full density."""
    view_finalists: int = Field(64, ge=1)
    """View candidates re-scored at full density after screening (a view costs far less than a
    manipulation candidate, and neighbouring views differ little)."""


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
    key = ("manipulation_ig", id(batch.prediction), cfg.incremental, cfg.screen_ray_step, cfg.finalists,
           cfg.finalist_views)
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
            screened = ctx.ig.view_ig_delta(ctx.field, deltas, ray_step=cfg.screen_ray_step)
            if mask is not None and mask.any():
                screened[:, ~mask] = -np.inf
            state["screened"] = screened
            coarse = screened.max(axis=1)
            top = np.argsort(-coarse, kind="stable")[: cfg.finalists]
            full = _full_density(ctx, state, top, cfg)
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


def _full_density(ctx: DecisionContext, state: dict[str, Any], idx: NDArray[np.int64] | list[int],
                  cfg: IGTermConfig) -> NDArray[np.float64]:
    """``max_v IG(v | predicted belief)`` at full density of the screened candidates ``idx``: over the
    views in the union of their ``finalist_views`` best screened views (every view: 0)."""
    deltas = [state["deltas"][i] for i in idx]
    screened = state["screened"][np.asarray(idx)]
    if cfg.finalist_views == 0 or cfg.finalist_views >= screened.shape[1]:
        return best_view(ctx.ig.view_ig_delta(ctx.field, deltas), state["mask"])
    best = np.argsort(-screened, axis=1, kind="stable")[:, : cfg.finalist_views]
    views = np.unique(best[np.isfinite(np.take_along_axis(screened, best, axis=1))])
    return ctx.ig.view_ig_delta(ctx.field, deltas, views=views).max(axis=1)


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
            return self._views(ctx, batch)["values"].copy()
        if not batch.actions:
            return np.zeros(0)
        return manipulation_ig(ctx, batch, self.config)

    def _views(self, ctx: DecisionContext, batch: CandidateBatch) -> dict[str, Any]:
        """Per-batch cache of the view candidates' values: IG, screened unless ``screen_views`` is off,
        plus the second view's IG on the best one (``two_step``)."""
        assert batch.view_indices is not None
        cfg = self.config
        key = ("view_ig", id(batch), cfg.screen_views, cfg.screen_ray_step, cfg.view_finalists, cfg.two_step,
               cfg.two_step_always)
        if key in ctx.cache:
            return ctx.cache[key]
        views = np.asarray(batch.view_indices, dtype=np.int64)
        step = cfg.screen_ray_step if cfg.screen_views else 1
        if step > 1:
            values, exact = ctx.ig.screened_view_ig(ctx.field, views, step, cfg.view_finalists)
            first = np.full(ctx.ig.num_views, -np.inf)
            first[views] = np.where(exact, values, -np.inf)  # the best view is an exactly scored one
        else:  # one sweep per field; ig.sweep keeps it (and where each ray stopped) for the manipulation branch
            first = np.asarray(ctx.ig.sweep(ctx.field), dtype=np.float64)
            values, exact = first[views], np.ones(len(views), dtype=bool)
        state: dict[str, Any] = {"values": values, "exact": exact}
        if cfg.two_step and len(views) and (ctx.manipulation_allowed or cfg.two_step_always):
            mask = reachable_mask(ctx)
            out_of_reach = set() if mask is None else set(np.flatnonzero(~mask).tolist())
            v1, _ig1, _v2, ig2 = ctx.ig.best_two_step(ctx.field, set(ctx.visited) | out_of_reach, first=first,
                                                      ray_step=step, finalists=cfg.view_finalists)
            values[views == v1] += ig2
        ctx.cache[key] = state
        return state

    def refine(self, ctx: DecisionContext, batch: CandidateBatch,
               indices: NDArray[np.int64]) -> NDArray[np.float64] | None:
        """Exact (full-density) values of screened candidates; None when all are exact."""
        if batch.category == "perception":
            views = self._views(ctx, batch)
            todo = [int(i) for i in indices if not views["exact"][i]]
            if not todo:
                return None
            assert batch.view_indices is not None
            views["values"][todo] = ctx.ig.views_ig(ctx.field, np.asarray(batch.view_indices)[todo])
            views["exact"][todo] = True
            return views["values"][np.asarray(indices)].copy()
        if batch.category != "manipulation":
            return None
        state = _manipulation_state(ctx, batch, self.config)
        todo = [int(i) for i in indices if not state["exact"][i]]
        if not todo:
            return None
        state["values"][todo] = _full_density(ctx, state, todo, self.config)
        state["exact"][todo] = True
        return state["values"][np.asarray(indices)].copy()

"""Held-out rollouts of observation models on recorded view sequences (``cnabu-map`` against its twins).

Every model integrates a scene's start view and recorded views in order, each on its own output,
from the empty map, exactly as in a view-only episode with those views. In a post-manipulation
sequence every model's belief goes through the same recorded push with the same effect model
(``rollouts.Effects``; ``cnabu-map``'s bounded like its output, ``rollouts.manipulate``) before the
view that follows it, and a belief is scored against the ground truth after its last view. The final beliefs are scored
against the ground truth on every voxel but the shelf's boards, pooled over scenes:

- the paper's ``occupancy_miou`` (mean of free and occupied IoU, occupied iff p > 0.5) and
  ``semantic_miou_2d`` (mean over all classes, background included, of the top-view class map IoU,
  classes absent from both maps skipped), suite-cumulative (intersections and unions summed over
  scenes) and per scene;
- NLL, Brier and top-label ECE (15 bins) of occupancy and semantics (``evaluation.Calibration``);
- the largest evidence total reached (bounded models stay below their bound).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_cnabu.learn.datagen import list_shards, load_shard
from msmem_cnabu.learn.evaluation import Calibration
from msmem_cnabu.learn.rollouts import Effects, manipulate, sequence
from msmem_core.map.belief import EvidentialMap
from msmem_core.run.metrics import class_iou_counts, miou_from_counts, occupancy_iou_counts, top_view_classes


class MapScore:
    """Pooled paper metrics and calibration of final beliefs."""

    def __init__(self, num_classes: int) -> None:
        self.c = num_classes
        self.occ = [np.zeros(2, np.int64), np.zeros(2, np.int64)]
        self.sem = [np.zeros(num_classes, np.int64), np.zeros(num_classes, np.int64)]
        self.per_scene: list[dict[str, float]] = []
        self.cal = Calibration()
        self.top = 0.0

    def add(self, belief: EvidentialMap, gt_occ: NDArray[np.bool_], gt_cls: NDArray[np.integer],
            valid: NDArray[np.bool_]) -> None:
        p = belief.expected_occupancy()
        q = belief.class_probs()
        pred_occ = (p > 0.5) & valid
        gt = gt_occ & valid
        oi, ou = occupancy_iou_counts(pred_occ, gt, valid)
        cls = np.where(pred_occ, np.argmax(q[1:], 0) + 1, 0)
        gcls = np.where(gt, gt_cls, 0)
        cols = valid.any(2)
        si, su = class_iou_counts(top_view_classes(cls), top_view_classes(gcls), self.c, cols)
        for acc, new in ((self.occ, (oi, ou)), (self.sem, (si, su))):
            acc[0] += new[0]
            acc[1] += new[1]
        self.per_scene.append({"occupancy_miou": miou_from_counts(oi, ou),
                               "semantic_miou_2d": miou_from_counts(si, su)})
        i = np.flatnonzero(valid.reshape(-1))
        self.cal.add(p.reshape(-1)[i], gt_occ.reshape(-1)[i], q.reshape(self.c, -1)[:, i],
                     gt_cls.reshape(-1)[i].astype(np.int64))
        self.top = max(self.top, float((belief.alpha + belief.beta).max()), float(belief.eta.sum(0).max()))

    def result(self) -> dict[str, Any]:
        scenes = {k: [s[k] for s in self.per_scene] for k in ("occupancy_miou", "semantic_miou_2d")}
        return {
            "occupancy_miou": miou_from_counts(*self.occ), "semantic_miou_2d": miou_from_counts(*self.sem),
            "occupancy_miou_scene_mean": float(np.mean(scenes["occupancy_miou"])),
            "semantic_miou_2d_scene_mean": float(np.nanmean(scenes["semantic_miou_2d"])),
            "per_scene": scenes, **self.cal.result(), "max_evidence_total": self.top,
        }


def twins() -> dict[str, Any]:
    """The analytic twins, fed with ray masks: ``analytic-observation`` and ``column-fill``."""
    from msmem_analytic.columnfill import ColumnFillObservationModel
    from msmem_analytic.observation import AnalyticObservationModel

    analytic = AnalyticObservationModel()
    return {"analytic-observation": analytic.apply_masks, "column-fill": ColumnFillObservationModel().update_masks}


def evaluate_rollouts(net: Any, data_dir: str | Path, models: dict[str, Callable[..., EvidentialMap]] | None = None,
                      max_scenes: int | None = None, log: Callable[[str], None] = print,
                      steps: Sequence[int] | None = None, effects: Effects | None = None,
                      unseen_class_weight: float = 1.0, class_map: dict[str, str] | None = None) -> dict[str, Any]:
    """Roll out ``cnabu-map`` (``net``: a ``MapNet``, or None to score only ``models``) and the twins on
    every held-out sequence; the scores of the final beliefs (and of the beliefs after ``steps`` views).
    ``effects``: the effect models of post-manipulation sequences (default ``Effects()``, built when a
    sequence needs it); ``unseen_class_weight``: ``cnabu-map``'s (``MapNet.step``); ``class_map``: for
    shards of other classes (``rollouts.sequence``)."""
    import torch

    paths = list_shards(data_dir, "observe")[:max_scenes]
    fns: dict[str, Callable[..., EvidentialMap]] = dict(models or twins())
    after: dict[str, Callable[[Effects, EvidentialMap, Any, Any], EvidentialMap]] = {m: Effects.apply for m in fns}
    if net is not None:
        def learned(b: EvidentialMap, f: Any, o: Any, s: Any) -> EvidentialMap:
            t = torch.from_numpy
            with torch.no_grad():
                a, bb, e = net.step(t(b.alpha)[None], t(b.beta)[None], t(b.eta)[None], t(f)[None], t(o)[None],
                                    t(s)[None], valid_t, unseen_class_weight)
            return EvidentialMap(b.grid, a[0].numpy(), bb[0].numpy(), e[0].numpy())

        def learned_after(effects: Effects, b: EvidentialMap, action: Any, workspace: Any) -> EvidentialMap:
            a, bb, e = (torch.from_numpy(x.copy())[None] for x in (b.alpha, b.beta, b.eta))
            manipulate(net, a, bb, e, 0, action, workspace, effects)
            return EvidentialMap(b.grid, a[0].numpy(), bb[0].numpy(), e[0].numpy())

        fns = {"cnabu-map": learned, **fns}
        after["cnabu-map"] = learned_after
    scores: dict[str, dict[int, MapScore]] = {m: {} for m in fns}
    views = manipulated = 0
    for path in paths:
        shard = load_shard(path)
        seq = sequence(shard, class_map)
        valid_t = torch.from_numpy(seq.valid)
        n = len(seq)
        marks = sorted({n, *(k for k in (steps or ()) if 0 < k <= n)})
        if seq.manipulations:
            effects = effects or Effects()
            manipulated += 1
        fx = effects
        for m, fn in fns.items():
            b = EvidentialMap.empty(shard.grid, seq.seen.shape[1])
            for t in range(n):
                if t in seq.manipulations and fx is not None:
                    b = after[m](fx, b, seq.manipulations[t], seq.workspace)
                b = fn(b, seq.free[t], seq.occ[t], seq.seen[t])
                if t + 1 in marks:
                    scores[m].setdefault(t + 1, MapScore(b.num_classes)).add(b, seq.step_gt_occ[t], seq.step_gt_cls[t],
                                                                              seq.valid)
        views += n
    out: dict[str, Any] = {
        "scenes": len(paths), "views": views, "post_manipulation_scenes": manipulated,
        "effect_models": effects.record() if effects is not None else None,
        "final": {m: s[max(s)].result() for m, s in scores.items()},
        "by_views": {m: {k: {kk: v for kk, v in sc.result().items() if kk != "per_scene"} for k, sc in s.items()}
                     for m, s in scores.items()}}
    for m, r in out["final"].items():
        log(f"{m:26s} occ mIoU {r['occupancy_miou']:.3f} sem mIoU 2-D {r['semantic_miou_2d']:.3f} "
            f"occ NLL {r['occ_nll']:.4f} sem NLL {r['sem_nll']:.4f} occ ECE {r['occ_ece']:.3f} "
            f"sem ECE {r['sem_ece']:.3f} max evidence {r['max_evidence_total']:.0f}")
    return out

"""Mapping and disturbance metrics on voxel grids and object poses (plain numpy).

Conventions: occupancy arrays are bool ``[X, Y, Z]``; class arrays are integer ``[X, Y, Z]`` with
0 = free / background and 1..C-1 = object classes; z is the grid's third axis (up). An IoU whose
union is empty is 1.0 (nothing to find and nothing claimed); a mean over an empty class set is NaN.

Beside these stricter metrics, the paper's own ([MEM]'s ``Cumulative_mIoU`` and calibration error:
:func:`paper_counts`) are computed from additive counts, so a suite can sum them over scenes before
dividing; there a class whose union is empty is skipped.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from msmem_core.world.scene import BACKGROUND


def _iou(pred: NDArray[np.bool_], gt: NDArray[np.bool_]) -> float:
    union = int(np.count_nonzero(pred | gt))
    return 1.0 if union == 0 else int(np.count_nonzero(pred & gt)) / union


def occupancy_iou(
    pred_occ: NDArray[np.bool_], gt_occ: NDArray[np.bool_], mask: NDArray[np.bool_] | None = None
) -> float:
    """|pred & gt| / |pred | gt| over all voxels, or only over voxels where ``mask`` is True."""
    pred, gt = np.asarray(pred_occ, dtype=bool), np.asarray(gt_occ, dtype=bool)
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} differs from ground truth {gt.shape}")
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        pred, gt = pred[m], gt[m]
    return _iou(pred, gt)


def observable_iou(pred_occ: NDArray[np.bool_], gt_occ: NDArray[np.bool_], observable: NDArray[np.bool_]) -> float:
    """Occupancy IoU restricted to the observable voxels (``visibility.observable_mask``).

    The mask drops only self-occluded object interiors, which no method can observe, so the
    score is comparable across methods on the same scene.
    """
    return occupancy_iou(pred_occ, gt_occ, observable)


def _class_miou(pred: NDArray[np.integer], gt: NDArray[np.integer], classes: Iterable[int] | None) -> float:
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} differs from ground truth {gt.shape}")
    if classes is None:
        classes = np.unique(gt)
    ious = [_iou(pred == c, gt == c) for c in classes if c != BACKGROUND]
    return float(np.mean(ious)) if ious else float("nan")


def semantic_miou(
    pred_cls: NDArray[np.integer], gt_cls: NDArray[np.integer], classes: Iterable[int] | None = None
) -> float:
    """Mean over object classes of the 3-D per-class IoU ``|pred == c & gt == c| / |pred == c | gt == c|``.

    ``classes`` defaults to the object classes present in ground truth (class 0 is never scored),
    so a class predicted but absent from the scene lowers no score except through the classes it
    steals voxels from.
    """
    return _class_miou(np.asarray(pred_cls), np.asarray(gt_cls), classes)


def top_view_classes(cls: NDArray[np.integer]) -> NDArray[np.integer]:
    """Bird's-eye class map ``[X, Y]``: per column the class of the highest voxel with class != 0, else 0."""
    c = np.asarray(cls)
    nonzero = c != BACKGROUND
    top = c.shape[2] - 1 - np.argmax(nonzero[:, :, ::-1], axis=2)  # highest z with a class
    out = np.take_along_axis(c, top[:, :, None], axis=2)[:, :, 0]
    return np.where(nonzero.any(axis=2), out, BACKGROUND)


def semantic_miou_bev(pred_cls: NDArray[np.integer], gt_cls: NDArray[np.integer]) -> float:
    """mIoU of the bird's-eye class maps (``top_view_classes``), as MEM's 2-D semantic map.

    Averaged over the object classes present in ground truth's map (class 0 excluded).
    """
    return _class_miou(top_view_classes(pred_cls), top_view_classes(gt_cls), None)


def position_change_m(initial_poses: Mapping[int, ArrayLike], final_poses: Mapping[int, ArrayLike]) -> float:
    """Summed XY displacement (metres) between initial and final pose of every object still present.

    Sums over the objects in ``final_poses`` (MEM's Position Change): removed objects (successful
    grasps) are absent from the final poses and excluded; an object of a failed grasp is still
    present and counts. Objects without an initial pose are an error.
    """
    total = 0.0
    for oid, final in final_poses.items():
        if oid not in initial_poses:
            raise KeyError(f"object {oid} has a final pose but no initial pose")
        d = np.asarray(final, dtype=np.float64)[:2, 3] - np.asarray(initial_poses[oid], dtype=np.float64)[:2, 3]
        total += float(np.hypot(d[0], d[1]))
    return total


def prediction_from_belief(
    expected_occupancy: NDArray[np.floating], class_probs: NDArray[np.floating], occ_threshold: float = 0.5
) -> tuple[NDArray[np.bool_], NDArray[np.int16]]:
    """Hard maps from a belief: occupied where expected occupancy > threshold; class there = argmax.

    ``class_probs`` is ``[C, X, Y, Z]`` (index 0 = background); the class of an occupied voxel is
    the most probable *object* class 1..C-1 (a voxel believed occupied is an object), else 0.
    """
    p = np.asarray(expected_occupancy)
    probs = np.asarray(class_probs)
    if probs.shape[1:] != p.shape or probs.shape[0] < 2:
        raise ValueError(f"class_probs shape {probs.shape} does not match occupancy {p.shape} as [C>=2, X, Y, Z]")
    occ = p > occ_threshold
    cls = (np.argmax(probs[1:], axis=0) + 1).astype(np.int16)
    return occ, np.where(occ, cls, np.int16(BACKGROUND)).astype(np.int16)


# ------------------------------------------------------------------- the paper's metrics ([MEM])
ECE_BINS = 15
"""Equal-width confidence bins of the expected calibration error over [0, 1]."""
PAPER_METRIC_KEYS = ("occupancy_miou", "semantic_miou_2d", "occupancy_ece", "semantic_ece")
"""The paper's own metrics (MEM's ``Cumulative_mIoU`` and calibration error), beside the stricter ones."""
PAPER_COUNT_KEYS = (
    "occupancy_intersection", "occupancy_union", "semantic_2d_intersection", "semantic_2d_union",
    "occupancy_ece_count", "occupancy_ece_confidence_sum", "occupancy_ece_correct_sum",
    "semantic_ece_count", "semantic_ece_confidence_sum", "semantic_ece_correct_sum",
)
"""The additive counts behind :data:`PAPER_METRIC_KEYS` (see :func:`paper_counts`)."""
PAPER_METRIC_COUNTS = {
    "occupancy_miou": ("occupancy_intersection", "occupancy_union"),
    "semantic_miou_2d": ("semantic_2d_intersection", "semantic_2d_union"),
    "occupancy_ece": ("occupancy_ece_count", "occupancy_ece_confidence_sum", "occupancy_ece_correct_sum"),
    "semantic_ece": ("semantic_ece_count", "semantic_ece_confidence_sum", "semantic_ece_correct_sum"),
}
"""The counts each of :data:`PAPER_METRIC_KEYS` is computed from (an mIoU: intersection, union; an ECE:
count, confidence sum, correct sum)."""


def class_iou_counts(
    pred: NDArray[np.integer], gt: NDArray[np.integer], num_classes: int, mask: NDArray[np.bool_] | None = None
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per class c in 0..num_classes-1: ``|pred == c & gt == c|`` and ``|pred == c | gt == c|``.

    Over all cells, or the cells where ``mask`` is True. Both are additive over cells and scenes
    (MEM's ``Cumulative_mIoU.update_counts``). Labels outside 0..num_classes-1 are an error.
    """
    p, g = np.asarray(pred), np.asarray(gt)
    if p.shape != g.shape:
        raise ValueError(f"prediction shape {p.shape} differs from ground truth {g.shape}")
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != p.shape:
            raise ValueError(f"mask shape {m.shape} differs from prediction shape {p.shape}")
        p, g = p[m], g[m]
    p, g = p.ravel().astype(np.int64), g.ravel().astype(np.int64)
    for name, a in (("prediction", p), ("ground truth", g)):
        if a.size and (int(a.min()) < 0 or int(a.max()) >= num_classes):
            raise ValueError(f"{name} holds labels outside 0..{num_classes - 1}")
    inter = np.bincount(p[p == g], minlength=num_classes).astype(np.int64)
    union = np.bincount(p, minlength=num_classes) + np.bincount(g, minlength=num_classes) - inter
    return inter, union.astype(np.int64)


def occupancy_iou_counts(
    pred_occ: NDArray[np.bool_], gt_occ: NDArray[np.bool_], mask: NDArray[np.bool_] | None = None
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Intersection and union of the two occupancy classes, index 0 = free and 1 = occupied (any nonzero
    value counts as occupied, as in :func:`occupancy_iou`)."""
    return class_iou_counts(np.asarray(pred_occ, dtype=bool), np.asarray(gt_occ, dtype=bool), 2, mask)


def miou_from_counts(inter: ArrayLike, union: ArrayLike) -> float:
    """Mean of ``inter / union`` over the classes with ``union > 0``; NaN if there is none.

    A class absent from both prediction and ground truth is skipped (MEM's mean would be NaN).
    """
    i, u = np.asarray(inter, dtype=np.float64), np.asarray(union, dtype=np.float64)
    if i.shape != u.shape:
        raise ValueError(f"intersection shape {i.shape} differs from union shape {u.shape}")
    seen = u > 0
    return float(np.mean(i[seen] / u[seen])) if seen.any() else float("nan")


def ece_bins(
    confidence: ArrayLike, correct: ArrayLike, n_bins: int = ECE_BINS
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
    """Reliability-diagram counts: per bin the number of samples, their summed confidence and how
    many are correct. Bin b holds confidences in ``[b / n_bins, (b + 1) / n_bins)``, the last bin
    also 1.0 (``b = min(floor(conf * n_bins), n_bins - 1)``). Additive over samples and scenes."""
    c = np.asarray(confidence, dtype=np.float64).ravel()
    ok = np.asarray(correct, dtype=bool).ravel()
    if c.shape != ok.shape:
        raise ValueError(f"{c.size} confidences but {ok.size} correctness flags")
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    if c.size and (not np.all(np.isfinite(c)) or c.min() < 0.0 or c.max() > 1.0):
        raise ValueError("confidences must lie in [0, 1]")
    b = np.minimum((c * n_bins).astype(np.int64), n_bins - 1)
    count = np.bincount(b, minlength=n_bins).astype(np.int64)
    conf_sum = np.bincount(b, weights=c, minlength=n_bins).astype(np.float64)
    return count, conf_sum, np.bincount(b[ok], minlength=n_bins).astype(np.int64)


def ece_from_bins(count: ArrayLike, confidence_sum: ArrayLike, correct_sum: ArrayLike) -> float:
    """Expected calibration error ``sum_b (n_b / N) |acc_b - conf_b|`` = ``sum_b |correct_b - conf_sum_b| / N``
    over the non-empty bins (acc_b = correct_b / n_b, conf_b = conf_sum_b / n_b); NaN if N = 0."""
    n = np.asarray(count, dtype=np.float64)
    total = float(n.sum())
    if total == 0:
        return float("nan")
    gap = np.abs(np.asarray(correct_sum, dtype=np.float64) - np.asarray(confidence_sum, dtype=np.float64))
    return float(gap.sum() / total)


def belief_nll(
    expected_occupancy: NDArray[np.floating], class_probs: NDArray[np.floating], gt_occ: NDArray[np.bool_],
    gt_cls: NDArray[np.integer], interior: NDArray[np.bool_], floor: float = 1e-6,
) -> dict[str, float]:
    """Mean negative log-likelihood of the ground truth under a belief's expected probabilities, over
    the ``interior`` voxels: ``occupancy_nll`` = mean of ``-log p`` (occupied) or ``-log(1 - p)``
    (free); ``semantic_nll`` = mean of ``-log class_probs[gt_cls]`` (class 0 on free voxels).
    Probabilities are clipped to ``[floor, 1 - floor]``, so a confidently wrong voxel costs at most
    ``-log floor`` (13.8) instead of infinity."""
    inside = np.asarray(interior, dtype=bool)
    if not inside.any():
        return {"occupancy_nll": float("nan"), "semantic_nll": float("nan")}
    p = np.clip(np.asarray(expected_occupancy, dtype=np.float64)[inside], floor, 1.0 - floor)
    y = np.asarray(gt_occ, dtype=bool)[inside]
    probs = np.asarray(class_probs)
    lab = np.asarray(gt_cls).astype(np.intp)[inside]
    q = np.take_along_axis(probs[:, inside], lab[None], 0)[0].astype(np.float64)
    return {"occupancy_nll": float(-np.mean(np.where(y, np.log(p), np.log1p(-p)))),
            "semantic_nll": float(-np.mean(np.log(np.clip(q, floor, 1.0))))}


def top_label(
    probs: NDArray[np.floating], labels: NDArray[np.integer]
) -> tuple[NDArray[np.floating], NDArray[np.bool_]]:
    """Top-label confidence ``max_c probs[c]`` and whether ``argmax_c probs[c] == labels`` (the lowest
    index wins a tie, as ``np.argmax``), for ``probs`` ``[C, ...]`` and integer ``labels`` ``[...]``.

    The same as ``probs.max(0), probs.argmax(0) == labels`` but several times faster on a grid:
    a full argmax runs only over the voxels where the labelled class reaches the maximum.
    """
    pr = np.asarray(probs)
    lab = np.asarray(labels).astype(np.intp).ravel()
    if pr.shape[1:] != np.shape(labels):
        raise ValueError(f"probs shape {pr.shape} does not match labels {np.shape(labels)} as [C, ...]")
    if lab.size and (int(lab.min()) < 0 or int(lab.max()) >= pr.shape[0]):
        raise ValueError(f"labels outside 0..{pr.shape[0] - 1}")
    flat = pr.reshape(pr.shape[0], -1)
    best = flat.max(axis=0)
    correct = np.take_along_axis(flat, lab[None], axis=0)[0] == best
    tied = np.flatnonzero(correct & (lab > 0))  # a lower class may tie with the labelled one
    if tied.size:
        correct[tied] = np.argmax(flat[:, tied], axis=0) == lab[tied]
    return best.reshape(pr.shape[1:]), correct.reshape(pr.shape[1:])


def paper_counts(
    expected_occupancy: NDArray[np.floating],
    class_probs: NDArray[np.floating],
    pred_cls: NDArray[np.integer],
    gt_occ: NDArray[np.bool_],
    gt_cls: NDArray[np.integer],
    interior: NDArray[np.bool_],
    *,
    n_bins: int = ECE_BINS,
) -> dict[str, list[int] | list[float]]:
    """The counts behind the paper's metrics of one belief against ground truth (keys: :data:`PAPER_COUNT_KEYS`).

    ``expected_occupancy`` p ``[X, Y, Z]`` and ``class_probs`` ``[C, X, Y, Z]`` of the belief,
    ``pred_cls`` its hard class grid (``prediction_from_belief``), the ground truth, and the
    ``interior`` voxels scored (``map.ig.shelf_interior_mask``). Over interior voxels:

    - occupancy IoU counts of the prediction ``p > 0.5`` (argmax of [1 - p, p], a tie is free)
      against ``gt_occ``, classes (free, occupied);
    - 2-D semantic IoU counts of the top-view class maps (``top_view_classes``) of ``pred_cls`` and
      ``gt_cls`` with every voxel outside the interior set to background, over the interior's
      columns (those with at least one interior voxel), classes 0..C-1 (background included);
    - occupancy ECE bins: confidence ``max(p, 1 - p)``, correct iff ``(p > 0.5) == gt_occ``;
    - semantic ECE bins: confidence ``max_c class_probs``, correct iff the argmax class (the lowest
      index on a tie, so background wins it) equals ``gt_cls`` (0 on free voxels).

    Every value is a list; summing the lists of several scenes gives the suite's counts
    (:func:`paper_metrics_from_counts`).
    """
    p = np.asarray(expected_occupancy)
    probs = np.asarray(class_probs)
    inside = np.asarray(interior, dtype=bool)
    c = probs.shape[0]
    if probs.shape[1:] != p.shape or inside.shape != p.shape:
        raise ValueError(f"class_probs {probs.shape}, occupancy {p.shape} and interior {inside.shape} do not match")
    gt = np.asarray(gt_occ, dtype=bool)[inside]
    pi = p[inside].astype(np.float64)
    occ = pi > 0.5
    o_inter, o_union = occupancy_iou_counts(occ, gt)
    keep = inside.any(axis=2)  # the interior's columns
    top_pred = top_view_classes(np.where(inside, pred_cls, BACKGROUND))[keep]
    top_gt = top_view_classes(np.where(inside, gt_cls, BACKGROUND))[keep]
    s_inter, s_union = class_iou_counts(top_pred, top_gt, c)
    o_bins = ece_bins(np.maximum(pi, 1.0 - pi), occ == gt, n_bins)
    conf, correct = top_label(probs, gt_cls)
    s_bins = ece_bins(np.clip(conf[inside], 0.0, 1.0), correct[inside], n_bins)
    values = (o_inter, o_union, s_inter, s_union, *o_bins, *s_bins)
    return {k: v.tolist() for k, v in zip(PAPER_COUNT_KEYS, values, strict=True)}


def sum_paper_counts(counts: Iterable[Mapping[str, ArrayLike]]) -> dict[str, list[float]]:
    """Element-wise sum of several scenes' :func:`paper_counts` (a suite's counts)."""
    total: dict[str, NDArray[np.float64]] = {}
    for c in counts:
        for k in PAPER_COUNT_KEYS:
            v = np.asarray(c[k], dtype=np.float64)
            if k in total and total[k].shape != v.shape:
                raise ValueError(f"{k}: {v.shape} counts do not add to {total[k].shape}")
            total[k] = total[k] + v if k in total else v
    return {k: v.tolist() for k, v in total.items()}


def paper_metrics_from_counts(counts: Mapping[str, ArrayLike]) -> dict[str, float]:
    """``occupancy_miou``, ``semantic_miou_2d``, ``occupancy_ece`` and ``semantic_ece`` from
    :func:`paper_counts` of one scene (per-scene values) or their sum over scenes (suite-cumulative)."""
    return {key: (ece_from_bins if key.endswith("_ece") else miou_from_counts)(*(counts[c] for c in names))
            for key, names in PAPER_METRIC_COUNTS.items()}


OBJECT_COUNT_KEYS = ("correctly_found", "misclassified", "not_found", "hallucinated")
"""The paper's Table II columns, in its order (see :func:`object_counts`)."""


def object_counts(
    pred_occ: NDArray[np.bool_],
    pred_cls: NDArray[np.integer],
    gt_instances: NDArray[np.integer],
    gt_instance_classes: Mapping[int, int],
    *,
    found_fraction: float = 0.2,
    min_hallucination_voxels: int = 8,
    exclude: NDArray[np.bool_] | None = None,
) -> dict[str, int]:
    """The paper's Table II object counts: correctly found, misclassified, not found, hallucinated.

    Inputs: predicted occupancy (bool) and class (0 = background) per voxel, the ground-truth
    instance grid of ``voxelize.voxelize_instances`` (object id per voxel, -1 = free; a voxel two
    objects share belongs to one of them) over the objects still in the shelf, and the true class of
    each of those objects (``gt_instance_classes``: object id -> class id; every id in the grid must
    be a key). ``exclude`` (e.g. the shelf walls) marks voxels ignored on both sides.

    Matching rule:

    - An object is **found** when at least ``found_fraction`` (20%) of its ground-truth voxels are
      predicted occupied. A found object is **correctly found** when its true class is the most
      frequent predicted class over its predicted-occupied ground-truth voxels (a tie with another
      class is not a majority and counts against the object), else **misclassified**. Every other
      object is **not found**, including one without any ground-truth voxel left (outside the
      grid or wholly in ``exclude``). So the first three counts sum to ``len(gt_instance_classes)``.
    - **Hallucinated** counts predicted blobs: per predicted object class, the connected components
      (26-connectivity) of predicted-occupied voxels of that class with at least
      ``min_hallucination_voxels`` (8) voxels that touch no ground-truth object voxel even after
      dilating the ground-truth occupancy by one voxel (3x3x3 cube). A blob next to or on an object,
      whatever its class, is not a hallucination; smaller specks are ignored as noise.
    """
    from scipy import ndimage

    occ = np.asarray(pred_occ, dtype=bool)
    cls = np.asarray(pred_cls)
    inst = np.asarray(gt_instances)
    if occ.ndim != 3:
        raise ValueError(f"pred_occ must be a 3-D [X, Y, Z] grid, got shape {occ.shape}")
    for name, a in (("pred_cls", cls), ("gt_instances", inst)):
        if a.shape != occ.shape:
            raise ValueError(f"{name} shape {a.shape} differs from pred_occ shape {occ.shape}")
        if not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{name} must hold integers, got dtype {a.dtype}")
    if not 0.0 < found_fraction <= 1.0:
        raise ValueError(f"found_fraction must be in (0, 1], got {found_fraction}")
    if min_hallucination_voxels < 1:
        raise ValueError(f"min_hallucination_voxels must be >= 1, got {min_hallucination_voxels}")
    if inst.size and int(inst.min()) < -1:
        raise ValueError(f"gt_instances holds {int(inst.min())}; expected object ids >= 0 and -1 for free voxels")
    if exclude is not None:
        ex = np.asarray(exclude, dtype=bool)
        if ex.shape != occ.shape:
            raise ValueError(f"exclude shape {ex.shape} differs from pred_occ shape {occ.shape}")
        occ = occ & ~ex
        inst = np.where(ex, -1, inst)
    is_obj = inst >= 0
    obj_ids = inst[is_obj]
    ids, sizes = np.unique(obj_ids, return_counts=True)
    voxels_of = dict(zip(ids.tolist(), sizes.tolist(), strict=True))
    unknown = sorted(set(voxels_of) - {int(k) for k in gt_instance_classes})
    if unknown:
        raise ValueError(f"gt_instances holds object ids {unknown} missing from gt_instance_classes")

    counts = dict.fromkeys(OBJECT_COUNT_KEYS, 0)
    hit = occ[is_obj]
    hit_ids, hit_cls = obj_ids[hit], cls[is_obj][hit]
    for oid, true_cls in gt_instance_classes.items():
        n = voxels_of.get(int(oid), 0)
        votes_for = hit_cls[hit_ids == oid]
        if n == 0 or len(votes_for) < found_fraction * n:
            counts["not_found"] += 1
            continue
        voted, votes = np.unique(votes_for, return_counts=True)
        winners = voted[votes == votes.max()]
        correct = len(winners) == 1 and int(winners[0]) == int(true_cls)
        counts["correctly_found" if correct else "misclassified"] += 1

    cube = np.ones((3, 3, 3), dtype=bool)  # 26-connectivity; dilation by one voxel in every direction
    near_gt = ndimage.binary_dilation(is_obj, structure=cube)
    for c in np.unique(cls[occ & ~near_gt]):  # a class with no voxel away from the objects has no hallucination
        if c == BACKGROUND:
            continue
        mask = occ & (cls == c)
        box = ndimage.find_objects(mask.view(np.uint8))[0]  # label only the class's bounding box
        labels, n = ndimage.label(mask[box], structure=cube)
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        touching = np.bincount(labels[near_gt[box]], minlength=n + 1) > 0
        counts["hallucinated"] += int(np.count_nonzero((sizes[1:] >= min_hallucination_voxels) & ~touching[1:]))
    return counts

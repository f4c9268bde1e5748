"""Mapping and disturbance metrics on voxel grids and object poses (plain numpy).

Conventions: occupancy arrays are bool ``[X, Y, Z]``; class arrays are integer ``[X, Y, Z]`` with
0 = free / background and 1..C-1 = object classes; z is the grid's third axis (up). An IoU whose
union is empty is 1.0 (nothing to find and nothing claimed); a mean over an empty class set is NaN.
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

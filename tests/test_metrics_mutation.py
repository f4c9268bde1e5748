"""The metrics on inputs their signatures allow but the main tests do not use: masks and occupancy given
as integers, class-probability arrays at the edge of their shape check, and the messages that name
what is wrong (gaps found by ``tests/mutation_scan.py`` on ``msmem_core/run/metrics.py``;
docs/explanation/reliability.md)."""

from __future__ import annotations

import numpy as np
import pytest

from msmem_core.run.metrics import (
    class_iou_counts,
    occupancy_iou,
    occupancy_iou_counts,
    prediction_from_belief,
    semantic_miou,
)

RNG = np.random.default_rng(5)
PRED = RNG.random((6, 5, 4)) < 0.4
GT = RNG.random((6, 5, 4)) < 0.4
MASK = RNG.random((6, 5, 4)) < 0.5


def test_masks_and_occupancy_given_as_integers_count_as_booleans():
    """A 0/1 or 0/255 array is a mask of the nonzero cells, never a list of indices."""
    want = occupancy_iou(PRED, GT, MASK)
    assert want == pytest.approx(np.sum(PRED & GT & MASK) / np.sum((PRED | GT) & MASK))
    for as_int in (lambda a: a.astype(np.int64), lambda a: a.astype(np.uint8) * 255):
        assert occupancy_iou(as_int(PRED), as_int(GT), as_int(MASK)) == want
    inter, union = occupancy_iou_counts(PRED, GT, MASK)
    for mask in (MASK.astype(np.int64), MASK.astype(np.uint8)):
        i, u = class_iou_counts(PRED.astype(np.int64), GT.astype(np.int64), 2, mask)
        np.testing.assert_array_equal(i, inter)
        np.testing.assert_array_equal(u, union)
    assert union[1] == np.sum((PRED | GT) & MASK)


def test_occupancy_counts_take_any_nonzero_value_as_occupied():
    inter, union = occupancy_iou_counts(PRED.astype(np.uint8) * 7, GT.astype(np.float32) * 0.5)
    assert inter.tolist() == [np.sum(~PRED & ~GT), np.sum(PRED & GT)]
    assert union.tolist() == [np.sum(~PRED | ~GT), np.sum(PRED | GT)]


def test_errors_name_what_is_wrong():
    labels = np.zeros((3, 4), np.int64)
    with pytest.raises(ValueError, match=r"^prediction shape \(3, 4\) differs from ground truth \(4, 3\)$"):
        semantic_miou(labels, labels.T)
    with pytest.raises(ValueError, match=r"^prediction shape \(3, 4\) differs from ground truth \(4, 3\)$"):
        class_iou_counts(labels, labels.T, 2)
    with pytest.raises(ValueError, match=r"^mask shape \(4, 3\) differs from prediction shape \(3, 4\)$"):
        class_iou_counts(labels, labels, 2, np.ones((4, 3), bool))
    bad = labels.copy()
    bad[0, 0] = 2
    with pytest.raises(ValueError, match=r"^prediction holds labels outside 0\.\.1$"):
        class_iou_counts(bad, labels, 2)
    with pytest.raises(ValueError, match=r"^ground truth holds labels outside 0\.\.1$"):
        class_iou_counts(labels, bad, 2)


def test_prediction_from_belief_needs_background_and_one_class_at_least():
    p = np.full((2, 3, 4), 0.9)
    occ, cls = prediction_from_belief(p, np.stack([np.full(p.shape, 0.2), np.full(p.shape, 0.8)]))
    assert occ.all()
    assert (cls == 1).all()
    assert cls.dtype == np.int16
    with pytest.raises(ValueError, match=r"as \[C>=2, X, Y, Z\]"):
        prediction_from_belief(p, np.ones((1, *p.shape)))  # background only
    with pytest.raises(ValueError, match=r"as \[C>=2, X, Y, Z\]"):
        prediction_from_belief(p, np.ones((3, 2, 3, 5)))


def test_semantic_miou_scores_the_classes_it_is_given():
    gt = np.array([1, 1, 2, 2, 0, 0])
    pred = np.array([1, 1, 2, 0, 3, 0])
    assert semantic_miou(pred, gt) == pytest.approx((1.0 + 0.5) / 2)  # classes of the ground truth
    assert semantic_miou(pred, gt, classes=[1, 2, 3]) == pytest.approx((1.0 + 0.5 + 0.0) / 3)
    assert semantic_miou(pred, gt, classes=[2]) == pytest.approx(0.5)


def test_top_label_checks_labels_against_the_class_axis():
    from msmem_core.run.metrics import top_label

    probs = np.full((2, 5), 0.5)  # 2 classes, 5 voxels: more voxels than classes
    conf, ok = top_label(probs, np.array([0, 1, 0, 1, 0]))
    np.testing.assert_array_equal(ok, [True, False, True, False, True])  # ties go to class 0
    np.testing.assert_array_equal(conf, np.full(5, 0.5))
    with pytest.raises(ValueError, match=r"^labels outside 0\.\.1$"):
        top_label(probs, np.array([0, 3, 0, 1, 0]))


def test_paper_counts_refuse_an_interior_of_another_shape():
    from msmem_core.run.metrics import paper_counts

    p = np.full((2, 3, 4), 0.5)
    probs = np.full((3, 2, 3, 4), 1 / 3)
    cls = np.zeros(p.shape, np.int64)
    with pytest.raises(ValueError, match=r"interior \(2, 3, 5\) do not match"):
        paper_counts(p, probs, cls, p > 0.5, cls, np.ones((2, 3, 5), bool))


def test_object_counts_take_their_parameters_inclusively():
    """found_fraction in (0, 1], min_hallucination_voxels >= 1: both ends that are allowed work."""
    from msmem_core.run.metrics import object_counts

    inst = np.full((4, 4, 4), -1)
    inst[:2, :2, :2] = 0
    occ = inst >= 0
    cls = np.where(occ, 3, 0)
    counts = object_counts(occ, cls, inst, {0: 3}, found_fraction=1.0, min_hallucination_voxels=1)
    assert counts["correctly_found"] == 1
    assert counts["hallucinated"] == 0
    for bad in ({"found_fraction": 1.5}, {"found_fraction": 0.0}, {"min_hallucination_voxels": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            object_counts(occ, cls, inst, {0: 3}, **bad)


def test_paper_counts_count_the_top_view_per_class_inside_the_interior():
    from msmem_core.run.metrics import paper_counts

    shape = (5, 2, 3)  # more columns along x than classes, so the class axis cannot be mistaken for x
    inside = np.ones(shape, bool)
    gt_cls = np.zeros(shape, np.int64)
    gt_cls[1, 0, 0] = 2  # one object of class 2, in one column
    p = np.where(gt_cls > 0, 0.9, 0.1)
    probs = np.stack([np.where(gt_cls == c, 0.8, 0.1) for c in range(3)])
    counts = paper_counts(p, probs, gt_cls, gt_cls > 0, gt_cls, inside)
    assert counts["semantic_2d_intersection"] == [9, 0, 1]  # per class 0..C-1 over the 10 columns
    assert counts["semantic_2d_union"] == [9, 0, 1]
    assert counts["occupancy_intersection"] == [29, 1]



def test_object_counts_size_objects_without_their_excluded_voxels_and_skip_background_blobs():
    from msmem_core.run.metrics import object_counts

    inst = np.full((8, 8, 8), -1)
    inst[:2, :2, :2] = 0  # an object of 8 voxels
    occ = np.zeros(inst.shape, bool)
    occ[0, 0, :2] = True  # 2 of its voxels predicted
    ex = np.zeros(inst.shape, bool)
    ex[:2, :2, :2] = True
    ex[0, 0, :2] = False  # all but those 2 excluded: the object is its 2 visible voxels
    cls = np.where(occ, 3, 0)
    assert object_counts(occ, cls, inst, {0: 3}, found_fraction=0.5)["not_found"] == 1
    assert object_counts(occ, cls, inst, {0: 3}, found_fraction=0.5, exclude=ex)["correctly_found"] == 1
    # a predicted blob of class 5 far from the object is a hallucination, also beside occupied voxels
    # predicted as background
    occ2, cls2 = occ.copy(), cls.copy()
    occ2[5:7, 5:7, 5:7] = True
    cls2[5:7, 5:7, 5:7] = 5
    occ2[7, 0, 7] = True  # class 0 (background) where occupancy is predicted
    assert object_counts(occ2, cls2, inst, {0: 3})["hallucinated"] == 1

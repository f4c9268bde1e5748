"""Metrics: IoUs, the bird's-eye semantic map, Position Change, belief thresholding, and the paper's
own metrics (MEM's Cumulative_mIoU and calibration error) from additive counts."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmem_core.map.ig import shelf_interior_mask, shelf_wall_mask
from msmem_core.run.metrics import (
    PAPER_COUNT_KEYS,
    class_iou_counts,
    ece_bins,
    ece_from_bins,
    miou_from_counts,
    observable_iou,
    occupancy_iou,
    occupancy_iou_counts,
    paper_counts,
    paper_metrics_from_counts,
    position_change_m,
    prediction_from_belief,
    semantic_miou,
    semantic_miou_bev,
    sum_paper_counts,
    top_label,
    top_view_classes,
)
from msmem_core.world.geometry import pose_matrix
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec


def _grid(*voxels: tuple[int, int, int], shape: tuple[int, int, int] = (4, 4, 4)) -> np.ndarray:
    g = np.zeros(shape, dtype=bool)
    for v in voxels:
        g[v] = True
    return g


def test_iou_of_identical_maps_is_one_and_of_disjoint_maps_is_zero() -> None:
    a = _grid((0, 0, 0), (1, 2, 3))
    assert occupancy_iou(a, a) == 1.0
    assert occupancy_iou(a, _grid((3, 3, 3))) == 0.0


def test_iou_hand_computed_and_empty_union() -> None:
    pred = _grid((0, 0, 0), (1, 0, 0), (2, 0, 0))
    gt = _grid((1, 0, 0), (2, 0, 0), (3, 0, 0), (3, 1, 0))
    assert occupancy_iou(pred, gt) == pytest.approx(2 / 5)
    empty = np.zeros((4, 4, 4), dtype=bool)
    assert occupancy_iou(empty, empty) == 1.0


def test_observable_iou_ignores_voxels_outside_the_mask() -> None:
    gt = _grid((1, 1, 1), (1, 1, 2))  # (1, 1, 2) is a self-occluded interior
    pred = _grid((1, 1, 1))
    mask = ~_grid((1, 1, 2))
    assert occupancy_iou(pred, gt) == pytest.approx(0.5)
    assert observable_iou(pred, gt, mask) == 1.0


def test_semantic_miou_averages_over_classes_present_in_ground_truth() -> None:
    gt = np.zeros((4, 1, 1), dtype=np.int16)
    gt[:2, 0, 0] = 3
    gt[2:, 0, 0] = 5
    pred = gt.copy()
    pred[1, 0, 0] = 5  # class 3: IoU 1/2; class 5: IoU 2/3
    assert semantic_miou(pred, gt) == pytest.approx((1 / 2 + 2 / 3) / 2)
    assert semantic_miou(gt, gt) == 1.0
    assert semantic_miou(np.full_like(gt, 7), gt) == 0.0  # class 7 is absent from GT: not averaged
    assert math.isnan(semantic_miou(gt, np.zeros_like(gt)))


def test_bev_takes_the_class_of_the_top_occupied_voxel() -> None:
    cls = np.zeros((2, 1, 5), dtype=np.int16)
    cls[0, 0, 0] = 2  # low object
    cls[0, 0, 3] = 4  # on top of it (a gap between them)
    cls[1, 0, 1] = 6
    assert top_view_classes(cls).tolist() == [[4], [6]]
    assert top_view_classes(np.zeros((1, 1, 3), dtype=np.int16)).tolist() == [[0]]


def test_bev_miou_sees_only_the_top_layer() -> None:
    gt = np.zeros((2, 1, 3), dtype=np.int16)
    gt[0, 0, 2], gt[1, 0, 0] = 1, 2
    pred = gt.copy()
    pred[0, 0, 0] = 9  # hidden under the correct top voxel: invisible in BEV
    assert semantic_miou_bev(pred, gt) == 1.0
    pred[1, 0, 2] = 1  # now column 1 shows class 1 on top: class 1 IoU 1/2, class 2 IoU 0
    assert semantic_miou_bev(pred, gt) == pytest.approx(0.25)


def test_position_change_counts_moved_objects_and_excludes_removed_ones() -> None:
    initial = {1: pose_matrix((0.0, 0.0, 0.0)), 2: pose_matrix((0.1, 0.1, 0.0)), 3: pose_matrix((0.2, 0.0, 0.0))}
    final = {
        1: pose_matrix((0.03, 0.04, 0.5)),  # pushed 5 cm in XY (z ignored)
        3: pose_matrix((0.2, 0.0, 0.0), (0.0, 0.0, 0.38268343, 0.92387953)),  # failed grasp, only rotated
    }  # object 2 was grasped and removed
    assert position_change_m(initial, final) == pytest.approx(0.05)
    assert position_change_m(initial, dict(initial)) == 0.0
    with pytest.raises(KeyError):
        position_change_m({}, {7: np.eye(4)})


def test_prediction_from_belief_thresholds_and_takes_the_best_object_class() -> None:
    occ = np.array([0.2, 0.6, 0.9]).reshape(3, 1, 1)
    probs = np.zeros((4, 3, 1, 1))
    probs[:, 0, 0, 0] = [0.1, 0.7, 0.1, 0.1]
    probs[:, 1, 0, 0] = [0.9, 0.02, 0.08, 0.0]  # background most likely, but the voxel is occupied
    probs[:, 2, 0, 0] = [0.1, 0.1, 0.2, 0.6]
    pred_occ, pred_cls = prediction_from_belief(occ, probs)
    assert pred_occ.ravel().tolist() == [False, True, True]
    assert pred_cls.ravel().tolist() == [0, 2, 3]
    assert pred_cls.dtype == np.int16
    with pytest.raises(ValueError, match="class_probs"):
        prediction_from_belief(occ, probs[:, :2])


# ----------------------------------------------------------------------- the paper's own metrics
def test_occupancy_miou_averages_free_and_occupied_and_a_tie_is_free() -> None:
    p = np.array([0.2, 0.5, 0.7, 0.9])
    gt = np.array([False, True, True, False])
    inter, union = occupancy_iou_counts(p > 0.5, gt)  # predicted occupied: 0.7 and 0.9; 0.5 is free
    assert inter.tolist() == [1, 1]  # free: voxel 0; occupied: voxel 2
    assert union.tolist() == [3, 3]  # free: voxels 0, 1, 3; occupied: voxels 1, 2, 3
    assert miou_from_counts(inter, union) == pytest.approx(1 / 3)
    mask = np.array([True, True, True, False])
    assert occupancy_iou_counts(p > 0.5, gt, mask)[1].tolist() == [2, 2]


def test_semantic_miou_2d_includes_background_and_skips_absent_classes() -> None:
    pred = np.array([[0, 1], [1, 2]])
    gt = np.array([[0, 1], [2, 2]])
    inter, union = class_iou_counts(pred, gt, 5)
    assert inter.tolist() == [1, 1, 1, 0, 0]
    assert union.tolist() == [1, 2, 2, 0, 0]
    # background IoU 1, class 1 1/2, class 2 1/2; classes 3 and 4 are in neither map
    assert miou_from_counts(inter, union) == pytest.approx((1 + 0.5 + 0.5) / 3)
    with pytest.raises(ValueError, match=r"outside 0\.\.4"):
        class_iou_counts(pred, np.full_like(gt, 5), 5)


def test_miou_of_empty_unions_is_nan_and_a_class_without_union_is_skipped() -> None:
    assert math.isnan(miou_from_counts([0, 0], [0, 0]))
    assert math.isnan(miou_from_counts([], []))
    assert miou_from_counts([0, 3], [0, 4]) == 0.75
    inter, union = class_iou_counts(np.zeros((0,), int), np.zeros((0,), int), 3)
    assert inter.tolist() == union.tolist() == [0, 0, 0]


def test_suite_accumulation_sums_counts_before_dividing() -> None:
    """Two scenes: a perfect one with one occupied voxel, and one whose ten occupied voxels are all missed."""
    gt_a = np.zeros(100, bool)
    gt_a[0] = True
    gt_b = np.zeros(100, bool)
    gt_b[:10] = True
    a = occupancy_iou_counts(gt_a, gt_a)
    b = occupancy_iou_counts(np.zeros(100, bool), gt_b)
    per_scene = [miou_from_counts(*a), miou_from_counts(*b)]
    assert per_scene == [1.0, pytest.approx((90 / 100 + 0) / 2)]
    suite = miou_from_counts(a[0] + b[0], a[1] + b[1])
    assert suite == pytest.approx((189 / 199 + 1 / 11) / 2)  # free 99 + 90 of 99 + 100; occupied 1 of 1 + 10
    assert abs(suite - np.mean(per_scene)) > 0.2


def test_ece_on_a_hand_example() -> None:
    conf = [0.1, 0.35, 0.41, 0.95, 1.0]
    correct = [False, True, False, True, True]
    count, conf_sum, correct_sum = ece_bins(conf, correct)
    assert len(count) == 15
    assert np.flatnonzero(count).tolist() == [1, 5, 6, 14]  # 1.0 falls in the last bin
    assert count[14] == 2
    assert conf_sum[14] == pytest.approx(1.95)
    assert correct_sum[14] == 2
    # (1/5)|0 - 0.1| + (1/5)|1 - 0.35| + (1/5)|0 - 0.41| + (2/5)|1 - 0.975|
    assert ece_from_bins(count, conf_sum, correct_sum) == pytest.approx(0.02 + 0.13 + 0.082 + 0.01)
    assert math.isnan(ece_from_bins(*ece_bins([], [])))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        ece_bins([1.2], [True])


def _ece_reference(conf: np.ndarray, correct: np.ndarray, n_bins: int = 15) -> float:
    """A naive loop over samples and bins, the way MEM's Calibration_calc_3D bins ([lo, hi), last bin closed)."""
    tiers = np.arange(n_bins + 1) / n_bins
    total = len(conf)
    ece = 0.0
    for i in range(n_bins):
        members = [k for k in range(total) if tiers[i] <= conf[k] < tiers[i + 1] or (i == n_bins - 1 and conf[k] == 1)]
        if members:
            acc = sum(bool(correct[k]) for k in members) / len(members)
            mean_conf = sum(float(conf[k]) for k in members) / len(members)
            ece += len(members) / total * abs(acc - mean_conf)
    return ece


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ece_matches_a_naive_reference_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    conf = rng.uniform(0, 1, 300)
    correct = rng.uniform(0, 1, 300) < conf**2  # overconfident
    assert ece_from_bins(*ece_bins(conf, correct)) == pytest.approx(_ece_reference(conf, correct), abs=1e-12)


labels = st.lists(st.integers(0, 3), min_size=1, max_size=40)


@settings(max_examples=60, deadline=None)
@given(labels, labels, st.integers(0, 2**31 - 1))
def test_miou_is_in_0_1_and_counts_add_over_cells(pred: list[int], gt: list[int], seed: int) -> None:
    n = min(len(pred), len(gt))
    p, g = np.array(pred[:n]), np.array(gt[:n])
    inter, union = class_iou_counts(p, g, 4)
    assert 0.0 <= miou_from_counts(inter, union) <= 1.0
    assert np.all(inter <= union)
    cut = np.random.default_rng(seed).integers(0, n + 1)
    a, b = class_iou_counts(p[:cut], g[:cut], 4), class_iou_counts(p[cut:], g[cut:], 4)
    assert (a[0] + b[0]).tolist() == inter.tolist()
    assert (a[1] + b[1]).tolist() == union.tolist()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 1), st.booleans()), min_size=1, max_size=60), st.integers(0, 60))
def test_ece_is_in_0_1_and_bins_add_over_samples(samples: list[tuple[float, bool]], cut: int) -> None:
    conf = np.array([c for c, _ in samples])
    correct = np.array([k for _, k in samples])
    bins = ece_bins(conf, correct)
    assert 0.0 <= ece_from_bins(*bins) <= 1.0
    assert int(bins[0].sum()) == len(samples)
    a, b = ece_bins(conf[:cut], correct[:cut]), ece_bins(conf[cut:], correct[cut:])
    for whole, x, y in zip(bins, a, b, strict=True):
        assert np.allclose(whole, x + y)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_top_label_equals_max_and_argmax_with_ties(seed: int) -> None:
    rng = np.random.default_rng(seed)
    probs = rng.integers(0, 3, size=(4, 5, 3)).astype(np.float32)  # many ties
    lab = rng.integers(0, 4, size=(5, 3))
    conf, correct = top_label(probs, lab)
    assert np.array_equal(conf, probs.max(axis=0))
    assert np.array_equal(correct, probs.argmax(axis=0) == lab)


def _tiny_world() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 3 x 1 x 2 grid whose column x = 2 lies outside the interior; the prior belief (p = 0.5,
    uniform classes) everywhere but on x = 2, where an occupied class-1 voxel is believed and true."""
    interior = np.zeros((3, 1, 2), bool)
    interior[:2] = True
    p = np.full((3, 1, 2), 0.5)
    p[2] = 0.9
    probs = np.full((3, 3, 1, 2), 1 / 3)
    gt_occ = np.zeros((3, 1, 2), bool)
    gt_occ[0, 0, 0] = gt_occ[2, 0, 1] = True
    gt_cls = np.zeros((3, 1, 2), np.int16)
    gt_cls[0, 0, 0], gt_cls[2, 0, 1] = 2, 1
    return p, probs, gt_occ, gt_cls, interior


def test_paper_counts_score_the_interior_ties_free_and_background_as_a_class() -> None:
    p, probs, gt_occ, gt_cls, interior = _tiny_world()
    _, pred_cls = prediction_from_belief(p, probs)
    assert pred_cls[2].ravel().tolist() == [1, 1]  # outside the interior: ignored below
    counts = paper_counts(p, probs, pred_cls, gt_occ, gt_cls, interior)
    assert set(counts) == set(PAPER_COUNT_KEYS)
    assert counts["occupancy_intersection"] == [3, 0]
    assert counts["occupancy_union"] == [4, 1]
    assert counts["semantic_2d_intersection"] == [1, 0, 0]
    assert counts["semantic_2d_union"] == [2, 0, 1]
    m = paper_metrics_from_counts(counts)
    assert m["occupancy_miou"] == pytest.approx((3 / 4 + 0) / 2)
    assert m["semantic_miou_2d"] == pytest.approx((1 / 2 + 0) / 2)  # top views [0, 0] vs [2, 0]; class 1 absent
    assert m["occupancy_ece"] == pytest.approx(abs(3 - 4 * 0.5) / 4)  # confidence 0.5, 3 of 4 right
    assert m["semantic_ece"] == pytest.approx(abs(3 - 4 / 3) / 4)  # a tie is background: right on the 3 free


def test_paper_counts_of_scenes_sum_to_the_suite() -> None:
    p, probs, gt_occ, gt_cls, interior = _tiny_world()
    _, pred_cls = prediction_from_belief(p, probs)
    one = paper_counts(p, probs, pred_cls, gt_occ, gt_cls, interior)
    perfect = paper_counts(gt_occ.astype(float), probs, gt_cls, gt_occ, gt_cls, interior)
    total = sum_paper_counts([one, perfect])
    assert total["occupancy_union"] == [7, 2]
    assert total["occupancy_ece_count"] == [a + b for a, b in zip(one["occupancy_ece_count"],
                                                                  perfect["occupancy_ece_count"], strict=True)]
    assert paper_metrics_from_counts(total)["occupancy_miou"] == pytest.approx((6 / 7 + 1 / 2) / 2)


def test_shelf_interior_is_the_closed_interior_box_between_the_walls_and_the_open_front() -> None:
    shelf = ShelfSpec()
    grid = GridSpec.around_box(shelf.interior_lower, shelf.interior_upper, 0.01, 2)
    interior, walls = shelf_interior_mask(grid, shelf), shelf_wall_mask(grid, shelf)
    assert not (interior & walls).any()
    front = grid.centers()[..., 1] < shelf.interior_lower[1]
    assert np.array_equal(interior | walls | front, np.ones(grid.shape, bool))
    extent = np.ptp(np.argwhere(interior), axis=0) + 1
    assert extent.tolist() == np.round((shelf.interior_upper - shelf.interior_lower) / 0.01).astype(int).tolist()


def test_belief_nll_against_scipy_and_by_hand():
    from scipy import stats

    from msmem_core.run.metrics import belief_nll

    rng = np.random.default_rng(5)
    shape = (4, 3, 2)
    p = rng.random(shape)
    probs = rng.dirichlet(np.ones(3), size=shape).transpose(3, 0, 1, 2)
    gt_occ = rng.random(shape) > 0.5
    gt_cls = np.where(gt_occ, rng.integers(1, 3, size=shape), 0)
    inside = np.ones(shape, bool)
    inside[0] = False
    r = belief_nll(p, probs, gt_occ, gt_cls, inside)
    want_o = -np.mean(stats.bernoulli.logpmf(gt_occ[inside].astype(int), p[inside]))
    q = np.array([probs[c, i, j, k] for (i, j, k), c in np.ndenumerate(gt_cls) if inside[i, j, k]])
    assert r["occupancy_nll"] == pytest.approx(want_o, rel=1e-9)
    assert r["semantic_nll"] == pytest.approx(-np.mean(np.log(q)), rel=1e-9)
    # a certain, wrong voxel costs -log(floor), not infinity
    one = belief_nll(np.ones((1, 1, 1)), np.array([[[[1.0]]], [[[0.0]]]]), np.zeros((1, 1, 1), bool),
                     np.ones((1, 1, 1), int), np.ones((1, 1, 1), bool))
    assert one["occupancy_nll"] == pytest.approx(-np.log(1e-6))
    assert one["semantic_nll"] == pytest.approx(-np.log(1e-6))


# ------------------------------------------------------------ input checks and branches (mutation testing)
def test_ece_bins_refuses_bad_input_naming_it_and_takes_one_bin() -> None:
    with pytest.raises(ValueError, match="3 confidences but 2 correctness flags"):
        ece_bins([0.1, 0.5, 0.9], [True, False])
    with pytest.raises(ValueError, match="n_bins must be >= 1, got 0"):
        ece_bins([0.5], [True], n_bins=0)
    for bad in ([float("nan")], [-0.01], [1.01]):
        with pytest.raises(ValueError, match=r"confidences must lie in \[0, 1\]"):
            ece_bins(bad, [True])
    count, conf, correct = ece_bins([0.2, 0.9, 1.0], [True, False, True], n_bins=1)  # one bin holds all
    assert (count.tolist(), correct.tolist()) == ([3], [2])
    assert conf.tolist() == pytest.approx([2.1])
    assert count.dtype == np.int64
    assert correct.dtype == np.int64


def test_occupancy_iou_over_a_mask_and_shape_mismatch() -> None:
    pred = np.array([True, True, False, False])
    gt = np.array([True, False, True, False])
    assert occupancy_iou(pred, gt) == pytest.approx(1 / 3)
    assert occupancy_iou(pred, gt, mask=np.array([True, True, False, True])) == pytest.approx(1 / 2)
    with pytest.raises(ValueError, match=r"prediction shape \(4,\) differs from ground truth \(3,\)"):
        occupancy_iou(pred, gt[:3])


def test_position_change_needs_an_initial_pose_for_every_final_one() -> None:
    with pytest.raises(KeyError, match="object 7 has a final pose but no initial pose"):
        position_change_m({1: np.eye(4)}, {7: np.eye(4)})


def test_belief_nll_is_nan_without_interior_and_scores_each_side() -> None:
    from msmem_core.run.metrics import belief_nll

    p = np.array([0.9, 0.2])
    probs = np.array([[0.1, 0.7], [0.9, 0.3]])  # [C, N]: class 1 on voxel 0, class 0 on voxel 1
    gt_occ, gt_cls = np.array([True, False]), np.array([1, 0])
    out = belief_nll(p, probs, gt_occ, gt_cls, np.array([False, False]))
    assert math.isnan(out["occupancy_nll"])
    assert math.isnan(out["semantic_nll"])
    out = belief_nll(p, probs, gt_occ, gt_cls, np.array([True, True]))
    assert out["occupancy_nll"] == pytest.approx(-(math.log(0.9) + math.log(0.8)) / 2)
    assert out["semantic_nll"] == pytest.approx(-(math.log(0.9) + math.log(0.7)) / 2)
    sure = belief_nll(np.array([1.0]), np.array([[0.0], [1.0]]), np.array([False]), np.array([0]), np.array([True]))
    assert sure["occupancy_nll"] == pytest.approx(-math.log(1e-6))  # clipped, not infinite
    assert sure["semantic_nll"] == pytest.approx(-math.log(1e-6))


def test_top_label_refuses_mismatched_shapes_and_labels_out_of_range() -> None:
    probs = np.array([[0.2, 0.5], [0.8, 0.5]])
    with pytest.raises(ValueError, match=r"probs shape \(2, 2\) does not match labels \(3,\) as \[C, \.\.\.\]"):
        top_label(probs, np.array([0, 1, 1]))
    for bad in ([0, 2], [-1, 0]):
        with pytest.raises(ValueError, match=r"labels outside 0\.\.1"):
            top_label(probs, np.array(bad))
    conf, correct = top_label(probs, np.array([1, 0]))  # a tie goes to the lower class
    assert conf.tolist() == [0.8, 0.5]
    assert correct.tolist() == [True, True]


def test_the_occupancy_ece_counts_a_voxel_correct_when_its_side_of_one_half_is_the_truths() -> None:
    grid = (3, 1, 1)
    p = np.array([0.9, 0.3, 0.8]).reshape(grid)  # believed occupied, free, occupied
    probs = np.stack([1 - p, p])  # two classes
    gt_occ = np.array([True, True, True]).reshape(grid)  # the second is wrong
    counts = paper_counts(p, probs, (p > 0.5).astype(int), gt_occ, gt_occ.astype(int), np.ones(grid, bool), n_bins=1)
    assert counts["occupancy_ece_correct_sum"] == [2]
    assert counts["occupancy_ece_count"] == [3]

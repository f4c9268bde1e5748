"""Metrics: IoUs, the bird's-eye semantic map, Position Change and belief thresholding."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msmem_core.run.metrics import (
    observable_iou,
    occupancy_iou,
    position_change_m,
    prediction_from_belief,
    semantic_miou,
    semantic_miou_bev,
    top_view_classes,
)
from msmem_core.world.geometry import pose_matrix


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

"""Table II object counts: correctly found, misclassified, not found, hallucinated (and removed)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmem_core.config import load_config
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import shelf_wall_mask
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.metrics import OBJECT_COUNT_KEYS, object_counts
from msmem_core.run.runner import MetricTracker, build_episode, run_episode
from msmem_core.testing import FakeSimulator
from msmem_core.world.scene import ObjectSpec, SceneSpec
from msmem_core.world.voxelize import voxelize, voxelize_instances

SHAPE = (24, 12, 10)
BOXES = {  # object id -> (slice box, class): three 3x3x3 objects on the floor, far apart
    0: ((slice(2, 5), slice(2, 5), slice(0, 3)), 1),
    1: ((slice(9, 12), slice(2, 5), slice(0, 3)), 2),
    2: ((slice(16, 19), slice(2, 5), slice(0, 3)), 3),
}
FAR = (slice(20, 22), slice(8, 10), slice(6, 8))  # a 2x2x2 = 8 voxel box, 3+ voxels from every object


def gt() -> tuple[np.ndarray, dict[int, int]]:
    inst = np.full(SHAPE, -1, dtype=np.int32)
    for oid, (box, _) in BOXES.items():
        inst[box] = oid
    return inst, {oid: c for oid, (_, c) in BOXES.items()}


def empty_pred() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(SHAPE, dtype=bool), np.zeros(SHAPE, dtype=np.int16)


def paint(occ: np.ndarray, cls: np.ndarray, where: tuple[slice, ...] | np.ndarray, c: int) -> None:
    occ[where] = True
    cls[where] = c


def counts(occ: np.ndarray, cls: np.ndarray, **kw: object) -> dict[str, int]:
    inst, classes = gt()
    return object_counts(occ, cls, inst, classes, **kw)


def test_right_class_wrong_class_and_nothing():
    occ, cls = empty_pred()
    paint(occ, cls, BOXES[0][0], 1)  # object 0 fully predicted, right class
    paint(occ, cls, BOXES[1][0], 5)  # object 1 fully predicted, wrong class
    assert counts(occ, cls) == {"correctly_found": 1, "misclassified": 1, "not_found": 1, "hallucinated": 0}


def test_found_needs_20_percent_of_the_voxels():
    occ, cls = empty_pred()
    flat = np.flatnonzero(gt()[0] == 0)  # 27 voxels: 6 are 22%, 5 are 18.5%
    paint(occ.reshape(-1), cls.reshape(-1), flat[:5], 1)
    assert counts(occ, cls)["correctly_found"] == 0
    paint(occ.reshape(-1), cls.reshape(-1), flat[:6], 1)
    assert counts(occ, cls)["correctly_found"] == 1
    assert counts(occ, cls, found_fraction=0.5)["correctly_found"] == 0


def test_class_is_the_majority_over_the_predicted_voxels_and_a_tie_is_not_a_majority():
    occ, cls = empty_pred()
    flat = np.flatnonzero(gt()[0] == 0)
    paint(occ.reshape(-1), cls.reshape(-1), flat[:10], 1)
    paint(occ.reshape(-1), cls.reshape(-1), flat[10:18], 4)  # 10 right vs 8 wrong; 9 voxels unpredicted
    assert counts(occ, cls)["correctly_found"] == 1
    paint(occ.reshape(-1), cls.reshape(-1), flat[18:20], 4)  # 10 vs 10
    assert counts(occ, cls)["misclassified"] == 1


def test_a_blob_far_from_every_object_is_a_hallucination():
    occ, cls = empty_pred()
    paint(occ, cls, FAR, 2)
    assert counts(occ, cls) == {"correctly_found": 0, "misclassified": 0, "not_found": 3, "hallucinated": 1}


def test_blobs_below_the_minimum_size_are_not_counted():
    occ, cls = empty_pred()
    five = np.zeros(SHAPE, dtype=bool)
    five[20:22, 8:10, 6] = True
    five[20, 8, 7] = True
    paint(occ, cls, five, 2)
    assert counts(occ, cls)["hallucinated"] == 0
    assert counts(occ, cls, min_hallucination_voxels=5)["hallucinated"] == 1


def test_blobs_are_split_by_predicted_class():
    occ, cls = empty_pred()
    paint(occ, cls, (slice(20, 22), slice(8, 10), slice(6, 8)), 2)
    paint(occ, cls, (slice(20, 22), slice(8, 10), slice(8, 10)), 3)  # touching, another class: 2 blobs
    assert counts(occ, cls)["hallucinated"] == 2
    occ, cls = empty_pred()
    paint(occ, cls, (slice(20, 22), slice(8, 10), slice(6, 7)), 2)  # 4 + 4 voxels: each below 8
    paint(occ, cls, (slice(20, 22), slice(8, 10), slice(7, 8)), 3)
    assert counts(occ, cls)["hallucinated"] == 0


def test_components_use_26_connectivity():
    occ, cls = empty_pred()
    for i in range(8):  # a diagonal chain of 8 single voxels: one component under 26-connectivity
        paint(occ, cls, (12 + i % 2, 7 + i % 2, i), 4)
    assert counts(occ, cls)["hallucinated"] == 1


@pytest.mark.parametrize("gap", [0, 1])
def test_a_blob_touching_an_object_is_not_a_hallucination(gap):
    occ, cls = empty_pred()
    x0 = 5 + gap  # object 0 ends at x = 4: gap 0 is face-adjacent, gap 1 is one free voxel away
    paint(occ, cls, (slice(x0, x0 + 2), slice(3, 5), slice(0, 2)), 6)
    assert counts(occ, cls)["hallucinated"] == (0 if gap == 0 else 1)


def test_diagonal_contact_counts_as_touching():
    occ, cls = empty_pred()
    paint(occ, cls, (slice(5, 7), slice(5, 7), slice(3, 5)), 6)  # meets object 0 only at its corner (4, 4, 2)
    assert counts(occ, cls)["hallucinated"] == 0


def test_a_blob_overlapping_an_object_with_another_class_is_not_a_hallucination():
    occ, cls = empty_pred()
    paint(occ, cls, (slice(3, 7), slice(3, 5), slice(1, 3)), 6)  # half in object 0, class 6
    assert counts(occ, cls) == {"correctly_found": 0, "misclassified": 1, "not_found": 2, "hallucinated": 0}


def test_excluded_voxels_are_ignored_on_both_sides():
    occ, cls = empty_pred()
    paint(occ, cls, FAR, 2)
    paint(occ, cls, BOXES[0][0], 1)
    exclude = np.zeros(SHAPE, dtype=bool)
    exclude[FAR] = True
    exclude[BOXES[0][0]] = True  # object 0 has no voxel left: not found
    assert counts(occ, cls, exclude=exclude) == {"correctly_found": 0, "misclassified": 0, "not_found": 3,
                                                 "hallucinated": 0}


def test_bad_inputs_raise_clear_errors():
    occ, cls = empty_pred()
    inst, classes = gt()
    with pytest.raises(ValueError, match="pred_cls shape"):
        object_counts(occ, cls[:-1], inst, classes)
    with pytest.raises(ValueError, match="gt_instances shape"):
        object_counts(occ, cls, inst[:, :-1], classes)
    with pytest.raises(ValueError, match="3-D"):
        object_counts(occ[0], cls[0], inst[0], classes)
    with pytest.raises(ValueError, match="integers"):
        object_counts(occ, cls, inst.astype(float), classes)
    with pytest.raises(ValueError, match=r"ids \[2\] missing"):
        object_counts(occ, cls, inst, {0: 1, 1: 2})
    with pytest.raises(ValueError, match="exclude shape"):
        object_counts(occ, cls, inst, classes, exclude=np.zeros((2, 2, 2), dtype=bool))
    with pytest.raises(ValueError, match="found_fraction"):
        object_counts(occ, cls, inst, classes, found_fraction=0.0)
    with pytest.raises(ValueError, match="min_hallucination_voxels"):
        object_counts(occ, cls, inst, classes, min_hallucination_voxels=0)
    with pytest.raises(ValueError, match="-1 for free"):
        object_counts(occ, cls, np.where(inst < 0, -2, inst), classes)


boxes = st.tuples(st.integers(0, 9), st.integers(0, 9), st.integers(0, 9), st.integers(1, 4), st.integers(1, 4),
                  st.integers(1, 4), st.integers(1, 5))


@settings(max_examples=60, deadline=None)
@given(st.lists(boxes, min_size=0, max_size=6), st.integers(0, 2**32 - 1), st.floats(0.0, 0.6))
def test_counts_partition_the_present_objects(objects, seed, density):
    inst = np.full((12, 12, 12), -1, dtype=np.int32)
    classes = {}
    for oid, (x, y, z, dx, dy, dz, c) in enumerate(objects):
        inst[x:x + dx, y:y + dy, z:z + dz] = oid  # may cover an earlier object, even wholly
        classes[oid] = c
    rng = np.random.default_rng(seed)
    occ = rng.random(inst.shape) < density
    cls = np.where(occ, rng.integers(1, 6, inst.shape), 0)
    out = object_counts(occ, cls, inst, classes)
    assert set(out) == set(OBJECT_COUNT_KEYS)
    assert min(out.values()) >= 0
    assert out["correctly_found"] + out["misclassified"] + out["not_found"] == len(classes)
    exact = object_counts(inst >= 0, np.where(inst >= 0, np.array([0, *classes.values()])[inst + 1], 0), inst,
                          classes)
    present = len(np.unique(inst[inst >= 0]))
    assert exact == {"correctly_found": present, "misclassified": 0, "not_found": len(classes) - present,
                     "hallucinated": 0}


def test_a_generated_scene_predicted_as_its_ground_truth_is_all_correctly_found():
    scene = suite_scenes("hard25")[3]  # generated by msmem_core.world.scenegen, stored (generating takes seconds)
    cfg = load_config("view-only", None, {})
    grid = cfg.grid_spec(scene.shelf)
    assert grid.shape == (78, 40, 30)
    inst = voxelize_instances(scene.objects, grid)
    occ, cls = voxelize(scene.objects, grid)
    assert np.array_equal(occ, inst >= 0)
    walls = shelf_wall_mask(grid, scene.shelf)
    classes = {o.id: o.class_id for o in scene.objects}
    t0 = time.perf_counter()
    out = object_counts(occ, cls, inst, classes, exclude=walls)
    seconds = time.perf_counter() - t0
    assert out == {"correctly_found": len(scene.objects), "misclassified": 0, "not_found": 0, "hallucinated": 0}
    assert seconds < 1.0  # ~10 ms; generous for a loaded machine
    shifted = object_counts(np.roll(occ, 12, axis=0), np.roll(cls, 12, axis=0), inst, classes, exclude=walls)
    assert sum(shifted[k] for k in ("correctly_found", "misclassified", "not_found")) == len(scene.objects)


SMALL = {"camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}


def three_objects() -> SceneSpec:
    return SceneSpec(name="three", objects=(
        ObjectSpec(id=0, class_name="cracker_box", position_m=(-0.15, 0.08, 0.0)),
        ObjectSpec(id=1, class_name="tomato_soup_can", position_m=(-0.15, 0.25, 0.0)),
        ObjectSpec(id=2, class_name="sugar_box", position_m=(0.2, 0.2, 0.0)),
    ))


def belief_of(tracker: MetricTracker) -> EvidentialMap:
    """A confident belief equal to the tracker's current ground truth."""
    b = EvidentialMap.empty(tracker.grid)
    b.alpha[tracker.gt_occ] = 100.0
    b.beta[~tracker.gt_occ] = 100.0
    x, y, z = np.nonzero(tracker.gt_occ)
    b.eta[tracker.gt_cls[x, y, z], x, y, z] = 100.0
    return b


def test_the_tracker_counts_present_objects_and_reports_removed_ones():
    cfg = load_config("view-only", None, SMALL)
    ep = build_episode(cfg, get_plugin_manager(), scene=three_objects())
    ep.sim = FakeSimulator(cfg.camera)
    ep.sim.reset(ep.scene)
    tracker = MetricTracker(ep)
    occ, cls = voxelize(ep.scene.objects, tracker.grid)
    assert np.array_equal(tracker.gt_occ, occ & ~tracker.walls)
    assert np.array_equal(tracker.gt_cls, np.where(tracker.walls, 0, cls))
    m = tracker(belief_of(tracker))
    assert [m[k] for k in (*OBJECT_COUNT_KEYS, "removed")] == [3, 0, 0, 0, 0]
    assert tracker(EvidentialMap.empty(tracker.grid))["not_found"] == 3

    stale = belief_of(tracker)
    ep.sim.remove_object(1)  # grasped out
    ep.sim.poses[2] = ep.sim.poses[2].copy()
    ep.sim.poses[2][1, 3] = -1.0  # pushed out of the shelf: none of its voxels is left in the grid
    m = tracker(stale)
    assert m["removed"] == 2
    assert (m["correctly_found"], m["misclassified"], m["not_found"]) == (1, 0, 0)
    assert m["hallucinated"] == 2, "the belief still shows the two objects that are gone"
    assert m["position_change_m"] == 0.0, "objects no longer in the shelf count as removed, not as moved"
    ep.sim.poses[0] = ep.sim.poses[0].copy()
    ep.sim.poses[0][0, 3] += 0.03  # a push within the shelf
    assert tracker(stale)["position_change_m"] == pytest.approx(0.03)


def test_episode_final_metrics_hold_the_counts():
    cfg = load_config("view-only", None, {**SMALL, "steps": 1})
    ep = build_episode(cfg, get_plugin_manager(), scene=three_objects())
    ep.sim = FakeSimulator(cfg.camera)
    final = run_episode(ep, None)
    for key in (*OBJECT_COUNT_KEYS, "removed"):
        assert isinstance(final[key], int)
        assert isinstance(final["initial"][key], int)
    assert final["correctly_found"] + final["misclassified"] + final["not_found"] == 3
    assert final["removed"] == 0

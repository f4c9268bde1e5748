"""The push skill (UPS sampling, execution), its analytic effect model and the manipulation terms."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from msmem_objectives.entropy import SemanticEntropyTerm
from msmem_objectives.ig import IGTerm, IGTermConfig
from msmem_push.effect import AnalyticPushEffect
from msmem_push.geometry import (
    box_corners,
    corners_extent,
    footprint_sweep_hits,
    gripper_pose,
    leading_half_depth,
    swept_extent,
    swept_voxels,
    swept_voxels_reference,
    tool_boxes,
)
from msmem_push.skill import START_FRONT_MARGIN_M, PushAction, PushConfig, PushSkill
from numpy.typing import NDArray
from pydantic import ValidationError

from msmem_core.errors import PluginError
from msmem_core.interfaces import CandidateBatch, DecisionContext, Prediction, Workspace
from msmem_core.map.belief import DeltaBeliefs, EvidentialMap
from msmem_core.map.ig import IGService, shelf_wall_mask
from msmem_core.msas import execute_measured
from msmem_core.perf.ig import block_scene, integrate_evidence, render_voxels
from msmem_core.plugins import get_plugin_manager
from msmem_core.plugins.manager import ComponentRef
from msmem_core.run.metrics import occupancy_iou
from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import look_at, quat_to_matrix, yaw_quat
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.meshes import stance_ratio
from msmem_core.world.scene import OBJECT_CLASSES, ObjectSpec, SceneSpec, ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints
from msmem_core.world.voxelize import interior_mask, voxelize
from tests.support.defaults import ANALYTIC

SHELF = ShelfSpec()
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.01)
WORKSPACE = Workspace(GRID, SHELF, GripperSpec())
SMALL_CAM = CameraConfig(width_px=160, height_px=120)


# ------------------------------------------------------------------------------------------ helpers
def synthetic_belief(seed: int, views: int = 3) -> EvidentialMap:
    """Random blocks on the shelf floor seen from a few views in front (free, seen, hidden voxels)."""
    rng = np.random.default_rng(seed)
    occ, cls = block_scene(GRID, SHELF, rng, num_blocks=int(rng.integers(4, 12)))
    b = EvidentialMap.empty(GRID)
    for _ in range(views):
        eye = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.6, -0.4), rng.uniform(0.1, 0.4)])
        pose = look_at(eye, (rng.uniform(-0.2, 0.2), 0.19, 0.1))
        b = integrate_evidence(b, render_voxels(occ, cls, GRID, SMALL_CAM, pose), stride=1)
    return b


def box_belief(boxes: list[tuple[tuple[float, float], tuple[float, float], float, int]]) -> EvidentialMap:
    """Fully known belief: free everywhere, confident boxes ((x0, y0), (x1, y1), height, class)."""
    b = EvidentialMap.empty(GRID)
    c = GRID.centers()
    b.beta[:] = 21.0
    b.eta[0] = 21.0
    for (x0, y0), (x1, y1), h, k in boxes:
        m = (c[..., 0] > x0) & (c[..., 0] < x1) & (c[..., 1] > y0) & (c[..., 1] < y1)
        m &= (c[..., 2] > 0) & (c[..., 2] < h)
        b.alpha[m], b.beta[m], b.eta[:, m] = 21.0, 1.0, 1.0
        b.eta[k, m] = 21.0
    return b


def push(start: tuple[float, float], u: tuple[float, float], length: float, height: float = 0.02) -> PushAction:
    return PushAction(start_m=start, direction=u, length_m=length, height_m=height)


def support_along(obj: ObjectSpec, pose: np.ndarray, u: np.ndarray) -> float:
    """How far the object's footprint reaches from its origin along the horizontal unit vector u."""
    best = -np.inf
    for part in obj.object_class.parts:
        centre = pose[:3, 3] + pose[:3, :3] @ np.asarray(part.position_m)
        rot = pose[:3, :3] @ quat_to_matrix(part.quat_xyzw)
        reach = np.abs(rot[:2, :2].T @ u) @ (np.asarray(part.size_m[:2]) / 2) if part.kind == "box" else part.size_m[0]
        best = max(best, float((centre[:2] - pose[:2, 3]) @ u + reach))
    return best


# ------------------------------------------------------------------------------------- configuration
def test_bad_push_config_and_actions_are_rejected_naming_the_field() -> None:
    with pytest.raises(ValidationError, match="min_length_m"):
        PushConfig(min_length_m=-0.05)
    with pytest.raises(ValidationError, match="max_length_m"):
        PushConfig(min_length_m=0.2, max_length_m=0.1)
    with pytest.raises(ValidationError, match="approach_y_m"):
        PushConfig(approach_y_m=-0.01)
    with pytest.raises(ValidationError, match="max_samples"):
        PushConfig(max_samples=0)
    with pytest.raises(PluginError, match=r"skills\.1\.params\.max_length_m"):
        get_plugin_manager().build("skill", ComponentRef(name="push", params={"max_length_m": -1.0}), where="skills.1")
    with pytest.raises(ValidationError, match="length_m"):
        push((0.0, 0.05), (0.0, 1.0), -0.1)
    with pytest.raises(ValueError, match="start_m"):  # checked against the workspace's shelf when executed
        push((0.5, 0.1), (0.0, 1.0), 0.1).check_start(SHELF.interior_box)  # beyond the right wall
    with pytest.raises(ValueError, match="start_m"):
        push((0.0, -START_FRONT_MARGIN_M - 0.01), (0.0, 1.0), 0.1).check_start(SHELF.interior_box)
    with pytest.raises(ValueError, match="start_m"):
        PushSkill().execute(None, push((0.5, 0.1), (0.0, 1.0), 0.1), SimpleNamespace(shelf=SHELF))  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="direction"):
        push((0.0, 0.05), (1.0, 1.0), 0.1)
    a = push((0.0, 0.05), (0.0, 1.0), 0.1)
    assert PushAction.model_validate_json(a.model_dump_json()) == a
    assert a.category == "manipulation"
    assert a.kind == "push"


def test_push_and_its_effect_model_are_registered_and_bound() -> None:
    pm = get_plugin_manager()
    spec = pm.skills()["push"]
    assert spec.effect_model == "cnabu-push"  # the better held-out NLL (test_cnabu_shipped)
    assert "effect" in pm.belief_models()["cnabu-push"].roles
    assert "effect" in pm.belief_models()["push-analytic"].roles
    assert "semantic-entropy" in pm.objective_terms()


def _ctx(belief: EvidentialMap, allowed: bool = True, ig: IGService | None = None, seed: int = 0) -> DecisionContext:
    return DecisionContext(5, belief, ig, np.zeros((0, 4, 4)), set(), WORKSPACE,  # type: ignore[arg-type]
                           np.random.default_rng(seed), allowed, 0.5)


def test_no_pushes_outside_the_manipulation_window() -> None:
    b = synthetic_belief(0)
    assert PushSkill().propose(_ctx(b))  # the synthetic beliefs do have occluded regions to push at
    assert PushSkill().propose(_ctx(b, allowed=False)) == []
    assert PushSkill().propose(_ctx(EvidentialMap.empty(GRID))) == []  # nothing known: nothing to push


# ---------------------------------------------------------------------------------------- sampling
@settings(max_examples=8, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_push_samples_never_start_in_believed_occupancy_nor_sweep_through_a_wall(seed: int) -> None:
    belief = synthetic_belief(seed)
    cfg = PushConfig(max_samples=40)
    actions = PushSkill(cfg).propose(_ctx(belief, seed=seed))
    assert len(actions) <= cfg.max_samples
    occupied = (belief.expected_occupancy() > cfg.occupied_threshold).ravel()
    walls = shelf_wall_mask(GRID, SHELF).ravel()
    lo_in, hi_in = SHELF.interior_lower, SHELF.interior_upper
    for a in actions:
        assert isinstance(a, PushAction)
        assert cfg.min_length_m <= a.length_m <= cfg.max_length_m
        assert abs(np.hypot(*a.direction) - 1) < 1e-9
        at_start = swept_voxels(GRID, a.start, a.u, a.height_m, a.tool(WORKSPACE.gripper))
        assert not occupied[at_start].any(), "the tool starts inside believed-occupied space"
        swept = a.swept_volume(WORKSPACE).ravel()
        assert swept.any()
        assert not (swept & walls).any(), "the push sweeps through a wall voxel"
        lo, hi = swept_extent(a.start, a.u, a.height_m, a.tool(WORKSPACE.gripper), a.length_m * a.u)
        assert lo[0] >= lo_in[0]
        assert hi[0] <= hi_in[0]
        assert hi[1] <= hi_in[1]
        assert hi[2] <= hi_in[2]
        approach = np.array([a.start[0], cfg.approach_y_m])
        corridor = swept_voxels(GRID, approach, a.u, a.height_m, a.tool(WORKSPACE.gripper), a.start - approach)
        assert not occupied[corridor].any(), "the approach crosses believed-occupied space"


@settings(max_examples=300, deadline=None)
@given(st.floats(-0.45, 0.45), st.floats(-0.1, 0.45), st.floats(0.0, 2 * np.pi), st.floats(-0.05, 0.3),
       st.floats(0.0, 0.3), st.booleans(), st.sampled_from(["along", "across", "forward"]))
def test_swept_voxels_kernel_equals_the_numpy_rasterisation(x: float, y: float, angle: float, tip_z: float,
                                                            length: float, on_grid: bool, palm: str) -> None:
    if on_grid:  # voxel-aligned starts, axis-aligned directions, whole-cm heights: the boundary cases
        x, y, tip_z, angle = round(x, 2) + 0.005, round(y, 2), round(tip_z, 2), round(angle / (np.pi / 4)) * np.pi / 4
    u = np.array([np.cos(angle), np.sin(angle)])
    boxes = tool_boxes(GripperSpec(), palm, (0.204, 0.063, 0.066) if palm == "forward" else None)
    want = swept_voxels_reference(GRID, (x, y), u, tip_z, boxes, length * u)
    np.testing.assert_array_equal(swept_voxels(GRID, (x, y), u, tip_z, boxes, length * u), want)
    np.testing.assert_array_equal(swept_voxels(GRID, (x, y), u, tip_z, boxes[:1]), swept_voxels_reference(
        GRID, (x, y), u, tip_z, boxes[:1]))


def test_ups_targets_the_occluder_of_a_hidden_region() -> None:
    # a wide box in front hides the region behind it; nothing else is known there
    b = EvidentialMap.empty(GRID)
    c = GRID.centers()
    front = (c[..., 1] < 0.04) & (c[..., 1] > 0) & (c[..., 2] > 0)
    b.beta[front], b.eta[0][front] = 21.0, 21.0  # free space in front of the box
    box = (np.abs(c[..., 0]) < 0.08) & (c[..., 1] > 0.04) & (c[..., 1] < 0.06) & (c[..., 2] > 0) & (c[..., 2] < 0.15)
    b.alpha[box], b.beta[box], b.eta[:, box] = 21.0, 1.0, 1.0
    b.eta[3][box] = 21.0
    around = (np.abs(c[..., 0]) >= 0.08) & (c[..., 1] > 0) & (c[..., 2] > 0)  # the sides are free and known
    b.beta[around], b.eta[0][around] = 21.0, 21.0
    actions = PushSkill().propose(_ctx(b))
    assert actions
    assert all(a.target_class == 3 for a in actions)
    starts = np.array([a.start_m for a in actions])
    assert np.all(starts[:, 1] < 0.06 + 0.03)  # in front of or beside the box
    dirs = np.array([a.direction for a in actions])
    assert np.any(dirs[:, 1] > 0.8)
    assert np.any(np.abs(dirs[:, 0]) > 0.8)


def test_clearance_keeps_the_pushed_object_clear_of_its_neighbour() -> None:
    """A wide box hides a region; a second box stands 6 cm to its right. With ``clearance_m`` no push
    of the wide box moves its footprint to within the clearance of the second box (less a voxel of
    rasterisation); without it some sideways pushes drive it into the second box."""
    b = EvidentialMap.empty(GRID)
    c = GRID.centers()
    floor = c[..., 2] > 0
    front = (c[..., 1] < 0.04) & (c[..., 1] > 0) & floor
    b.beta[front], b.eta[0][front] = 21.0, 21.0
    around = (np.abs(c[..., 0]) >= 0.08) & (c[..., 1] > 0) & floor
    b.beta[around], b.eta[0][around] = 21.0, 21.0
    boxes = {3: ((-0.08, 0.04), (0.08, 0.06)), 5: ((0.14, 0.03), (0.20, 0.07))}
    for k, ((x0, y0), (x1, y1)) in boxes.items():
        m = (c[..., 0] > x0) & (c[..., 0] < x1) & (c[..., 1] > y0) & (c[..., 1] < y1) & floor & (c[..., 2] < 0.15)
        b.alpha[m], b.beta[m], b.eta[:, m] = 21.0, 1.0, 1.0
        b.eta[k, m] = 21.0
    (ax0, ay0), (ax1, ay1) = boxes[3]
    (bx0, by0), (bx1, by1) = boxes[5]

    def overlap_after(a: PushAction, margin: float) -> bool:
        d = max(a.length_m - PushConfig().standoff_m, 0.0) * np.asarray(a.direction)
        return bool(ax0 + d[0] < bx1 + margin and ax1 + d[0] > bx0 - margin
                    and ay0 + d[1] < by1 + margin and ay1 + d[1] > by0 - margin)

    clearance = 0.02
    kept = [a for seed in range(4) for a in PushSkill(PushConfig(clearance_m=clearance)).propose(_ctx(b, seed=seed))
            if a.target_class == 3]
    free = [a for seed in range(4) for a in PushSkill().propose(_ctx(b, seed=seed)) if a.target_class == 3]
    assert kept
    assert free
    assert any(overlap_after(a, 0.0) for a in free), "without a clearance some pushes hit the neighbour"
    assert not any(overlap_after(a, clearance - 0.011) for a in kept)
    toward = [a for a in kept if a.direction[0] > 0.8]
    assert toward, "pushes toward the neighbour are shortened, not all dropped"
    assert max(a.length_m for a in toward) <= 0.06 - clearance + PushConfig().standoff_m + 0.011


def _row_belief(boxes: dict[int, tuple[tuple[float, float], tuple[float, float]]],
                heights: dict[int, float] | None = None) -> EvidentialMap:
    """Free space known in front of y = 4 cm and beside |x| = 8 cm, unknown elsewhere; each box (class:
    (x0, y0), (x1, y1)) 15 cm tall (or ``heights[class]``) and confidently of its class."""
    b = EvidentialMap.empty(GRID)
    c = GRID.centers()
    floor = c[..., 2] > 0
    known = ((c[..., 1] < 0.04) | (np.abs(c[..., 0]) >= 0.08)) & (c[..., 1] > 0) & floor
    b.beta[known], b.eta[0][known] = 21.0, 21.0
    for k, ((x0, y0), (x1, y1)) in boxes.items():
        top = (heights or {}).get(k, 0.15)
        m = (c[..., 0] > x0) & (c[..., 0] < x1) & (c[..., 1] > y0) & (c[..., 1] < y1) & floor & (c[..., 2] < top)
        b.alpha[m], b.beta[m], b.eta[:, m] = 21.0, 1.0, 1.0
        b.eta[k, m] = 21.0
    return b


def test_chain_clearance_stops_the_row_short_of_the_wall_but_lets_the_target_push_its_neighbour() -> None:
    """A wide box hides a region; a second box stands 6 cm to its right and 8 cm from the right wall. With
    ``chain_clearance_m`` a push to the right may drive the second box (unlike ``clearance_m``) but ends
    before the second box, driven by the first, reaches the wall: after 14 cm of travel, less the
    clearance. Pushes into the shelf, where nothing known stands before the back wall, keep their full length."""
    x_hi = WORKSPACE.shelf.interior_box[3]
    b = _row_belief({3: ((-0.08, 0.04), (0.08, 0.06)), 5: ((0.14, 0.03), (x_hi - 0.08, 0.07))})
    clearance, standoff, voxel = 0.01, PushConfig().standoff_m, GRID.voxel_m

    def pushes(cfg: PushConfig) -> list[PushAction]:
        return [a for seed in range(6) for a in PushSkill(cfg).propose(_ctx(b, seed=seed)) if a.target_class == 3]

    free, kept = pushes(PushConfig(chain_clearance_m=None)), pushes(PushConfig(chain_clearance_m=clearance))
    right = [a for a in kept if a.direction[0] > 0.95]
    into = [a for a in kept if a.direction[1] > 0.95]
    assert right
    assert into
    jam = 0.06 + 0.08  # travel of the first box when the second one reaches the wall
    assert max(a.length_m for a in right) <= jam - clearance + standoff + voxel
    assert max(a.length_m for a in right) > 0.06 + standoff + voxel, "pushing into the neighbour is allowed"
    assert max(a.length_m for a in free if a.direction[0] > 0.95) > jam + standoff + voxel
    assert max(a.length_m for a in into) > PushConfig().max_length_m - voxel


def test_chain_clearance_with_max_height_ratio_stops_before_a_thin_tall_neighbour() -> None:
    """The same row, but the neighbour is a 3 cm thin, 15 cm tall board (a book on its edge): with
    ``max_height_ratio`` a chain must not reach it, so pushes to the right end before contact (after
    6 cm of travel, less the clearance), while the box itself (6 cm deep) is still pushed."""
    b = _row_belief({3: ((-0.08, 0.04), (0.08, 0.10)), 5: ((0.14, 0.03), (0.17, 0.11))})
    clearance, standoff, voxel = 0.01, PushConfig().standoff_m, GRID.voxel_m

    def right(cfg: PushConfig) -> list[PushAction]:
        return [a for seed in range(6) for a in PushSkill(cfg).propose(_ctx(b, seed=seed))
                if a.target_class == 3 and a.direction[0] > 0.95]

    chain_only = right(PushConfig(chain_clearance_m=clearance))
    both = right(PushConfig(chain_clearance_m=clearance, max_height_ratio=4.0))
    assert both
    assert max(a.length_m for a in both) <= 0.06 - clearance + standoff + voxel
    assert max(a.length_m for a in chain_only) > 0.06 + standoff + voxel


def test_chain_travel_limits_how_far_a_driven_neighbour_moves() -> None:
    """The row of the chain-clearance test: the neighbour starts moving after 6 cm of the first box's
    travel. With ``chain_travel_m`` 3 cm, pushes to the right end 3 cm later (9 cm of travel) instead of
    at the wall (14 cm, less the clearance); pushes into the shelf, which drive nothing known, keep
    their full length."""
    x_hi = WORKSPACE.shelf.interior_box[3]
    b = _row_belief({3: ((-0.08, 0.04), (0.08, 0.06)), 5: ((0.14, 0.03), (x_hi - 0.08, 0.07))})
    standoff, voxel = PushConfig().standoff_m, GRID.voxel_m

    def pushes(cfg: PushConfig) -> list[PushAction]:
        return [a for seed in range(6) for a in PushSkill(cfg).propose(_ctx(b, seed=seed)) if a.target_class == 3]

    limited = pushes(PushConfig(chain_travel_m=0.03))
    right = [a for a in limited if a.direction[0] > 0.95]
    into = [a for a in limited if a.direction[1] > 0.95]
    assert right
    assert max(a.length_m for a in right) <= 0.06 + 0.03 + standoff + voxel
    assert max(a.length_m for a in right) > 0.06 + standoff + voxel, "the neighbour is still pushed, a little"
    unlimited = [a for a in pushes(PushConfig()) if a.direction[0] > 0.95]
    assert max(a.length_m for a in unlimited) > 0.06 + 0.03 + standoff + voxel
    assert max(a.length_m for a in into) > PushConfig().max_length_m - voxel


def test_trip_height_ratio_stops_a_tall_object_before_a_much_lower_one() -> None:
    """The row of the chain-clearance test with a 4 cm low neighbour: with ``trip_height_ratio`` 2 the 15 cm
    tall box is not driven into it (pushes to the right end before contact, after 6 cm of travel less the
    clearance) but still pushed into the shelf; at ratio 4 (15 < 4 x 4) and without the check the
    neighbour is driven. A low box driving a tall neighbour trips nothing."""
    b = _row_belief({3: ((-0.08, 0.04), (0.08, 0.10)), 5: ((0.14, 0.03), (0.17, 0.11))}, {5: 0.04})
    clearance, standoff, voxel = PushConfig().chain_clearance_m, PushConfig().standoff_m, GRID.voxel_m
    contact = 0.06 - clearance + standoff + voxel  # the longest push that stops before the neighbour

    def right(cfg: PushConfig, belief: EvidentialMap = b) -> list[PushAction]:
        return [a for seed in range(6) for a in PushSkill(cfg).propose(_ctx(belief, seed=seed))
                if a.target_class == 3 and a.direction[0] > 0.95]

    tripping = [a for seed in range(6) for a in PushSkill(PushConfig(trip_height_ratio=2.0)).propose(
        _ctx(b, seed=seed)) if a.target_class == 3]
    assert [a for a in tripping if a.direction[0] > 0.95]
    assert max(a.length_m for a in tripping if a.direction[0] > 0.95) <= contact
    assert max(a.length_m for a in tripping if a.direction[1] > 0.95) > PushConfig().max_length_m - voxel
    for cfg in (PushConfig(trip_height_ratio=None), PushConfig(trip_height_ratio=4.0)):
        assert max(a.length_m for a in right(cfg)) > 0.06 + standoff + voxel
    low_first = _row_belief({3: ((-0.08, 0.04), (0.08, 0.10)), 5: ((0.14, 0.03), (0.17, 0.11))}, {3: 0.04})
    assert max(a.length_m for a in right(PushConfig(trip_height_ratio=2.0), low_first)) > 0.06 + standoff + voxel


def test_max_pushes_per_object_refuses_an_object_pushed_that_often_and_only_that_object() -> None:
    """Two boxes of different classes: after one executed push of box 3 (recorded by ``record_push``, which
    ``execute`` calls), ``max_pushes_per_object`` 1 proposes no more pushes of it but still of box 5; at 2,
    box 3 is still pushed, and it is recognised where the push left it (its end contact) as well as where
    it started."""
    b = _row_belief({3: ((-0.08, 0.04), (0.0, 0.08)), 5: ((0.06, 0.04), (0.14, 0.08))})

    def targets(skill: PushSkill) -> set[int | None]:
        return {a.target_class for seed in range(4) for a in skill.propose(_ctx(b, seed=seed))}

    once = PushSkill(PushConfig(max_pushes_per_object=1))
    assert targets(once) == {3, 5}
    first = next(a for a in once.propose(_ctx(b)) if a.target_class == 3)
    once.record_push(first)
    assert targets(once) == {5}
    twice = PushSkill(PushConfig(max_pushes_per_object=2))
    twice.record_push(first)
    assert targets(twice) == {3, 5}
    moved = PushSkill(PushConfig(max_pushes_per_object=1))  # only the end contact lies on the footprint now
    far = first.model_copy(update={"contact_m": (first.contact_m[0] - 0.3, first.contact_m[1], 0.05),
                                   "direction": (1.0, 0.0), "length_m": 0.3 + PushConfig().standoff_m})
    moved.record_push(far)
    assert targets(moved) == {5}
    assert targets(PushSkill()) == {3, 5}
    once.track(_ctx(b))  # the same episode (step 5): still remembered
    assert targets(once) == {5}
    once.track(DecisionContext(0, b, None, np.zeros((0, 4, 4)), set(), WORKSPACE,  # type: ignore[arg-type]
                               np.random.default_rng(0), True, 0.5))
    assert targets(once) == {3, 5}, "a new episode (step 0) forgets the last one's pushes"


def test_max_height_ratio_refuses_to_push_a_thin_tall_object() -> None:
    """A 16 x 2 cm box 15 cm tall (7.5 times as tall as its narrowest width) is pushed without the
    check, not at all with ``max_height_ratio`` 3, and again with 8."""
    b = EvidentialMap.empty(GRID)
    c = GRID.centers()
    floor = c[..., 2] > 0
    known = ((c[..., 1] < 0.04) | (np.abs(c[..., 0]) >= 0.08)) & (c[..., 1] > 0) & floor
    b.beta[known], b.eta[0][known] = 21.0, 21.0
    m = (np.abs(c[..., 0]) < 0.08) & (c[..., 1] > 0.04) & (c[..., 1] < 0.06) & floor & (c[..., 2] < 0.15)
    b.alpha[m], b.beta[m], b.eta[:, m] = 21.0, 1.0, 1.0
    b.eta[3, m] = 21.0

    def pushes(cfg: PushConfig) -> list[PushAction]:
        return [a for seed in range(3) for a in PushSkill(cfg).propose(_ctx(b, seed=seed))]  # type: ignore[misc]

    assert pushes(PushConfig())
    assert pushes(PushConfig(max_height_ratio=3.0)) == []
    assert pushes(PushConfig(max_height_ratio=8.0))


def _class_ctx(belief: EvidentialMap, seed: int, classes: tuple = OBJECT_CLASSES) -> DecisionContext:  # type: ignore[type-arg]
    """``_ctx`` in a workspace that knows the built-in classes' shapes (as a run's does)."""
    ws = Workspace(GRID, SHELF, GripperSpec(), classes=classes)
    return DecisionContext(5, belief, None, np.zeros((0, 4, 4)), set(), ws,  # type: ignore[arg-type]
                           np.random.default_rng(seed), True, 0.5)


def test_stance_ratio_judges_a_class_by_the_axis_standing_up() -> None:
    """A sugar box (9 x 4 x 17.5 cm) standing is 17.5 / 4 tall for its width, lying on its side 4 / 9;
    a cracker box (16 x 6 x 21 cm) standing 21 / 6. The axis standing up is the extent closest to the
    believed height, so a top seen a little low still finds it."""
    sugar, cracker = (next(c for c in OBJECT_CLASSES if c.name == n) for n in ("sugar_box", "cracker_box"))
    assert stance_ratio(sugar, 0.175) == pytest.approx(0.175 / 0.04)
    assert stance_ratio(sugar, 0.15) == pytest.approx(0.175 / 0.04)
    assert stance_ratio(sugar, 0.04) == pytest.approx(0.04 / 0.09)
    assert stance_ratio(sugar, 0.09) == pytest.approx(0.09 / 0.04)  # on its long edge: thin again
    assert stance_ratio(cracker, 0.21) == pytest.approx(0.21 / 0.06)


def test_an_upright_class_tips_by_its_support_not_its_extents() -> None:
    """Standing upright, a box's tip ratio is its height over its narrow width, as its extents say; a
    10 cm cube of a box on a 1 cm thin foot (extents 10 x 10 x 10 cm) tips as its mass centre (7.4 cm
    up) over its foot's radius (1 cm) says."""
    from msmem_core.world.scene import ObjectClass, Part

    cracker = next(c for c in OBJECT_CLASSES if c.name == "cracker_box")
    assert stance_ratio(cracker, 0.21) == pytest.approx(0.21 / 0.06)
    foot, top = np.pi * 0.01**2 * 0.05, 0.1 * 0.1 * 0.05
    com_z = (foot * 0.025 + top * 0.075) / (foot + top)
    mushroom = ObjectClass(name="mushroom", class_id=1, mass_kg=0.1, parts=(
        Part(kind="cylinder", size_m=(0.01, 0.05), position_m=(0.0, 0.0, 0.025)),
        Part(kind="box", size_m=(0.1, 0.1, 0.05), position_m=(0.0, 0.0, 0.075))))
    assert stance_ratio(mushroom, 0.1) == pytest.approx(com_z / 0.01, rel=0.01)  # the foot is a 48-gon


def test_class_height_ratio_refuses_a_standing_sugar_box_from_its_front_face_alone() -> None:
    """A sugar box (class 2) seen from the front only: its believed footprint is 9 cm wide and 4 cm
    deep. Standing (17.5 cm tall) it is not pushed by default, judged by its class's shape; lying
    (4 cm tall) it is; without the check, or without class shapes in the workspace, it is pushed
    standing too."""
    def belief(height: float) -> EvidentialMap:
        b = EvidentialMap.empty(GRID)
        c = GRID.centers()
        floor = c[..., 2] > 0
        known = ((c[..., 1] < 0.04) | (np.abs(c[..., 0]) >= 0.08)) & (c[..., 1] > 0) & floor
        b.beta[known], b.eta[0][known] = 21.0, 21.0
        m = (np.abs(c[..., 0]) < 0.045) & (c[..., 1] > 0.04) & (c[..., 1] < 0.08) & floor & (c[..., 2] < height)
        b.alpha[m], b.beta[m], b.eta[:, m] = 21.0, 1.0, 1.0
        b.eta[2, m] = 21.0
        return b

    def pushes(b: EvidentialMap, cfg: PushConfig, classes: tuple = OBJECT_CLASSES) -> list:  # type: ignore[type-arg]
        return [a for seed in range(3) for a in PushSkill(cfg).propose(_class_ctx(b, seed, classes))]

    standing, lying = belief(0.175), belief(0.04)
    assert pushes(standing, PushConfig()) == []
    assert pushes(lying, PushConfig())
    assert pushes(standing, PushConfig(class_height_ratio=None))
    assert pushes(standing, PushConfig(), classes=())
    assert pushes(standing, PushConfig(class_height_ratio=5.0)), "4.4 is below a ratio of 5"


def test_chain_clearance_stops_before_a_neighbour_standing_thin_by_its_class() -> None:
    """The chain-clearance row, the neighbour a sugar box (class 2) believed 15 cm tall, its footprint
    4 cm deep and 8 cm wide: by its class's shape it stands thin (17.5 / 4), so pushes to the right end
    before contact (after 6 cm, less the clearance); as a mustard bottle (class 5, 19 / 5.8) it is
    driven as before."""
    x_hi = WORKSPACE.shelf.interior_box[3]
    clearance, standoff, voxel = 0.01, PushConfig().standoff_m, GRID.voxel_m

    def right(neighbour: int) -> list[PushAction]:
        b = _row_belief({3: ((-0.08, 0.04), (0.08, 0.06)), neighbour: ((0.14, 0.03), (x_hi - 0.08, 0.07))})
        return [a for seed in range(6) for a in PushSkill(PushConfig()).propose(_class_ctx(b, seed))
                if a.target_class == 3 and a.direction[0] > 0.95]  # type: ignore[attr-defined]

    thin, sturdy = right(2), right(5)
    assert thin
    assert max(a.length_m for a in thin) <= 0.06 - clearance + standoff + voxel
    assert max(a.length_m for a in sturdy) > 0.06 + standoff + voxel


# ------------------------------------------------------------------------------------ effect model
def test_effect_model_moves_a_pushed_box_and_what_is_in_its_way() -> None:
    # box A (class 3) at y 0.10-0.16, box B (class 5) behind it at y 0.20-0.26, both 8 cm wide
    b = box_belief([((-0.04, 0.10), (0.04, 0.16), 0.10, 3), ((-0.04, 0.20), (0.04, 0.26), 0.10, 5)])
    hd = leading_half_depth(PushSkill().tool, 0.02, 0.10)
    a = push((0.0, 0.10 - 0.01 - hd), (0.0, 1.0), 0.15)  # 1 cm standoff: A moves 14 cm, B 10 cm
    model = AnalyticPushEffect()
    pred = model.predict(b, [a], WORKSPACE)
    after = pred.beliefs[0]
    occ0, occ1 = b.expected_occupancy() > 0.5, after.expected_occupancy() > 0.5
    cls1 = np.argmax(after.eta, axis=0)
    ys = GRID.centers()[..., 1]
    a_new, b_new = occ1 & (cls1 == 3), occ1 & (cls1 == 5)
    assert a_new.sum() == (occ0 & (np.argmax(b.eta, axis=0) == 3)).sum()  # evidence moved, none lost
    assert ys[a_new].min() == pytest.approx(0.10 + 0.14, abs=0.011)
    assert ys[b_new].min() == pytest.approx(0.20 + 0.10, abs=0.011)
    vacated = (ys > 0.10) & (ys < 0.20) & occ0
    assert np.all(after.expected_occupancy()[vacated] == 0.5), "the box's old place returns to the prior"
    # the changed mask is exactly where evidence differs; the untouched rest is identical
    diff = (after.alpha != b.alpha) | (after.beta != b.beta) | np.any(after.eta != b.eta, axis=0)
    np.testing.assert_array_equal(pred.changed[0], diff)
    assert isinstance(pred.beliefs, DeltaBeliefs)


def test_effect_model_stops_objects_at_the_back_wall_and_is_batched() -> None:
    b = box_belief([((-0.04, 0.28), (0.04, 0.34), 0.10, 3), ((0.20, 0.10), (0.26, 0.16), 0.05, 7)])
    model = AnalyticPushEffect()
    a_back = push((0.0, 0.28 - 0.02), (0.0, 1.0), 0.25)  # only 4 cm of room behind the box
    moves = model.displacements(b, a_back, WORKSPACE)
    assert len(moves) == 1
    assert moves[0][1] == pytest.approx(0.04, abs=0.011)
    a_miss = push((-0.3, 0.05), (0.0, 1.0), 0.1)  # touches nothing
    a_side = push((0.15, 0.13), (1.0, 0.0), 0.08)
    batch = model.predict(b, [a_back, a_miss, a_side], WORKSPACE)
    for k, a in enumerate([a_back, a_miss, a_side]):
        single = model.predict(b, [a], WORKSPACE)
        np.testing.assert_array_equal(batch.changed[k], single.changed[0])
        np.testing.assert_array_equal(batch.beliefs[k].alpha, single.beliefs[0].alpha)
    assert model.displacements(b, a_miss, WORKSPACE) == []
    # a push that touches nothing changes only the semantic confidence along the tool's path
    assert np.array_equal(batch.beliefs[1].alpha, b.alpha)
    assert np.array_equal(batch.beliefs[1].beta, b.beta)


# ---------------------------------------------------------------------------------- objective terms
def _small_ig(seed: int = 0) -> IGService:
    views = generate_viewpoints(ViewpointConfig(), SHELF)[::15]
    return IGService(GRID, SMALL_CAM, views, SHELF)


def test_manipulation_ig_is_the_best_view_after_the_predicted_belief_and_screening_keeps_finalists_exact() -> None:
    belief = synthetic_belief(3)
    ig = _small_ig()
    ctx = _ctx(belief, ig=ig)
    actions = PushSkill(PushConfig(max_samples=12)).propose(ctx)
    assert len(actions) > 4
    pred = AnalyticPushEffect().predict(belief, actions, WORKSPACE)
    batch = CandidateBatch("push", "manipulation", list(actions), prediction=pred)
    full = ig.view_ig([ig.prepare(b, before=ctx.field) for b in pred.beliefs]).max(axis=1)
    exact = IGTerm(IGTermConfig(screen_ray_step=1)).score(ctx, batch)
    np.testing.assert_allclose(exact, full, rtol=1e-9)
    reference = IGTerm(IGTermConfig(incremental=False)).score(ctx, batch)
    np.testing.assert_allclose(reference, full, rtol=1e-12)
    screened = IGTerm(IGTermConfig(screen_ray_step=2, finalists=3)).score(ctx, batch)
    finalists = np.isclose(screened, full, rtol=1e-9)
    assert finalists.sum() >= 3
    assert np.all(screened[~finalists] <= screened[finalists].min() + 1e-9)


def push_batch(seed: int) -> tuple[EvidentialMap, IGService, DecisionContext, Prediction, CandidateBatch]:
    """A synthetic belief, the small IG service, a context on them and 12 sampled pushes, predicted
    by the analytic effect model, as a batch."""
    belief = synthetic_belief(seed)
    ig = _small_ig()
    ctx = _ctx(belief, ig=ig)
    actions = PushSkill(PushConfig(max_samples=12)).propose(ctx)
    pred = AnalyticPushEffect().predict(belief, actions, WORKSPACE)
    return belief, ig, ctx, pred, CandidateBatch("push", "manipulation", list(actions), prediction=pred)


def test_finalists_are_scored_at_full_density_over_their_best_screened_views() -> None:
    belief, ig, ctx, pred, batch = push_batch(2)
    fields = [ig.prepare(b, before=ctx.field) for b in pred.beliefs]
    full = ig.view_ig(fields)  # [K, V] at full density
    coarse = np.stack([ig.sweep(f, ray_step=2) for f in fields])  # the screening's view of each
    top = np.argsort(-coarse.max(axis=1), kind="stable")[:3]
    # each finalist over its own 2 best screened views: the best full-density IG among the union's views
    two = IGTerm(IGTermConfig(finalists=3, finalist_views=2)).score(_ctx(belief, ig=ig), batch)
    union = np.unique(np.argsort(-coarse[top], axis=1, kind="stable")[:, :2])
    np.testing.assert_allclose(two[top], full[np.ix_(top, union)].max(axis=1), rtol=1e-9)
    assert np.all(two[top] <= full[top].max(axis=1) + 1e-9)
    assert np.any(two[top] < full[top].max(axis=1) - 1e-6)  # here the restriction does cost some IG
    # every view (0, or as many as there are): the best view's full-density IG
    for k in (0, ig.num_views):
        every = IGTerm(IGTermConfig(finalists=3, finalist_views=k)).score(_ctx(belief, ig=ig), batch)
        np.testing.assert_allclose(every[top], full[top].max(axis=1), rtol=1e-9)


def test_semantic_entropy_term_is_the_clipped_entropy_difference() -> None:
    belief = synthetic_belief(4)
    actions = PushSkill(PushConfig(max_samples=10)).propose(_ctx(belief))
    pred = AnalyticPushEffect().predict(belief, actions, WORKSPACE)
    ctx = _ctx(belief)
    batch = CandidateBatch("push", "manipulation", list(actions), prediction=pred)
    term = SemanticEntropyTerm()
    assert term.applies_to == frozenset({"manipulation"})
    sparse = term.score(ctx, batch)
    h0 = belief.total_semantic_entropy()
    want = np.array([min(0.0, h0 - b.total_semantic_entropy()) for b in pred.beliefs])
    np.testing.assert_allclose(sparse, want, rtol=1e-6, atol=1e-3)
    dense = Prediction.from_beliefs(belief, list(pred.beliefs))  # an effect model predicting whole maps
    for d, e in zip(dense.changes, pred.changes, strict=True):
        np.testing.assert_array_equal(d.idx, e.idx)
    dense_batch = CandidateBatch("push", "manipulation", list(actions), prediction=dense)
    np.testing.assert_allclose(term.score(_ctx(belief), dense_batch), want, rtol=1e-9)
    assert np.all(sparse <= 0.0)
    assert np.any(sparse < 0.0)
    # a prediction that only adds confidence is not rewarded
    sharper = belief.copy()
    sharper.eta[0] += 5.0
    sharp_batch = CandidateBatch("push", "manipulation", list(actions[:1]),
                                 prediction=Prediction.from_beliefs(belief, [sharper]))
    assert term.score(_ctx(belief), sharp_batch)[0] == 0.0


def test_unclipped_semantic_entropy_is_the_papers_difference_and_rewards_removed_entropy() -> None:
    from msmem_objectives.entropy import SemanticEntropyConfig

    belief = synthetic_belief(4)
    actions = PushSkill(PushConfig(max_samples=10)).propose(_ctx(belief))
    pred = AnalyticPushEffect().predict(belief, actions, WORKSPACE)
    batch = CandidateBatch("push", "manipulation", list(actions), prediction=pred)
    term = SemanticEntropyTerm(SemanticEntropyConfig(clip=False))
    h0 = belief.total_semantic_entropy()
    want = np.array([h0 - b.total_semantic_entropy() for b in pred.beliefs])
    np.testing.assert_allclose(term.score(_ctx(belief), batch), want, rtol=1e-6, atol=1e-3)
    sharper = belief.copy()
    sharper.eta[0] += 5.0  # more background evidence everywhere: less entropy
    sharp = CandidateBatch("push", "manipulation", list(actions[:1]),
                           prediction=Prediction.from_beliefs(belief, [sharper]))
    assert term.score(_ctx(belief), sharp)[0] == pytest.approx(h0 - sharper.total_semantic_entropy(), rel=1e-6)
    assert term.score(_ctx(belief), sharp)[0] > 0.0


# ---------------------------------------------------------------------------------- physics (PyBullet)
@pytest.fixture(scope="module")
def sim():  # type: ignore[no-untyped-def]
    from msmem_pybullet.simulator import PyBulletConfig, PyBulletSimulator

    s = PyBulletSimulator(PyBulletConfig(label_noise=0.0))
    yield s
    s.close()


def commanded_pushes(sim, skill: PushSkill, n: int = 20, seed: int = 2024) -> tuple[int, int, int, list[str]]:  # type: ignore[no-untyped-def]
    """n seeded single-object pushes (random class, yaw, direction, length) through ``skill.execute``,
    the tool starting ``standoff_m`` from the object along the line through its origin. Returns how
    many moved the commanded length (length - standoff) within 30 % or 2 cm, how many fell, how many
    times the tool reached the end of its push, and a log."""
    cfg = skill.config
    rng = np.random.default_rng(seed)
    good, fell, reached, rows = 0, 0, 0, []
    for _ in range(n):
        cls = OBJECT_CLASSES[int(rng.integers(len(OBJECT_CLASSES)))]
        into = rng.random() < 0.6
        ang = np.pi / 2 + rng.uniform(-0.3, 0.3) if into else rng.choice([0.0, np.pi]) + rng.uniform(-0.2, 0.2)
        u = np.array([np.cos(ang), np.sin(ang)])
        x = rng.uniform(-0.2, 0.2) if into else -0.1 * np.sign(u[0])
        y = rng.uniform(0.08, 0.15) if into else rng.uniform(0.12, 0.25)
        obj = ObjectSpec(id=3, class_name=cls.name, position_m=(float(x), float(y), 0.0),
                         quat_xyzw=tuple(float(q) for q in yaw_quat(rng.uniform(-np.pi, np.pi))))
        sim.reset(SceneSpec(objects=(obj,)))
        pose = sim.object_poses()[3]
        top = max(p.position_m[2] + p.half_height_m for p in cls.parts)
        height = max(cfg.min_tool_height_m, min(cfg.tool_height_m, cfg.low_object_fraction * top))
        lead = leading_half_depth(skill.tool, height, top)
        start = pose[:2, 3] - (support_along(obj, pose, -u) + cfg.standoff_m + lead) * u
        length = float(rng.uniform(cfg.min_length_m, 0.2))
        action = PushAction(start_m=(float(start[0]), float(start[1])),
                            direction=(float(u[0]), float(u[1])), length_m=length, height_m=height,
                            palm=cfg.palm)
        out = execute_measured(skill, sim, action, SimpleNamespace(shelf=SHELF))  # type: ignore[arg-type]
        commanded = length - cfg.standoff_m  # the tool meets the object after the standoff
        moved = out.displacement_m[3]
        ok = abs(moved - commanded) <= max(0.3 * commanded, 0.02)
        good += ok
        fell += bool(out.fell_or_left)
        reached += out.success
        rows.append(f"{cls.name:16s} commanded {commanded:.3f} moved {moved:.3f} fell {out.fell_or_left} ok {ok}")
        assert sim.gripper_pose()[2, 3] > 1.0, "the gripper is parked after the push"
    return good, fell, reached, rows


def test_pushes_move_objects_by_the_commanded_length(sim) -> None:  # type: ignore[no-untyped-def]
    good, fell, reached, rows = commanded_pushes(sim, PushSkill())
    print("\n".join(rows))
    print(f"pushes within 30% or 2 cm of the commanded length: {good}/20 ({fell} fell)")
    assert good >= 16
    assert reached == 20, "the tool did not reach the end of every push"


@pytest.mark.slow
def test_the_default_tool_height_topples_nothing_where_mems_topples_objects(sim) -> None:  # type: ignore[no-untyped-def]
    """The survey behind the 2 cm default (docs/explanation/push.md): 40 pushes per setting, the same seed."""
    low = commanded_pushes(sim, PushSkill(PushConfig(palm="along", tool_height_m=0.02)), n=40, seed=7)
    high = commanded_pushes(sim, PushSkill(PushConfig(palm="along", tool_height_m=0.085)), n=40, seed=7)
    assert low[1] == 0, "a push at the default height toppled an object"
    assert low[0] >= 38
    assert high[1] > low[1], "MEM's 8.5 cm should topple more objects than the 2 cm default"


def test_effect_model_predicts_the_post_push_occupancy_better_than_no_change(sim) -> None:  # type: ignore[no-untyped-def]
    from msmem_analytic.observation import AnalyticObservationModel

    views = generate_viewpoints(ViewpointConfig(), SHELF)
    observe, model = AnalyticObservationModel(), AnalyticPushEffect()
    inside = interior_mask(SHELF, GRID)
    results = []
    for seed in range(4):
        skill = PushSkill()  # one per scene: it remembers the pushes it executed (max_pushes_per_object)
        rng = np.random.default_rng(seed)
        objs = (
            ObjectSpec(id=0, class_name="cracker_box", position_m=(float(rng.uniform(-0.15, 0.15)), 0.06, 0.0)),
            ObjectSpec(id=1, class_name="tomato_soup_can", position_m=(float(rng.uniform(-0.25, 0.25)), 0.25, 0.0)),
            ObjectSpec(id=2, class_name="foam_brick", position_m=(float(rng.uniform(-0.3, 0.3)), 0.18, 0.0),
                       quat_xyzw=tuple(float(q) for q in yaw_quat(rng.uniform(-1, 1)))),
        )
        sim.reset(SceneSpec(objects=objs))
        belief = EvidentialMap.empty(GRID)
        for v in rng.choice(len(views), 4, replace=False):
            belief = observe.update(belief, sim.observe(views[v]))
        actions = skill.sample(belief, SHELF, rng)
        assert actions
        predicted = model.predict(belief, actions[:1], WORKSPACE).beliefs[0]
        skill.execute(sim, actions[0], SimpleNamespace(shelf=SHELF))
        poses = sim.object_poses()
        gt, _ = voxelize([o for o in objs if o.id in poses], GRID, poses=poses)
        iou_pred = occupancy_iou(predicted.expected_occupancy() > 0.5, gt, inside)
        iou_same = occupancy_iou(belief.expected_occupancy() > 0.5, gt, inside)
        results.append((iou_pred, iou_same))
    print("post-push occupancy IoU (effect model, no change):", [(round(a, 4), round(b, 4)) for a, b in results])
    assert all(p > s for p, s in results)


# ------------------------------------------------------------------------------------------ episode
def test_push_only_episode_executes_a_push_and_records_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from msmem_core.config import load_config
    from msmem_core.run.runner import build_episode, run_episode

    monkeypatch.setenv("MSMEM_PLUGINS", "bonus=tests.support.manipulation_bonus")
    scene = SceneSpec(name="two", objects=(
        ObjectSpec(id=0, class_name="cracker_box", position_m=(-0.1, 0.08, 0.0)),
        ObjectSpec(id=1, class_name="tomato_soup_can", position_m=(-0.1, 0.25, 0.0)),
    ))
    over = {
        **ANALYTIC, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 4}, "steps": 3,
        "msas": {"manipulation_window": [1, 5]},
        "objective": [{"name": "ig"}, {"name": "semantic-entropy", "weight": 0.2},
                      {"name": "manipulation-bonus"}],
    }
    cfg = load_config("push-only", None, over)
    assert [s.name for s in cfg.skills] == ["view", "push"]
    ep = build_episode(cfg, get_plugin_manager(), scene=scene)
    final = run_episode(ep, tmp_path)
    steps = [json.loads(line) for line in (tmp_path / "steps.jsonl").read_text().splitlines()]
    assert [s["skill"] for s in steps] == ["view", "push", "view"]  # the push's associated view follows it
    rec = steps[1]
    assert rec["action"]["kind"] == "push"
    assert rec["candidates"]["push"] > 0
    assert set(rec["terms"]) == {"ig", "semantic-entropy", "manipulation-bonus"}
    assert rec["terms"]["semantic-entropy"] <= 0.0
    assert final["actions"] == {"view": 2, "push": 1}


@pytest.mark.slow  # an end-to-end run or a benchmark: the slow suite (CI) runs it
def test_perf_push_times_the_named_effect_model_and_matches_the_reference() -> None:
    from msmem_push.perf import perf_push

    lines: list[str] = []
    res = perf_push(repeats=1, samples=6, reference=True, report=lines.append, effect_model="push-analytic")
    assert res["candidates"] > 0
    assert any("predict (push-analytic)" in line for line in lines)
    assert res["max_rel_diff_exact_vs_reference"] < 1e-9
    assert res["total_s"] >= res["sample_s"] + res["predict_s"]


def _sweep_hits_reference(cells, u, steps, s, labels, wall):  # type: ignore[no-untyped-def]
    """The footprint sweep as plain array arithmetic over every step and cell (what the chain check did)."""
    moved = (cells[None, :, :] + 0.5) + steps[:, None, None] * u[None, None, :] / s
    ij = np.floor(moved).astype(np.int64)
    nx, ny = labels.shape
    inside = (ij[..., 0] >= 0) & (ij[..., 0] < nx) & (ij[..., 1] >= 0) & (ij[..., 1] < ny)
    hit = ~inside
    hit[inside] = wall[ij[inside][:, 0], ij[inside][:, 1]]
    rows = np.flatnonzero(hit.any(axis=1))
    at_wall = int(rows[0]) if len(rows) else -1
    lab = np.zeros(inside.shape, dtype=np.int64)
    lab[inside] = labels[ij[inside][:, 0], ij[inside][:, 1]]
    first = np.full(labels.max() + 1, -1)
    for j in range(1, labels.max() + 1):
        at = np.flatnonzero((lab == j).any(axis=1))
        if len(at) and (at_wall < 0 or at[0] <= at_wall):
            first[j] = at[0]
    return at_wall, first


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), angle=st.floats(0.0, 2 * np.pi), walls=st.booleans())
def test_the_compiled_footprint_sweep_equals_the_array_reference(seed: int, angle: float, walls: bool) -> None:
    """The chain check's kernel: the first wall step and each label's first step, exactly as array code."""
    rng = np.random.default_rng(seed)
    labels = np.zeros((30, 20), dtype=np.int32)
    for k in range(1, 5):  # four rectangles, some overlapping (the later label wins)
        i, j = rng.integers(0, 26), rng.integers(0, 16)
        labels[i:i + rng.integers(1, 5), j:j + rng.integers(1, 5)] = k
    wall = np.zeros_like(labels, dtype=bool)
    if walls:
        wall[:, 18:] = True
        wall[27:, :] = True
    cells = np.argwhere(labels == 1) if (labels == 1).any() else np.array([[10, 8]])
    u = np.array([np.cos(angle), np.sin(angle)])
    steps = np.arange(0.005, 0.27, 0.005)
    at_wall, first = footprint_sweep_hits(cells, u, steps, 0.01, labels, wall)
    ref_wall, ref_first = _sweep_hits_reference(cells, u, steps, 0.01, labels, wall)
    assert at_wall == ref_wall
    assert first.tolist() == ref_first.tolist()


# ------------------------------------------------------------------------------- forward pushes (an arm's)
def _forward_oracle(grid: GridSpec, tip: tuple[float, float, float], travel: tuple[float, float],
                    hand: tuple[float, ...], gripper: GripperSpec) -> NDArray[np.int64]:
    """The voxels of the forward tool swept by ``travel``, from the gripper's solids placed by its pose:
    fingers x in [-t, t], y in [-w/2, w/2], z in [-l, 0] and the hand behind them, in the gripper frame,
    moved into the world by ``gripper_pose(..., "forward")``; a voxel is in when its centre lies less than
    half a voxel from the swept box on every axis (the module's rasterisation rule)."""
    pose = gripper_pose(tip[:2], tip[2], (0.0, 1.0), "forward")
    fl, ft, fw = gripper.finger_length_m, gripper.finger_thickness_m, gripper.finger_width_m
    width, thick, depth, *wrist = hand
    solids = [((-ft, -fw / 2, -fl), (ft, fw / 2, 0.0)),
              ((-width / 2, -thick / 2, -fl - depth), (width / 2, thick / 2, -fl))]
    if wrist:  # behind the hand, on the approach axis
        ww, wl = wrist
        solids.append(((-ww / 2, -ww / 2, -fl - depth - wl), (ww / 2, ww / 2, -fl - depth)))
    c = grid.centers()
    s = grid.voxel_m
    inside = np.zeros(grid.shape, dtype=bool)
    for lo, hi in solids:
        corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        world = (pose @ corners.T).T[:, :3]
        wlo, whi = world.min(axis=0), world.max(axis=0)
        move = np.array([*travel, 0.0])  # along an axis: the swept solid is a box too
        wlo, whi = wlo + np.minimum(move, 0.0), whi + np.maximum(move, 0.0)
        inside |= np.all((c > wlo - s / 2 + 1e-9 * s) & (c < whi + s / 2 - 1e-9 * s), axis=-1)
    return np.flatnonzero(inside.ravel())


@pytest.mark.parametrize("hand", [None, (0.204, 0.063, 0.066), (0.204, 0.063, 0.066, 0.09, 0.1)])
@pytest.mark.parametrize("direction", [(0.0, 1.0), (1.0, 0.0), (-1.0, 0.0)])
def test_the_forward_tool_sweeps_the_fingers_and_the_hand_behind_them(
        hand: tuple[float, ...] | None, direction: tuple[float, float]) -> None:
    """Pointing into the shelf, the tool is the fingers ahead and the hand behind them, around the tip's
    height: its swept voxels, straight in or sideways, are those of the gripper's solids placed by the
    forward gripper pose and moved along the push."""
    g = GripperSpec()
    dims = hand or (g.palm_length_m, g.palm_width_m, g.palm_depth_m)
    a = PushAction(start_m=(0.035, 0.16), direction=direction, length_m=0.12, height_m=0.085, palm="forward",
                   hand_m=hand)
    got = a.swept_indices(WORKSPACE)
    travel = (0.12 * direction[0], 0.12 * direction[1])
    np.testing.assert_array_equal(got, _forward_oracle(GRID, (0.035, 0.16, 0.085), travel, dims, g))
    assert ("hand_m" in a.model_dump()) == (hand is not None), "the hand is recorded only when given"
    # the leading face on the tool's line is the fingertips' (straight in) or the fingers' side (sideways)
    lead = 0.0 if direction[1] else g.finger_thickness_m
    assert leading_half_depth(a.tool(g), 0.085, 0.2) == pytest.approx(lead)
    with pytest.raises(ValidationError, match="forward"):
        PushAction(start_m=(0.0, 0.1), direction=(0.6, 0.8), length_m=0.1, height_m=0.085, palm="forward")


def test_a_forward_tool_whose_hand_would_reach_the_floor_is_refused_naming_the_fields() -> None:
    with pytest.raises(ValidationError, match=r"min_tool_height_m\n.*0.01 puts the hand .* at least 0.0315"):
        PushConfig(palm="forward", hand_m=(0.204, 0.063, 0.066))
    with pytest.raises(ValidationError, match=r"at least 0.045"):
        PushConfig(palm="forward", hand_m=(0.204, 0.063, 0.066, 0.09, 0.1), min_tool_height_m=0.04)
    PushConfig(palm="forward", hand_m=(0.204, 0.063, 0.066), min_tool_height_m=0.0315)
    PushConfig(palm="forward")  # the floating gripper's 2 cm palm clears the floor at the 1 cm minimum
    PushConfig(min_tool_height_m=0.01, hand_m=(0.204, 0.063, 0.066))  # pointing down, the hand is above the tip


def test_forward_pushes_go_straight_in_and_keep_the_wide_hand_off_the_walls() -> None:
    """With ``palm: forward`` every candidate goes in or sideways and records the hand; a 20 cm hand is
    not proposed where it would sweep through a side wall (a box 3 cm from the right wall), a 2 cm one is."""
    x_hi = WORKSPACE.shelf.interior_box[3]
    b = _row_belief({3: ((-0.08, 0.04), (0.08, 0.06)), 5: ((x_hi - 0.07, 0.04), (x_hi - 0.03, 0.06))})
    c = GRID.centers()
    behind = (c[..., 0] > x_hi - 0.07) & (c[..., 1] > 0.06) & (c[..., 2] > 0)  # box 5 hides what is behind it
    b.alpha[behind], b.beta[behind], b.eta[:, behind] = 1.0, 1.0, 1.0
    cfg = {"palm": "forward", "tool_height_m": 0.085, "min_tool_height_m": 0.04}

    def pushes(hand: tuple[float, float, float]) -> list[PushAction]:
        skill = PushSkill(PushConfig(**cfg, hand_m=hand))  # type: ignore[arg-type]
        return [a for seed in range(6) for a in skill.propose(_ctx(b, seed=seed))]  # type: ignore[misc]

    wide, narrow = pushes((0.204, 0.063, 0.066)), pushes((0.02, 0.02, 0.03))
    assert wide
    assert narrow
    for a in wide + narrow:
        assert a.direction in {(0.0, 1.0), (1.0, 0.0), (-1.0, 0.0)}
        assert a.palm == "forward"
        assert a.hand_m is not None
        lo, hi = swept_extent(a.start, a.u, a.height_m, a.tool(WORKSPACE.gripper), a.length_m * a.u)
        assert lo[2] >= 0.0, "the hand drags on the shelf floor"
    assert 5 in {a.target_class for a in narrow}
    assert 5 not in {a.target_class for a in wide}, "the 20 cm hand would sweep through the right wall"
    for a in wide:
        lo, hi = swept_extent(a.start, a.u, a.height_m, a.tool(WORKSPACE.gripper), a.length_m * a.u)
        assert WORKSPACE.shelf.interior_box[0] <= lo[0]
        assert hi[0] <= x_hi


def test_a_forward_push_moves_the_box_in_as_the_effect_model_predicts(sim) -> None:  # type: ignore[no-untyped-def]
    """The floating gripper pointing into the shelf pushes a box 12 cm deeper in PyBullet, and the analytic
    effect model moves its believed voxels by as much (within 1.5 cm)."""
    from msmem_analytic.observation import AnalyticObservationModel

    views = generate_viewpoints(ViewpointConfig(), SHELF)
    obj = ObjectSpec(id=0, class_name="cracker_box", position_m=(0.0, 0.08, 0.0),
                     quat_xyzw=tuple(float(q) for q in yaw_quat(np.pi / 2)))
    sim.reset(SceneSpec(objects=(obj,)))
    belief = EvidentialMap.empty(GRID)
    for v in (150, 155, 160):
        belief = AnalyticObservationModel().update(belief, sim.observe(views[v]))
    skill = PushSkill(PushConfig(palm="forward", tool_height_m=0.06, min_tool_height_m=0.04))
    before = np.asarray(sim.object_poses()[0][:3, 3])
    gt, _ = voxelize([obj], GRID)
    front_y = float(GRID.centers()[gt][:, 1].min() - GRID.voxel_m / 2)
    a = PushAction(start_m=(0.0, front_y - 0.01), direction=(0.0, 1.0), length_m=0.13, height_m=0.06,
                   palm="forward", target_class=1, contact_m=(0.0, front_y, 0.06))
    skill.execute(sim, a, SimpleNamespace(shelf=SHELF))
    moved = np.asarray(sim.object_poses()[0][:3, 3]) - before
    assert 0.10 < moved[1] < 0.14
    assert abs(moved[0]) < 0.02
    assert abs(moved[2]) < 0.01
    predicted = AnalyticPushEffect().predict(belief, [a], WORKSPACE).beliefs[0]
    inside = interior_mask(SHELF, GRID)
    ys = [float(GRID.centers()[(m.expected_occupancy() > 0.5) & inside][:, 1].mean()) for m in (belief, predicted)]
    assert abs((ys[1] - ys[0]) - moved[1]) < 0.015


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(["along", "across", "forward"]), st.floats(-0.4, 0.4), st.floats(-0.3, 0.5),
       st.floats(-np.pi, np.pi))
def test_the_tools_corner_extent_is_that_of_its_corner_arrays(palm: str, x: float, y: float, ang: float) -> None:
    # the sampler's room along u reads this extent: it must be the arrays' values to the last bit
    u = np.array([np.cos(ang), np.sin(ang)])
    boxes = tool_boxes(GripperSpec(), palm, (0.204, 0.063, 0.066) if palm == "forward" else None, u)
    corners = np.concatenate([box_corners(np.array([x, y]), u, b) for b in boxes])
    want = (corners[:, 0].min(), corners[:, 0].max(), corners[:, 1].min(), corners[:, 1].max())
    assert corners_extent(np.array([x, y]), u, boxes) == tuple(float(v) for v in want)


def test_the_chain_room_kernel_is_the_python_rule() -> None:
    """``geometry.chain_room`` (what proposals use) returns what ``_chain_room_reference`` does, float for
    float, at every call of proposals on random shelves, with and without the fall rules, a chain's
    travel limit and the trip rule, with its cap and without."""
    calls = 0

    class Both(PushSkill):
        def _chain_room(self, t, u, grid, chain, cap=np.inf, floor_z=0.0):  # type: ignore[no-untyped-def]
            nonlocal calls
            fast = super()._chain_room(t, u, grid, chain, cap, floor_z)
            for c in (cap, np.inf):
                assert super()._chain_room(t, u, grid, chain, c, floor_z) == self._chain_room_reference(
                    t, u, grid, chain, c, floor_z), (t.key, u, c)
            calls += 1
            return fast

    configs = [PushConfig(), PushConfig(chain_travel_m=0.03), PushConfig(trip_height_ratio=2.0, max_height_ratio=4.0),
               PushConfig(trip_height_ratio=None, max_pushes_per_object=None, chain_clearance_m=0.0)]
    for seed in range(6):
        belief = synthetic_belief(seed)
        for cfg in configs:
            Both(cfg).propose(_ctx(belief, seed=seed))
    assert calls > 300


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_where_a_push_line_last_crosses_the_footprint_is_the_array_rule(seed: int) -> None:
    """``geometry.last_on_footprint`` (what ``_candidate`` uses) is the numpy rule it replaces: the
    last of the points ``q - ts * u`` whose cell ``floor(((q - ts * u) - o) / s)`` is in the footprint."""
    from msmem_push.geometry import last_on_footprint

    rng = np.random.default_rng(seed)
    s = 0.01
    foot = rng.random((30, 20)) < 0.05
    foot[rng.integers(0, 30), :] = True
    ts = np.arange(0.0, 0.6, s / 8)
    o = np.array([-0.15, -0.1])
    for _ in range(50):
        q = o + rng.uniform(-0.05, 0.35, 2)
        if rng.random() < 0.5:  # on cell boundaries, where the order of the arithmetic decides the cell
            q = o + rng.integers(0, 25, 2) * s
        a = rng.uniform(0, 2 * np.pi)
        u = np.array([np.cos(a), np.sin(a)])
        if rng.random() < 0.3:
            u = np.round(u)
        ij = np.floor(((q[None, :] - ts[:, None] * u[None, :]) - o) / s).astype(np.int64)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < 30) & (ij[:, 1] >= 0) & (ij[:, 1] < 20)
        inside = np.zeros(len(ts), dtype=bool)
        inside[ok] = foot[ij[ok, 0], ij[ok, 1]]
        want = int(np.flatnonzero(inside).max()) if inside.any() else -1
        assert last_on_footprint(q[0], q[1], u[0], u[1], ts, o[0], o[1], s, foot) == want

"""The grasp skill (UGS: FE-UMGF buffer, executable grasps, execution), its analytic effect model
(sigma_g) and the grasp-only method; the batched collision tests against the per-grasp loop they
replaced (kept here as a reference)."""

from __future__ import annotations

import dataclasses
import logging
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from msmem_grasp.effect import AnalyticGraspEffect, GraspEffectConfig
from msmem_grasp.planning import (
    Objects,
    blocked_mask,
    fill_down,
    gripper_boxes,
    gripper_points,
    gripper_points_batch,
    path_offsets,
    sweep_hits,
    swept_indices,
    swept_indices_reference,
)
from msmem_grasp.skill import GraspAction, GraspConfig, GraspSkill
from pydantic import ValidationError

from msmem_core.errors import PluginError
from msmem_core.interfaces import CandidateBatch, DecisionContext, Workspace
from msmem_core.map.belief import DeltaBeliefs, EvidentialMap
from msmem_core.map.ig import IGService
from msmem_core.msas import execute_measured
from msmem_core.plugins import get_plugin_manager
from msmem_core.plugins.manager import ComponentRef
from msmem_core.run.metrics import occupancy_iou, position_change_m
from msmem_core.testing.conformance import gripper_pose
from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import yaw_quat
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.scene import ObjectSpec, SceneSpec, ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, default_start_view, generate_viewpoints
from msmem_core.world.voxelize import interior_mask, voxelize

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SHELF = ShelfSpec()
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.01)
INTERIOR = SHELF.interior_box
WORKSPACE = Workspace(GRID, SHELF, GripperSpec())
SUGAR, MEAT, FOAM, CRACKER = 2, 9, 13, 1  # class ids
PANDA_HAND = (0.204, 0.063, 0.066, 0.09, 0.1)
"""The Panda hand (width along the closing axis, thickness, depth) and its wrist (width, length)."""
PANDA_GRASPS = {"hand_m": PANDA_HAND, "max_approach_deg": 30.0, "min_height_m": 0.045, "roll": "both",
                "predictor": "geometric", "geometric": {"approach": "front-first"}}


# ------------------------------------------------------------------------------------------ helpers
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


def ctx(belief: EvidentialMap, step: int = 5, allowed: bool = True, ig: IGService | None = None) -> DecisionContext:
    return DecisionContext(step, belief, ig, np.zeros((0, 4, 4)), set(), WORKSPACE,  # type: ignore[arg-type]
                           np.random.default_rng(0), allowed, 0.5)


def top_grasp(x: float, y: float, z: float, width: float, lift: float = 0.03, cls: int | None = SUGAR,
              closing: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> GraspAction:
    """A top-down grasp centred at (x, y, z) closing along ``closing``, approached from the front above."""
    pose = gripper_pose((x, y, z), (0, 0, -1), closing)
    b = np.asarray(closing)
    contact = np.array([x, y, z]) - width / 2 * b
    pre = np.array([x, y, z + 0.05])
    lifted = np.array([x, y, z + lift])
    return GraspAction(
        pose=tuple(tuple(float(v) for v in row) for row in pose), width_m=width, opening_m=min(width + 0.02, 0.08),
        contact_m=tuple(float(v) for v in contact), target_class=cls,  # type: ignore[arg-type]
        approach_m=((x, -0.12, z + 0.05), tuple(float(v) for v in pre)),  # type: ignore[arg-type]
        retreat_m=(tuple(float(v) for v in lifted), (x, -0.3, float(lifted[2]))),  # type: ignore[arg-type]
    )

# target sugar-box-like block behind a lower block touching its front, and a bystander far to the side
TARGET = ((-0.02, 0.18), (0.02, 0.27), 0.17, SUGAR)
IN_THE_WAY = ((-0.05, 0.12), (0.05, 0.18), 0.08, MEAT)
BYSTANDER = ((0.20, 0.10), (0.36, 0.16), 0.21, CRACKER)


# ------------------------------------------------------------------------------- registration, config
def test_grasp_skill_and_its_effect_model_are_registered_and_bound() -> None:
    pm = get_plugin_manager()
    assert pm.skills()["grasp"].effect_model == "cnabu-grasp"  # the better held-out NLL (test_cnabu_shipped)
    assert "effect" in pm.belief_models()["cnabu-grasp"].roles
    assert "effect" in pm.belief_models()["grasp-analytic"].roles
    skill = pm.build("skill", ComponentRef(name="grasp", params={"top_k": 5}), gripper=GripperSpec(max_opening_m=0.07))
    assert isinstance(skill, GraspSkill)
    assert skill.config.top_k == 5
    assert skill.config.gripper.max_opening_m == 0.07  # the run's gripper fills the unset field
    with pytest.raises(PluginError, match=r"skills\.1\.params\.top_k"):
        pm.build("skill", ComponentRef(name="grasp", params={"top_k": 0}), where="skills.1")
    with pytest.raises(PluginError, match=r"decay"):
        pm.build("skill", ComponentRef(name="grasp", params={"fusion": {"decay": 1.5}}))


def test_grasp_actions_are_json_and_reject_a_non_rigid_pose() -> None:
    a = top_grasp(0.0, 0.2, 0.14, 0.04)
    assert GraspAction.model_validate_json(a.model_dump_json()) == a
    assert "hand_m" not in a.model_dump()  # records without a hand are as before
    handed = a.model_copy(update={"hand_m": PANDA_HAND})
    assert GraspAction.model_validate_json(handed.model_dump_json()) == handed
    assert (a.kind, a.category) == ("grasp", "manipulation")
    bad = [list(r) for r in a.pose]
    bad[0][0] = 2.0
    with pytest.raises(ValidationError, match="rigid"):
        GraspAction.model_validate({**a.model_dump(), "pose": bad})
    with pytest.raises(ValidationError, match="width_m"):
        GraspAction.model_validate({**a.model_dump(), "width_m": -0.01})


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_swept_indices_kernel_equals_the_numpy_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pts = gripper_points(GripperSpec(), 0.06, 0.005)
    # a path partly outside the grid on every side: those points are dropped by both
    path = path_offsets(rng.uniform(GRID.origin - 0.1, GRID.upper_m + 0.1, size=(4, 3)), 0.005)
    got = swept_indices(GRID, q, pts, path)
    assert len(got) > 0
    np.testing.assert_array_equal(got, swept_indices_reference(GRID, q, pts, path))


def test_the_swept_volume_follows_the_approach_the_lift_and_the_retreat() -> None:
    a = top_grasp(0.0, 0.2, 0.14, 0.04)
    vol = a.swept_volume(WORKSPACE)
    ijk = GRID.index_of
    c = GRID.centers()
    for p in ([0.0, 0.2, 0.205], [0.0, 0.1, 0.255], [0.0, 0.0, 0.235], [0.025, 0.0, 0.2]):  # palm, fingers
        i, j, k = ijk(np.array([p]))[0]
        assert vol[i, j, k], p
    between = (np.abs(c[..., 0]) < 0.01) & (np.abs(c[..., 1] - 0.2) < 0.005) & (c[..., 2] < 0.13)
    assert not vol[between].any()  # the object's place between the fingers is not the gripper's
    assert not vol[c[..., 0] > 0.1].any()
    # the closed gripper in the retreat is narrower than the open one in the approach
    assert vol.sum() == len(a.swept_indices(WORKSPACE))


# ------------------------------------------------------------------- reference: the per-grasp loop
class _ReferenceGraspSkill(GraspSkill):
    """``GraspSkill.executable`` as it was before the batched collision tests: per candidate, its
    region and gripper points, then one numpy test per path (``_hits``)."""

    def executable(self, belief: EvidentialMap, shelf: ShelfSpec) -> list[GraspAction]:
        cfg = self.config
        c = self.candidates(belief, shelf)
        if c is None:
            return []
        grid = belief.grid
        out: list[GraspAction] = []
        per_object: dict[int, int] = {}
        for i in self.test_order(c, np.arange(len(c.grasps))):  # the order is the skill's (twins)
            lab = int(c.label[i])
            if lab <= 0 or per_object.get(lab, 0) >= cfg.max_per_object:
                continue
            pose = c.poses[i]
            region = c.objects.region(grid, lab, pose, c.opening[i], cfg.max_object_radius_m)
            approach = self._plan_approach_reference(grid, c.blocked, region, pose, float(c.opening[i]))
            if approach is None:
                continue
            lift_m = self._lift(grid, c.p, c.objects, lab, region, pose, float(c.width[i]), c.top)
            if lift_m is None:
                continue
            out.append(self.action(c, i, approach, lift_m, shelf))
            per_object[lab] = per_object.get(lab, 0) + 1
            if len(out) >= cfg.top_k:
                break
        return out

    def _plan_approach_reference(self, grid: GridSpec, blocked: np.ndarray, region: np.ndarray, pose: np.ndarray,
                                 opening: float) -> np.ndarray | None:
        cfg = self.config
        s = grid.voxel_m
        pts = gripper_points(cfg.gripper, opening, s / 2, cfg.tolerance_m, cfg.hand_m)
        # the way in: the boxes grown by move_in_clearance_m (None: shrunk as everywhere else)
        pts_in = pts if cfg.move_in_clearance_m is None else gripper_points(
            cfg.gripper, opening, s / 2, -cfg.move_in_clearance_m, cfg.hand_m)
        r = pose[:3, :3]
        grasp = pose[:3, 3]
        if _hits_reference(grid, blocked, region, r, pts, path_offsets(grasp[None], s)):
            return None
        for d in cfg.approach_distances_m:
            pre = grasp - d * pose[:3, 2]
            outside = pre.copy()
            outside[1] = min(cfg.outside_y_m, pre[1])
            if _hits_reference(grid, blocked, None, r, pts_in, path_offsets(np.stack([outside, pre]), s / 2)):
                continue
            if _hits_reference(grid, blocked, region, r, pts, path_offsets(np.stack([pre, grasp]), s / 2)):
                continue
            return np.stack([outside, pre])
        return None


def _hits_reference(grid: GridSpec, blocked: np.ndarray, region: np.ndarray | None, rotation: np.ndarray,
                    pts: np.ndarray, path: np.ndarray) -> bool:
    world = (path[:, None, :] + (pts @ rotation.T)[None]).reshape(-1, 3)
    ijk = grid.index_of(world)
    inside = grid.contains_index(ijk)
    if (~inside & (ijk[:, 1] >= 0)).any():
        return True
    ii = ijk[inside]
    hit = np.unique((ii[:, 0] * grid.shape[1] + ii[:, 1]) * grid.shape[2] + ii[:, 2])
    hit = hit[blocked[hit]]
    if region is not None and len(region):
        hit = np.setdiff1d(hit, region, assume_unique=True)
    return len(hit) > 0


def _seeded_belief(seed: int) -> EvidentialMap:
    """Random boxes of random classes, some unseen space behind them and noisy evidence."""
    rng = np.random.default_rng(seed)
    boxes = []
    for _ in range(int(rng.integers(3, 7))):
        x0, y0 = rng.uniform(-0.35, 0.3), rng.uniform(0.03, 0.3)
        w, d = rng.uniform(0.03, 0.12), rng.uniform(0.03, 0.1)
        boxes.append(((x0, y0), (x0 + w, y0 + d), float(rng.uniform(0.05, 0.22)), int(rng.choice([SUGAR, MEAT, FOAM,
                                                                                                    CRACKER]))))
    b = box_belief(boxes)
    c = GRID.centers()
    hidden = (c[..., 1] > 0.3) & (c[..., 0] > rng.uniform(-0.3, 0.3)) & ~(b.expected_occupancy() > 0.5)
    b.alpha[hidden], b.beta[hidden], b.eta[:, hidden] = 1.0, 1.0, 1.0
    b.alpha += rng.uniform(0.0, 0.5, b.alpha.shape).astype(np.float32)
    return b


# seed 0 in the fast suite; seeds 1 (with the hand) and 2 (with the twins' other orders) in the slow one
@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_batched_collision_tests_equal_the_per_grasp_loop(seed: int) -> None:
    belief = _seeded_belief(seed)
    found = []
    proposed: list[list[GraspAction]] = []
    every = {"top_k": 300, "max_per_object": 300, "turn_to": ()}  # every candidate: the twins only in the first
    others = {0: [], 1: [{**every, "hand_m": PANDA_HAND}],
              2: [{"twins": "first"}, {"twins": "last"}, {"move_in_clearance_m": None},
                  {"move_in_clearance_m": 0.01}]}[seed]
    for params in ({}, every, *others):
        cfg = GraspConfig(predictor="geometric", seed=seed, **params)  # type: ignore[arg-type]
        skill, reference = GraspSkill(cfg), _ReferenceGraspSkill(cfg)
        skill.track(ctx(belief))
        reference.buffer = skill.buffer
        got, want = skill.executable(belief, SHELF), reference.executable(belief, SHELF)
        assert [g.model_dump() for g in got] == [g.model_dump() for g in want]  # same grasps, order, poses, paths
        found.append(len(got))
        if params:
            assert len(got) > 4
        if "twins" in params:
            assert got != proposed[0]  # the order changes what is proposed
        if "hand_m" in params:
            assert len(got) < found[1]  # the 20 cm hand fits fewer places than the palm
        proposed.append(got)

    # every candidate's test at the grasp and on its way in, one at a time against the kernel
    cfg = GraspConfig(predictor="geometric")
    skill = GraspSkill(cfg)
    skill.track(ctx(belief))
    h = skill.buffer.hypotheses()
    a, _ = h.approach()
    from msmem_grasp.fevmf import executable_grasp

    opening = np.minimum(np.minimum(h.width, 0.08) + cfg.opening_margin_m, 0.08)
    poses = executable_grasp(h.contact, a, h.mu_b, np.minimum(h.width, 0.08))
    objects = Objects.of(belief, INTERIOR)
    label = objects.label_at(GRID, h.contact + 0.005 * h.mu_b)
    blocked = blocked_mask(belief, SHELF).ravel()
    pts = gripper_points_batch(cfg.gripper, opening, 0.005, cfg.tolerance_m)
    local = np.stack([pts[i] @ poses[i, :3, :3].T for i in range(len(h))])
    grasp, pre = poses[:, :3, 3], poses[:, :3, 3] - 0.05 * poses[:, :3, 2]
    paths = [grasp[i][None] if i % 2 else path_offsets(np.stack([pre[i], grasp[i]]), 0.005) for i in range(len(h))]
    ptr = np.cumsum([0] + [len(q) for q in paths])
    got = sweep_hits(GRID, blocked, objects.labels, local, np.concatenate(paths), ptr, np.arange(len(h)), label, poses,
                     opening, cfg.max_object_radius_m)
    want = []
    for i in range(len(h)):
        np.testing.assert_array_equal(pts[i], gripper_points(cfg.gripper, float(opening[i]), 0.005, cfg.tolerance_m))
        region = objects.region(GRID, int(label[i]), poses[i], opening[i], cfg.max_object_radius_m)
        want.append(_hits_reference(GRID, blocked, region, poses[i, :3, :3], pts[i], paths[i]))
    assert len(h) > 100
    assert 0 < sum(want) < len(want)
    np.testing.assert_array_equal(got, want)


# ----------------------------------------------------------------------------------------- proposal
def test_executable_grasps_come_from_the_belief_are_reachable_and_collision_free(caplog, tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    belief = box_belief([TARGET, BYSTANDER])
    monkeypatch.setattr("msmem_grasp.weights.SHIPPED_WEIGHTS", tmp_path / "missing.pt")  # none installed
    skill = GraspSkill(GraspConfig())  # auto, none named, none installed: the fallback
    with caplog.at_level(logging.WARNING, logger="msmem.grasp"):
        grasps = skill.propose(ctx(belief))
    assert "geometric fallback" in caplog.text  # no weights: the fallback is announced
    assert grasps
    assert all(isinstance(g, GraspAction) and g.predictor == "geometric" for g in grasps)
    assert {g.target_class for g in grasps} <= {SUGAR, CRACKER}
    assert SUGAR in {g.target_class for g in grasps}
    assert len(grasps) <= skill.config.top_k
    assert all(sum(g.target_class == k for g in grasps) <= skill.config.max_per_object for k in (SUGAR, CRACKER))
    occupied = belief.expected_occupancy().reshape(-1) > 0.5
    objects = Objects.of(belief, INTERIOR)
    for g in grasps:
        m = g.matrix
        a = m[:3, 2]
        assert a[1] >= -math.sin(math.radians(15))
        assert a[2] <= math.sin(math.radians(15))
        assert g.affordance >= 0.5
        assert g.uncertainty <= 0.5
        assert g.approach_m[0][1] < 0.0  # the approach starts outside the shelf
        # the gripper on its way in touches no believed object, except the target near the end
        pts = gripper_points(skill.config.gripper, g.opening_m, 0.005, skill.config.tolerance_m)
        inbound = swept_indices(GRID, m[:3, :3], pts, path_offsets(np.array(g.approach_m), 0.005))
        assert not occupied[inbound].any()
        final = swept_indices(GRID, m[:3, :3], pts, path_offsets(np.array([g.approach_m[-1], m[:3, 3]]), 0.005))
        label = objects.label_at(GRID, np.array([g.contact_m]) + 0.005 * m[:3, 0])[0]
        assert np.all(objects.labels.reshape(-1)[final[occupied[final]]] == label)
        assert 0.0 < g.width_m <= g.opening_m <= 0.08


def test_with_fe_vmf_weights_the_skill_fuses_the_network_outputs(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import json

    from msmem_grasp.fevmf import FEVMF
    from msmem_grasp.learn.training import WEIGHTS_FORMAT, default_model_config, sha256_file, sidecar_path
    from msmem_grasp.weights import WeightsError

    torch.manual_seed(0)
    model = FEVMF(default_model_config())  # untrained: the code path, not the quality
    path = tmp_path / "w.pt"
    torch.save(model.state_dict(), path)
    sidecar_path(path).write_text(json.dumps({"format": WEIGHTS_FORMAT, "sha256": sha256_file(path),
                                              "model": model.config.model_dump()}))
    skill = GraspSkill(GraspConfig(predictor="fe-vmf", weights=path, num_points=512))
    belief = box_belief([TARGET, BYSTANDER])
    grasps = skill.propose(ctx(belief))
    assert skill.predictor == "fe-vmf:w.pt"
    assert 0 < len(skill.buffer) <= 512
    assert all(g.predictor == "fe-vmf:w.pt" for g in grasps)
    with pytest.raises(WeightsError, match="does not exist"):
        _ = GraspSkill(GraspConfig(predictor="fe-vmf", weights=tmp_path / "missing.pt")).predictor


def test_no_grasps_outside_the_window_or_into_unknown_space() -> None:
    belief = box_belief([TARGET])
    assert GraspSkill(GraspConfig(predictor="geometric")).propose(ctx(belief, allowed=False)) == []
    hidden = belief.copy()
    c = GRID.centers()
    behind = (c[..., 1] > 0.18) & (np.abs(c[..., 0]) < 0.15) & ~(belief.expected_occupancy() > 0.5)
    hidden.beta[behind], hidden.eta[:, behind] = 1.0, 1.0  # never seen around and behind the box
    assert GraspSkill(GraspConfig(predictor="geometric")).propose(ctx(hidden)) == []
    assert GraspSkill(GraspConfig(predictor="geometric")).propose(ctx(EvidentialMap.empty(GRID))) == []


def test_the_buffer_is_updated_every_step_and_cleared_for_a_new_episode() -> None:
    belief = box_belief([TARGET])
    skill = GraspSkill(GraspConfig(predictor="geometric", fusion={"decay": 1.0}))
    skill.track(ctx(belief, step=0, allowed=False))
    n0, s0 = len(skill.buffer), float((skill.buffer.alpha + skill.buffer.beta).sum())
    skill.track(ctx(belief, step=0, allowed=False))  # same step, same belief: no second update
    assert float((skill.buffer.alpha + skill.buffer.beta).sum()) == s0
    skill.propose(ctx(belief, step=1, allowed=False))  # not allowed to act, the buffer still fuses
    assert len(skill.buffer) >= n0
    assert float((skill.buffer.alpha + skill.buffer.beta).sum()) > 1.5 * s0
    skill.track(ctx(belief, step=0))  # a new episode
    assert float((skill.buffer.alpha + skill.buffer.beta).sum()) == pytest.approx(s0)


def test_after_a_manipulation_the_buffer_restarts_from_views_taken_since() -> None:
    from msmem_grasp.fpp import virtual_front_views

    belief = box_belief([TARGET])
    skill = GraspSkill(GraspConfig(predictor="geometric", fusion={"decay": 1.0}))
    views = virtual_front_views()

    def at(step: int, visited: set[int], manipulated: int) -> DecisionContext:
        c = ctx(belief, step=step)
        c.viewpoints, c.visited, c.last_manipulation = views, visited, manipulated
        return c

    skill.track(at(0, set(), -1))  # before any manipulation the virtual front cameras see the belief
    before = len(skill.buffer)
    assert before > 0
    skill.track(at(4, set(), 3))  # a push at step 3, no view since: the belief is a prediction
    assert len(skill.buffer) == 0
    assert skill.propose(at(4, set(), 3)) == []
    skill.track(at(5, {0}, 3))  # the associated view was taken: grasps come back from what it saw
    assert 0 < len(skill.buffer)
    fused = float((skill.buffer.alpha + skill.buffer.beta).sum())
    skill.track(at(6, {0}, 3))  # no new manipulation: the buffer keeps fusing
    assert float((skill.buffer.alpha + skill.buffer.beta).sum()) > fused


def test_with_confirm_a_manipulation_keeps_the_grasps_its_following_view_confirms() -> None:
    from msmem_grasp.fpp import virtual_front_views

    belief = box_belief([TARGET])
    moved = box_belief([((-0.15, 0.18), (-0.11, 0.27), 0.14, SUGAR)])  # the object is elsewhere now
    skill = GraspSkill(GraspConfig(predictor="geometric", fusion={"decay": 1.0}, after_manipulation="confirm"))
    views = virtual_front_views()

    def at(b: EvidentialMap, step: int, visited: set[int], manipulated: int) -> DecisionContext:
        c = ctx(b, step=step)
        c.viewpoints, c.visited, c.last_manipulation = views, visited, manipulated
        return c

    skill.track(at(belief, 0, set(), -1))
    before = skill.buffer.state()
    assert len(before["alpha"]) > 0
    skill.track(at(belief, 4, set(), 3))  # a manipulation, no view yet: the buffer waits, kept whole
    assert len(skill.buffer) == len(before["alpha"])
    skill.track(at(belief, 5, {0, 1, 2}, 3))  # the views see the object where it was: grasps confirmed
    assert np.all(skill.buffer.hits[: len(before["alpha"])] >= 1)
    assert (skill.buffer.hits >= 2).sum() > 0.5 * len(before["alpha"])
    skill.track(at(moved, 7, {0, 1, 2}, 6))  # another manipulation moved it: the old grasps go
    skill.track(at(moved, 8, {0, 1, 2}, 6))
    kept = skill.buffer.contact
    assert len(kept) > 0
    assert np.all(kept[:, 0] < -0.09), "only grasps on the object's new place remain"


def test_the_lift_rises_over_a_low_object_in_the_way_when_the_shelf_leaves_room() -> None:
    low = ((-0.05, 0.12), (0.05, 0.18), 0.04, MEAT)
    short_target = ((-0.02, 0.18), (0.02, 0.27), 0.10, SUGAR)
    grasps = GraspSkill(GraspConfig(predictor="geometric")).propose(ctx(box_belief([short_target, low])))
    top_down = [g for g in grasps if g.target_class == SUGAR and g.matrix[2, 2] < -0.9]
    assert top_down
    for g in top_down:  # lifted over the 4 cm block: the object's bottom clears it
        assert g.retreat_m[0][2] - g.pose[2][3] >= 0.05 - 1e-9


def test_a_grasp_whose_object_cannot_leave_past_a_neighbour_is_skipped_unless_asked() -> None:
    target = ((-0.02, 0.18), (0.02, 0.27), 0.10, SUGAR)
    blocker = ((-0.05, 0.10), (0.05, 0.16), 0.07, MEAT)  # in front: lower than the approach, above max_lift_m

    def on_target(belief: EvidentialMap, **kw: object) -> list[GraspAction]:
        skill = GraspSkill(GraspConfig(predictor="geometric", max_lift_m=0.05, **kw))  # type: ignore[arg-type]
        return [g for g in skill.propose(ctx(belief)) if g.target_class == SUGAR]

    dragging = on_target(box_belief([target, blocker]), blocked_exit="lift_m")
    assert dragging  # lift_m proposes them at the minimum lift: the object drags the block out
    assert all(abs(g.retreat_m[0][2] - g.pose[2][3] - 0.03) < 1e-9 for g in dragging)
    assert on_target(box_belief([target, blocker])) == []  # the default (skip) does not
    low = ((-0.05, 0.10), (0.05, 0.16), 0.03, MEAT)  # one it can be lifted over: still proposed
    assert on_target(box_belief([target, low]))


# ---------------------------------------------------------------------------- an arm's hand (Panda)
def test_the_hand_and_wrist_replace_the_palm_in_the_gripper_points() -> None:
    grip = GripperSpec()
    palm = gripper_points(grip, 0.06, 0.005)
    hand = gripper_points(grip, 0.06, 0.005, hand_m=PANDA_HAND)
    fingers = hand[hand[:, 2] > -grip.finger_length_m + 1e-9]  # (the palm's and the hand's faces are at -length)
    np.testing.assert_array_equal(fingers, palm[palm[:, 2] > -grip.finger_length_m + 1e-9])  # the same fingers
    fl = grip.finger_length_m
    (_, h_half), (w_centre, w_half) = gripper_boxes(grip, 0.06, PANDA_HAND)[2:]
    np.testing.assert_allclose(2 * h_half, (0.204, 0.063, 0.066))  # width, thickness, depth
    np.testing.assert_allclose(w_centre, (0.0, 0.0, -fl - 0.066 - 0.05))  # the wrist right behind the hand
    np.testing.assert_allclose(2 * w_half, (0.09, 0.09, 0.1))
    np.testing.assert_allclose(hand.min(axis=0), (-0.102, -0.045, -fl - 0.166))  # the points fill them
    np.testing.assert_allclose(hand.max(axis=0), (0.102, 0.045, 0.0))
    openings = np.array([0.02, 0.05, 0.08])
    batch = gripper_points_batch(grip, openings, 0.005, 0.003, PANDA_HAND)
    for i, o in enumerate(openings):
        np.testing.assert_array_equal(batch[i], gripper_points(grip, float(o), 0.005, 0.003, PANDA_HAND))


FRONT_TARGET = ((-0.02, 0.14), (0.02, 0.20), 0.12, SUGAR)
"""A 4 cm wide, 12 cm tall box 14 cm deep in the shelf."""
NEIGHBOURS = [((-0.16, 0.04), (-0.07, 0.10), 0.12, MEAT), ((0.07, 0.04), (0.16, 0.10), 0.12, CRACKER)]
"""Two boxes in front of it, 5 cm to either side of it: room for the fingers and a palm, not a 20 cm hand."""


def test_grasps_from_the_front_keep_to_the_cone_the_height_and_turn_both_ways() -> None:
    grasps = GraspSkill(GraspConfig(**PANDA_GRASPS)).propose(ctx(box_belief([FRONT_TARGET])))  # type: ignore[arg-type]
    assert len(grasps) >= 2
    assert {g.target_class for g in grasps} == {SUGAR}
    for g in grasps:
        m = g.matrix
        assert m[1, 2] >= math.cos(math.radians(30)) - 1e-9  # approach within 30 deg of +y
        assert m[2, 3] >= 0.045
        assert g.hand_m == PANDA_HAND
    pairs = list(zip(grasps[::2], grasps[1::2], strict=True))  # each grasp, then the same one turned
    for g, t in pairs:
        np.testing.assert_allclose(t.matrix[:3, 2:], g.matrix[:3, 2:])  # same approach and centre
        np.testing.assert_allclose(t.matrix[:3, :2], -g.matrix[:3, :2])  # closing axis and y reversed
    up = GraspSkill(GraspConfig(**{**PANDA_GRASPS, "roll": "back-up"})).propose(ctx(box_belief([FRONT_TARGET])))  # type: ignore[arg-type]
    assert up
    assert all(g.matrix[2, 1] >= 0.0 for g in up)
    assert {round(g.pose[2][3], 6) for g in grasps} <= {round(g.pose[2][3], 6) for g in up}  # the same grasps
    # a 16 cm deep box: front-first still grasps its back part from above (with a palm: the hand and wrist
    # pointing down do not fit under the shelf top), unless the cone forbids it
    deep = box_belief([((-0.02, 0.10), (0.02, 0.26), 0.12, SUGAR)])
    palm = {**PANDA_GRASPS, "hand_m": None, "top_k": 300, "max_per_object": 300}
    wide = GraspSkill(GraspConfig(**{**palm, "max_approach_deg": 180.0})).propose(ctx(deep))  # type: ignore[arg-type]
    assert any(g.matrix[2, 2] < -0.9 for g in wide)
    assert not any(g.matrix[2, 2] < -0.9 for g in GraspSkill(GraspConfig(**{**PANDA_GRASPS, "max_approach_deg": 180.0})
                                                              ).propose(ctx(deep)))  # type: ignore[arg-type]
    coned = GraspSkill(GraspConfig(**palm)).propose(ctx(deep))  # type: ignore[arg-type]
    assert coned
    assert all(g.matrix[1, 2] >= math.cos(math.radians(30)) - 1e-9 for g in coned)
    # without the cone, the default predictor grasps this box from above
    top = GraspSkill(GraspConfig(predictor="geometric")).propose(ctx(box_belief([FRONT_TARGET])))
    assert any(g.matrix[2, 2] < -0.9 for g in top)


def test_the_hand_keeps_the_grasp_away_from_neighbours_the_palm_passes() -> None:
    belief = box_belief([FRONT_TARGET, *NEIGHBOURS])

    def on_target(**kw: object) -> list[GraspAction]:
        cfg = GraspConfig(**{**PANDA_GRASPS, **kw})  # type: ignore[arg-type]
        return [g for g in GraspSkill(cfg).propose(ctx(belief)) if g.target_class == SUGAR]

    assert on_target(hand_m=None)  # fingers and palm pass between the neighbours
    assert on_target() == []  # the 20 cm hand does not
    assert on_target(hand_m=None, min_height_m=0.2) == []  # nothing on a 12 cm box is 20 cm up
    g = on_target(hand_m=None)[0]
    ws = Workspace(GRID, SHELF, GripperSpec())
    swept = g.model_copy(update={"hand_m": PANDA_HAND}).swept_volume(ws)
    neighbours = box_belief(NEIGHBOURS).expected_occupancy() > 0.5
    assert not (g.swept_volume(ws) & neighbours).any()
    assert (swept & neighbours).any()  # CDC and the effect model see the hand sweep through them


# ------------------------------------------------------------------------------------- effect model
def test_the_effect_removes_the_target_and_pushes_out_what_is_in_its_way() -> None:
    belief = box_belief([TARGET, IN_THE_WAY, BYSTANDER])
    a = top_grasp(0.0, 0.225, 0.14, 0.04)
    model = AnalyticGraspEffect()
    pred = model.predict(belief, [a], WORKSPACE)
    assert isinstance(pred.beliefs, DeltaBeliefs)
    after = pred.beliefs[0]
    c = GRID.centers()

    def inside(box: tuple) -> np.ndarray:  # type: ignore[type-arg]
        (x0, y0), (x1, y1), h, _ = box
        return (c[..., 0] > x0) & (c[..., 0] < x1) & (c[..., 1] > y0) & (c[..., 1] < y1) & (c[..., 2] > 0) & (
            c[..., 2] < h)

    target, way, by = inside(TARGET), inside(IN_THE_WAY), inside(BYSTANDER)
    p = after.expected_occupancy()
    # the grasped box left with the gripper: its space is believed free (target: free, the default)
    assert np.all(after.alpha[target] == 1.0)
    assert np.all(after.beta[target] == 21.0)
    assert np.all(np.argmax(after.eta, axis=0)[target] == 0)
    # as MEM (target: prior): its voxels return to the prior
    mem = AnalyticGraspEffect(GraspEffectConfig(target="prior")).predict(belief, [a], WORKSPACE).beliefs[0]
    assert np.all(mem.alpha[target] == 1.0)
    assert np.all(mem.beta[target] == 1.0)
    assert np.all(mem.eta[:, target] == 1.0)
    assert pred.excluded is not None
    excluded = np.isin(np.arange(GRID.size), pred.excluded[0]).reshape(GRID.shape)
    assert np.array_equal(excluded, target)
    assert np.all(p[way] < 0.05)
    assert np.all(np.argmax(after.eta, axis=0)[way] == 0)
    assert np.all(after.vacuity()[way] < 0.5)
    assert np.array_equal(after.alpha[by], belief.alpha[by])  # the bystander stays
    assert np.array_equal(pred.changed[0], target | way)
    # a CDC term (confident afterwards, class changed from a known one) sees the pushed block only
    known = belief.vacuity() < 0.5
    cls0, cls1 = np.argmax(belief.eta, axis=0), np.argmax(after.eta, axis=0)
    u_diff = known & (after.vacuity() < 0.5) & (cls0 != cls1) & ~excluded
    assert np.array_equal(u_diff, way)
    # lifted high enough, the object leaves over the block: nothing else changes
    high = model.predict(belief, [top_grasp(0.0, 0.225, 0.14, 0.04, lift=0.09)], WORKSPACE)
    assert np.array_equal(high.changed[0], target)


def _tall_box() -> tuple[EvidentialMap, np.ndarray, GraspAction]:  # type: ignore[type-arg]
    """A confident 24 cm box in the front row, the mask of its voxels, and a front grasp 6 cm above the floor."""
    box = ((-0.03, 0.05), (0.03, 0.11), 0.24, SUGAR)
    c = GRID.centers()
    whole = (np.abs(c[..., 0]) < 0.03) & (c[..., 1] > 0.05) & (c[..., 1] < 0.11) & (c[..., 2] > 0) & (c[..., 2] < 0.24)
    pose = gripper_pose((0.0, 0.05, 0.06), (0, 1, 0), (1, 0, 0))
    a = GraspAction(pose=tuple(tuple(float(v) for v in row) for row in pose), width_m=0.06, opening_m=0.08,
                    contact_m=(-0.03, 0.05, 0.06), target_class=SUGAR,
                    retreat_m=((0.0, 0.05, 0.09), (0.0, -0.3, 0.09)))
    return box_belief([box]), whole, a


def _disturbed_if_emptied(belief: EvidentialMap, whole: np.ndarray, excluded: np.ndarray) -> int:  # type: ignore[type-arg]
    """CDC's count over the box's voxels when the whole box is believed free afterwards (what the
    learned grasp model predicts for it), ``excluded`` (flat indices) left out."""
    from msmem_objectives.cdc import disturbed_voxels

    flat = np.flatnonzero(whole.reshape(-1))
    after = belief.copy()
    after.alpha[whole], after.beta[whole], after.eta[:, whole] = 1.0, 21.0, 1.0
    after.eta[0, whole] = 21.0
    eta0, eta1 = belief.eta.reshape(belief.num_classes, -1), after.eta.reshape(belief.num_classes, -1)
    return int(disturbed_voxels(eta0[:, flat], eta1[:, flat], 0.5, np.isin(flat, excluded)).sum())


def test_the_intended_removal_is_the_whole_grasped_object_not_only_the_fingers_region() -> None:
    """A 24 cm box grasped from the front 6 cm above the floor: the region the fingers close on is
    clipped 10 cm above the grasp, but the whole box leaves with it. Both effect models report the whole
    box as the intended removal, so a CDC term that sees the box's upper part become free counts
    nothing; with the region alone it counted that upper part as collateral damage."""
    from msmem_cnabu.features import grasp_removals

    belief, whole, a = _tall_box()
    model = AnalyticGraspEffect()
    objects = Objects.of(belief, INTERIOR)
    label, region = model.target_region(belief, objects, a)
    flat = np.flatnonzero(whole.reshape(-1))
    assert label > 0
    assert 0 < len(region) < len(flat)  # the region stops below the box's top
    removal = model.removal(belief, objects, a)
    assert np.array_equal(removal, flat)
    pred = model.predict(belief, [a], WORKSPACE)
    assert pred.excluded is not None
    assert np.array_equal(pred.excluded[0], flat)
    assert [r.tolist() for r in grasp_removals(belief, [a], WORKSPACE)] == [flat.tolist()]
    assert _disturbed_if_emptied(belief, whole, removal) == 0
    assert _disturbed_if_emptied(belief, whole, region) == len(flat) - len(region)


def test_the_intended_removal_takes_the_objects_own_voxels_of_another_class() -> None:
    """The default belief labels bands of an object with another class (here the lower 10 cm of the 24 cm
    box's front voxel layer as a meat can): a component of its own. The band stands in the box's
    columns under its top, where nothing else can stand, so it is part of the removal; a CDC term that
    sees it become free counts nothing (it counted the band's 60 voxels with the box's component alone)."""
    belief, whole, a = _tall_box()
    c = GRID.centers()
    band = whole & (c[..., 1] < 0.06) & (c[..., 2] < 0.10)
    belief.eta[:, band] = 1.0
    belief.eta[MEAT, band] = 21.0
    model = AnalyticGraspEffect()
    objects = Objects.of(belief, INTERIOR)
    label, region = model.target_region(belief, objects, a)
    own = objects.carried(GRID, label, region, 0.02)
    flat = np.flatnonzero(whole.reshape(-1))
    assert not np.isin(np.flatnonzero(band.reshape(-1)), own).any()  # another component
    removal = model.removal(belief, objects, a)
    assert np.array_equal(removal, flat)
    assert _disturbed_if_emptied(belief, whole, removal) == 0
    assert _disturbed_if_emptied(belief, whole, own) == band.sum() == 60


def test_the_hidden_lower_part_of_the_grasped_object_is_carried_out_too() -> None:
    belief = box_belief([TARGET, IN_THE_WAY])
    c = GRID.centers()
    low = (np.abs(c[..., 0]) < 0.02) & (c[..., 1] > 0.18) & (c[..., 1] < 0.27) & (c[..., 2] > 0) & (c[..., 2] < 0.09)
    belief.alpha[low], belief.beta[low], belief.eta[:, low] = 1.0, 1.0, 1.0  # seen only above the block
    objects = Objects.of(belief, INTERIOR)
    region = np.flatnonzero((objects.labels.reshape(-1) > 0) & (objects.cls.reshape(-1) == SUGAR))
    label = int(objects.labels.reshape(-1)[region[0]])
    full = fill_down(GRID, belief.expected_occupancy(), objects.labels, region, label, 0.3)
    assert set(np.flatnonzero(low.reshape(-1))) <= set(full.tolist())
    pred = AnalyticGraspEffect().predict(belief, [top_grasp(0.0, 0.225, 0.14, 0.04)], WORKSPACE)
    way = (np.abs(c[..., 0]) < 0.05) & (c[..., 1] > 0.12) & (c[..., 1] < 0.18) & (c[..., 2] > 0) & (c[..., 2] < 0.08)
    assert np.all(pred.changed[0][way])  # the block in front is still predicted pushed out


def test_batched_predictions_equal_one_at_a_time_and_other_actions_are_refused() -> None:
    belief = box_belief([TARGET, IN_THE_WAY, BYSTANDER])
    actions = [top_grasp(0.0, 0.225, 0.14, 0.04), top_grasp(0.0, 0.225, 0.14, 0.04, lift=0.09),
               top_grasp(0.28, 0.13, 0.19, 0.06, cls=CRACKER, closing=(0.0, 1.0, 0.0))]
    model = AnalyticGraspEffect(GraspEffectConfig())
    batch = model.predict(belief, actions, WORKSPACE)
    assert batch.changed.shape == (3, *GRID.shape)
    for k, a in enumerate(actions):
        one = model.predict(belief, [a], WORKSPACE)
        assert np.array_equal(batch.changed[k], one.changed[0])
        for name in ("alpha", "beta", "eta"):
            assert np.array_equal(getattr(batch.beliefs[k], name), getattr(one.beliefs[0], name))
    from msmem_push.skill import PushAction

    push = PushAction(start_m=(0.0, 0.05), direction=(0.0, 1.0), length_m=0.1, height_m=0.02)
    with pytest.raises(TypeError, match="grasp"):
        model.predict(belief, [push], WORKSPACE)


def test_grasp_candidates_are_scored_by_the_ig_and_entropy_terms() -> None:
    from msmem_objectives.entropy import SemanticEntropyConfig, SemanticEntropyTerm
    from msmem_objectives.ig import IGTerm, IGTermConfig

    from msmem_core.map.belief import categorical_entropy

    belief = box_belief([TARGET, IN_THE_WAY, BYSTANDER])
    c = GRID.centers()
    hidden = (c[..., 1] > 0.27) & (np.abs(c[..., 0]) < 0.1) & (c[..., 2] < 0.2)
    belief.alpha[hidden], belief.beta[hidden], belief.eta[:, hidden] = 1.0, 1.0, 1.0  # unknown behind the target
    views = generate_viewpoints(ViewpointConfig(), SHELF)[::15]
    ig = IGService(GRID, CameraConfig(width_px=160, height_px=120), views, SHELF)
    actions = [top_grasp(0.0, 0.225, 0.14, 0.04), top_grasp(0.28, 0.13, 0.19, 0.06, cls=CRACKER, closing=(0, 1, 0))]
    pred = AnalyticGraspEffect().predict(belief, actions, WORKSPACE)
    batch = CandidateBatch("grasp", "manipulation", list(actions), prediction=pred)
    d = ctx(belief, ig=ig)
    exact = IGTerm(IGTermConfig(screen_ray_step=1)).score(d, batch)
    before = ig.prepare(belief)
    full = ig.view_ig([ig.prepare(b, before=before) for b in pred.beliefs]).max(axis=1)
    np.testing.assert_allclose(exact, full, rtol=1e-9)
    best_view = ig.view_ig(before).max()
    assert exact[0] > best_view  # the target's removal opens the unknown space behind it
    # the bystander's opens nothing new (what its own voxels still had to show leaves with it)
    assert exact[1] <= best_view * (1 + 1e-9)
    # removal: exempt (the default): the intended removal's voxels do not count in dH; counted: they do.
    # On a belief whose objects' classes are surer than two views of free space, removal raises entropy
    sure = belief.copy()
    sure.eta[1:] = 1.0 + 4.0 * (sure.eta[1:] - 1.0)
    pred = AnalyticGraspEffect().predict(sure, actions, WORKSPACE)
    batch = CandidateBatch("grasp", "manipulation", list(actions), prediction=pred)
    exempt = SemanticEntropyTerm(SemanticEntropyConfig(clip=False)).score(ctx(sure), batch)
    counted = SemanticEntropyTerm(SemanticEntropyConfig(clip=False, removal="counted")).score(ctx(sure), batch)
    eta0 = sure.eta.reshape(sure.num_classes, -1)
    for k, ch in enumerate(pred.changes):
        dh = categorical_entropy(eta0[:, ch.idx]) - categorical_entropy(ch.eta)
        gone = pred.excluded_among(k)
        assert gone is not None
        assert gone.any()
        assert dh[gone].sum() < -1.0  # the removal alone raises the entropy
        np.testing.assert_allclose(counted[k], dh.sum(), rtol=1e-9)
        np.testing.assert_allclose(exempt[k], dh[~gone].sum(), rtol=1e-9, atol=1e-9)


# ------------------------------------------------------------------------------ physics (PyBullet)
def observed_belief(sim, scene: SceneSpec, views: list[int]) -> EvidentialMap:  # type: ignore[no-untyped-def]
    from msmem_analytic.observation import AnalyticObservationModel

    vps = generate_viewpoints(ViewpointConfig())
    model = AnalyticObservationModel()
    b = EvidentialMap.empty(GRID)
    for v in views:
        b = model.update(b, sim.observe(vps[v]))
    return b


VIEWS = [default_start_view(ViewpointConfig()), 5, 94, 105, 194, 205, 255, 45]
"""The episodes' start view and views from the left, middle and right grids, low and high."""


def test_a_failed_grasp_counts_in_position_change_and_a_removed_object_does_not() -> None:
    pytest.importorskip("pybullet")
    from msmem_pybullet.simulator import PyBulletSimulator

    scene = SceneSpec(name="pc", objects=(
        ObjectSpec(id=0, class_name="sugar_box", position_m=(-0.15, 0.15, 0.0), quat_xyzw=tuple(yaw_quat(math.pi / 2))),
        ObjectSpec(id=1, class_name="tomato_soup_can", position_m=(0.12, 0.15, 0.0)),
    ))
    sim = PyBulletSimulator(label_noise=0.0)
    try:
        sim.reset(scene)
        initial = sim.object_poses()
        skill = GraspSkill(GraspConfig(predictor="geometric"))
        c = SimpleNamespace(shelf=scene.shelf)
        ok = execute_measured(skill, sim, top_grasp(-0.15, 0.15, 0.145, 0.04), c)  # across the 4 cm box
        assert ok.success
        assert ok.removed == [0]
        assert 0 not in ok.displacement_m
        assert set(sim.object_poses()) == {1}
        # a grasp 3 cm off the can's axis: the closing fingers squeeze it out sideways
        bad = execute_measured(skill, sim, top_grasp(0.15, 0.15, 0.08, 0.066, closing=(0.0, 1.0, 0.0)), c)
        assert not bad.success
        assert bad.removed == []
        final = sim.object_poses()
    finally:
        sim.close()
    moved = float(np.linalg.norm(final[1][:2, 3] - initial[1][:2, 3]))
    assert moved > 0.005, "the failed grasp should have moved the can"
    assert bad.displacement_m[1] == pytest.approx(moved, abs=1e-3)  # (measured from before that grasp)
    assert position_change_m(initial, final) == pytest.approx(moved)  # the removed box is excluded


def test_predicted_occupancy_after_a_disturbing_grasp_beats_removal_alone() -> None:
    pytest.importorskip("pybullet")
    from msmem_pybullet.simulator import PyBulletSimulator

    q90 = tuple(yaw_quat(math.pi / 2))
    scene = SceneSpec(name="neighbour-in-the-way", objects=(
        ObjectSpec(id=0, class_name="sugar_box", position_m=(0.0, 0.22, 0.0), quat_xyzw=q90),
        ObjectSpec(id=1, class_name="potted_meat_can", position_m=(0.0, 0.22 - 0.045 - 0.0255 - 0.002, 0.0)),
        ObjectSpec(id=2, class_name="cracker_box", position_m=(0.25, 0.20, 0.0)),
        ObjectSpec(id=3, class_name="foam_brick", position_m=(-0.22, 0.25, 0.0)),
    ))
    sim = PyBulletSimulator(label_noise=0.0)
    model = AnalyticGraspEffect()
    inside = interior_mask(SHELF, GRID)
    compared = 0
    try:
        sim.reset(scene)
        belief = observed_belief(sim, scene, VIEWS)
        # the can is in the way of the grasps as predicted (turned ones may pass beside it)
        skill = GraspSkill(GraspConfig(predictor="geometric", blocked_exit="lift_m", turn_to=()))
        grasps = [g for g in skill.propose(ctx(belief)) if g.target_class == SUGAR]
        assert grasps
        pred = model.predict(belief, grasps, WORKSPACE)
        token = sim.snapshot()
        for k, g in enumerate(grasps[:4]):
            pushed = model.displacements(belief, g, WORKSPACE)["pushed"]
            sim.restore(token)
            out = execute_measured(skill, sim, g, SimpleNamespace(shelf=scene.shelf))  # type: ignore[arg-type]
            if not out.success or not pushed:
                continue
            poses = sim.object_poses()
            truth, _ = voxelize([o for o in scene.objects if o.id in poses], GRID, poses=poses)
            removed_only = belief.copy()
            region = model.displacements(belief, g, WORKSPACE)["region"]
            for name in ("alpha", "beta"):
                getattr(removed_only, name).reshape(-1)[region] = 1.0
            removed_only.eta.reshape(belief.num_classes, -1)[:, region] = 1.0
            ours = occupancy_iou((pred.beliefs[k].expected_occupancy() > 0.5) & inside, truth & inside)
            base = occupancy_iou((removed_only.expected_occupancy() > 0.5) & inside, truth & inside)
            assert 1 in out.fell_or_left  # the can in the way was pushed off the shelf
            assert ours > base, (k, ours, base)
            compared += 1
            print("grasp", k, "IoU predicted", round(ours, 3), "removal only", round(base, 3))
    finally:
        sim.close()
    assert compared >= 1, "no successful grasp pushed the can (nothing to compare)"


def test_turned_approaches_are_orthogonal_to_the_closing_axis_and_within_45_deg_of_their_direction() -> None:
    from msmem_grasp.skill import turn_about

    rng = np.random.default_rng(0)
    b = rng.normal(size=(400, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    for d in ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)):
        a, ok = turn_about(b, d)
        along = b @ np.asarray(d)
        assert 0 < ok.sum() < len(b)
        np.testing.assert_array_equal(ok, np.abs(along) <= math.sin(math.radians(45)))  # within 45 deg of d
        np.testing.assert_allclose(np.linalg.norm(a[ok], axis=1), 1.0)
        np.testing.assert_allclose((a[ok] * b[ok]).sum(1), 0.0, atol=1e-12)
        np.testing.assert_allclose(a[ok] @ np.asarray(d), np.sqrt(1.0 - along[ok] ** 2))  # the most of d left
        assert not a[~ok].any()


@pytest.mark.parametrize(("max_per_object", "top_k"), [(1, 40), (2, 40), (4, 40), (300, 300)])
def test_turned_twins_last_only_fill_the_places_the_predicted_grasps_leave(max_per_object: int, top_k: int) -> None:
    """``twins: last``: every grasp the skill proposes without twins is proposed with them, first and in the
    same order; a twin is proposed only for an object that the predicted grasps leave short of
    ``max_per_object``."""
    belief = box_belief([TARGET, BYSTANDER])
    got = {}
    for turn_to in ((), ("front", "sides")):
        skill = GraspSkill(GraspConfig(predictor="geometric", max_per_object=max_per_object, top_k=top_k,
                                       turn_to=turn_to, twins="last"))  # type: ignore[arg-type]
        got[turn_to] = skill.propose(ctx(belief))
    base, out = got[()], got[("front", "sides")]
    assert base
    assert out[: len(base)] == base
    twins = out[len(base):]
    per_class = {k: sum(g.target_class == k for g in base) for k in {g.target_class for g in out}}
    for g in twins:
        assert per_class[g.target_class] < max_per_object
        per_class[g.target_class] += 1
    assert all(n <= max_per_object for n in per_class.values())
    if top_k == 300:
        assert twins  # where there is room, twins are proposed


def test_a_grasp_turned_to_the_front_keeps_its_contacts_and_holds_where_from_above_the_hand_does_not_fit() -> None:
    pytest.importorskip("pybullet")
    from msmem_grasp.fusion import GraspHypotheses
    from msmem_pybullet.simulator import PyBulletSimulator

    # a predicted grasp from above, 7.5 cm under the top of a standing 4 cm-wide box: the palm meets the box
    scene = SceneSpec(name="turn", objects=(
        ObjectSpec(id=0, class_name="sugar_box", position_m=(0.0, 0.15, 0.0), quat_xyzw=tuple(yaw_quat(math.pi / 2))),))
    sim = PyBulletSimulator(label_noise=0.0)
    try:
        sim.reset(scene)
        belief = observed_belief(sim, scene, VIEWS)
        one = np.ones(1)
        from_above = GraspHypotheses(
            contact=np.array([[-0.02, 0.15, 0.10]]), mu_a_hat=np.array([[0.0, 0.0, -1.0]]), kappa_a_hat=50 * one,
            mu_b=np.array([[1.0, 0.0, 0.0]]), kappa_b=50 * one, alpha=9 * one, beta=one, width=0.04 * one)
        got = {}
        for turn_to in ((), ("front",), ("sides",), ("front", "sides")):
            skill = GraspSkill(GraspConfig(predictor="geometric", turn_to=turn_to))  # type: ignore[arg-type]
            skill.buffer.update(from_above)
            stages: dict[str, int] = {}
            got[turn_to] = skill.executable(belief, scene.shelf, stages, WORKSPACE.classes)
            # closing along x: a twin from the front, none from the sides
            assert stages["from_front"] == (2 if "front" in turn_to else 1)
        assert got[()] == got[("sides",)] == []
        assert len(got[("front",)]) == 1
        assert got[("front", "sides")] == got[("front",)]  # the predicted one does not fit, its turned twin does
        g = got[("front",)][0]
        np.testing.assert_allclose(g.matrix[:3, 2], [0.0, 1.0, 0.0], atol=1e-12)  # straight into the shelf
        np.testing.assert_allclose(g.matrix[:3, 0], [1.0, 0.0, 0.0], atol=1e-12)  # the same closing axis
        np.testing.assert_allclose(g.matrix[:3, 3], [0.0, 0.15, 0.10], atol=1e-12)  # and centre
        assert g.contact_m == pytest.approx((-0.02, 0.15, 0.10))
        # closing along the depth: twins from both sides, none from the front
        deep = GraspSkill(GraspConfig(predictor="geometric", turn_to=("front", "sides")))  # type: ignore[arg-type]
        deep.buffer.update(dataclasses.replace(from_above, contact=np.array([[0.0, 0.105, 0.10]]),
                                               mu_b=np.array([[0.0, 1.0, 0.0]]), width=0.09 * one))
        stages = {}
        deep.executable(belief, scene.shelf, stages, WORKSPACE.classes)
        assert stages["from_front"] == 3
        out = execute_measured(GraspSkill(GraspConfig(predictor="geometric")), sim, g,
                               SimpleNamespace(shelf=scene.shelf))  # type: ignore[arg-type]
        assert out.success
        assert out.removed == [0]
    finally:
        sim.close()


@pytest.mark.slow
def test_a_grasp_only_episode_executes_a_grasp(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from msmem_core.config import load_config
    from msmem_core.run.runner import build_episode, run_episode

    # the analytic models, and MEM's IG for predictions (the entropy a grasp's prediction adds counts): a
    # grasp wins within 8 steps here; under the defaults this scene's grasps lose to views (docs/explanation/grasp.md)
    cfg = load_config("grasp-only", overrides={
        "steps": 8, "scene": {"seed": 1}, "ig": {"predicted_entropy": "as-predicted"},
        "observation_model": {"name": "analytic-observation"},
        "effect_models": {"push": {"name": "push-analytic"}, "grasp": {"name": "grasp-analytic"}}})
    ep = build_episode(cfg, get_plugin_manager())
    final = run_episode(ep, tmp_path)
    assert final["actions"].get("grasp", 0) >= 1
    grasps = [r for r in ep.records if r["skill"] == "grasp"]
    assert any(r["success"] for r in grasps)


@pytest.mark.slow
def test_bench_grasp_success_rate() -> None:
    """Top-1 fused grasps over 10 generated scenes x 2 trials; run with -m slow -s to see the number."""
    from msmem_grasp.learn.bench import GraspBenchConfig, bench_grasp

    s = bench_grasp(GraspBenchConfig(), progress=False)["summary"]
    print(f"\nbench-grasp: {s['successes']}/{s['executed']} succeeded ({s['success_rate']:.2f}), "
          f"{s['no_candidate']} trials without an executable grasp, predictor {s['predictor']}")
    assert s["executed"] >= 5
    assert s["success_rate"] >= 0.8

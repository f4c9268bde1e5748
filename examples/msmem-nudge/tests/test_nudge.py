"""msmem-nudge's own tests: registration, proposals from the belief, the effect model, the travel-cost
term, and a real PyBullet nudge that moves an object sideways. Fixtures come from msmem's testing kit
(``plugin_manager``, ``fake_simulator``: loaded automatically as a pytest plugin)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from msmem_nudge.effect import NudgeEffect
from msmem_nudge.skill import NudgeAction, NudgeConfig, NudgeSkill
from msmem_nudge.travel import TravelCost, TravelCostConfig

from msmem_core.interfaces import CandidateBatch, Workspace
from msmem_core.map.belief import EvidentialMap
from msmem_core.msas import execute_measured
from msmem_core.world.camera import CameraConfig
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ObjectSpec, SceneSpec, ShelfSpec, object_class
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

SHELF = ShelfSpec()
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.01, 1)
WORKSPACE = Workspace(GRID, SHELF)
CAN = object_class("potted_meat_can").class_id


def box_belief(x: tuple[float, float], y: tuple[float, float], top: float, cls: int = CAN) -> EvidentialMap:
    """A belief that has seen a box's front and top: occupied and confident inside it, free above it."""
    b = EvidentialMap.empty(GRID)
    c = GRID.centers()
    inside = (c[..., 0] > x[0]) & (c[..., 0] < x[1]) & (c[..., 1] > y[0]) & (c[..., 1] < y[1]) \
        & (c[..., 2] > 0) & (c[..., 2] < top)
    above = (c[..., 0] > x[0]) & (c[..., 0] < x[1]) & (c[..., 1] > y[0]) & (c[..., 1] < y[1]) & (c[..., 2] > top) \
        & (c[..., 2] < SHELF.height_m)
    b.alpha[inside] += 20.0
    b.eta[cls][inside] += 20.0
    b.beta[above] += 20.0
    b.eta[0][above] += 20.0
    return b


def test_the_package_registers_a_skill_an_effect_model_and_a_term(plugin_manager):
    reg = {kind: plugin_manager.registered(kind) for kind in ("skill", "belief-model", "objective-term")}
    assert reg["skill"]["nudge"].distribution == "msmem-nudge"
    assert reg["skill"]["nudge"].spec.effect_model == "nudge-effect"
    assert "effect" in reg["belief-model"]["nudge-effect"].spec.roles
    assert reg["objective-term"]["travel-cost"].distribution == "msmem-nudge"
    skill = plugin_manager.build("skill", "nudge")
    assert isinstance(skill, NudgeSkill)
    assert skill.category == "manipulation"


def test_nudges_are_proposed_beside_a_seen_object_at_70_percent_of_its_height():
    belief = box_belief((-0.05, 0.05), (0.03, 0.08), 0.09)
    acts = NudgeSkill().sample(belief, SHELF, np.random.default_rng(0))
    assert acts, "a low confident object at the front should get nudge candidates"
    assert {a.direction for a in acts} == {(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)}
    for a in acts:
        assert a.start_m[2] == pytest.approx(0.7 * 0.09, abs=1e-9)
        assert 0.03 <= a.nudge_m <= 0.05
        side = a.start_m[0] < -0.05 if a.direction[0] > 0 else a.start_m[0] > 0.05
        assert side, "the fingers start beside the object, on the side they push from"
        assert a.approach_z_m > a.top_m
        assert not (a.swept_volume(WORKSPACE) & (belief.expected_occupancy() > 0.5)).all()


def test_no_nudge_for_objects_too_tall_for_the_gripper_or_likely_to_tip():
    tall = box_belief((-0.08, 0.08), (0.03, 0.09), 0.21)  # a cracker box: no room above it
    assert NudgeSkill().sample(tall, SHELF, np.random.default_rng(0)) == []
    thin = box_belief((-0.01, 0.01), (0.03, 0.12), 0.15)  # 2 cm wide, 15 cm tall: it would tip
    assert NudgeSkill().sample(thin, SHELF, np.random.default_rng(0)) == []


def test_the_effect_model_shifts_the_object_and_frees_what_it_left():
    belief = box_belief((-0.05, 0.05), (0.03, 0.08), 0.09)
    acts = [a for a in NudgeSkill().sample(belief, SHELF, np.random.default_rng(0)) if a.direction[0] > 0]
    pred = NudgeEffect().predict(belief, acts[:1], WORKSPACE)
    after = pred.beliefs[0]
    n = round(acts[0].nudge_m / GRID.voxel_m)
    occ_before = belief.expected_occupancy() > 0.5
    occ_after = after.expected_occupancy() > 0.5
    assert np.array_equal(np.roll(occ_before, n, axis=0), occ_after)
    assert pred.changed[0].sum() == 2 * n * occ_before.any(axis=0).sum()
    left = occ_before & ~occ_after
    assert np.allclose(after.expected_occupancy()[left], 0.5), "vacated voxels return to the prior"


def test_travel_cost_charges_camera_travel_from_the_previous_view_and_time_per_kind():
    views = generate_viewpoints(ViewpointConfig(), SHELF)
    term = TravelCost(TravelCostConfig(seconds_per_kind={"view": 1.0, "nudge": 8.0}))
    ctx = SimpleNamespace(visited={150}, viewpoints=views)
    view_actions = [SimpleNamespace(kind="view"), SimpleNamespace(kind="view")]
    batch = CandidateBatch("view", "perception", view_actions, view_indices=np.array([150, 299]))  # type: ignore[arg-type]
    near, far = term.score(ctx, batch)
    assert near == pytest.approx(-1.0)
    assert far < near - 1.0
    nudge = NudgeSkill().sample(box_belief((-0.05, 0.05), (0.03, 0.08), 0.09), SHELF, np.random.default_rng(0))[:1]
    cost = term.score(ctx, CandidateBatch("nudge", "manipulation", nudge))  # type: ignore[arg-type]
    assert cost[0] < -8.0


def test_execute_composes_simulator_moves_and_parks(fake_simulator):
    belief = box_belief((-0.05, 0.05), (0.03, 0.08), 0.09)
    action = NudgeSkill().sample(belief, SHELF, np.random.default_rng(0))[0]
    fake_simulator.reset(SceneSpec(name="empty"))
    out = execute_measured(NudgeSkill(), fake_simulator, action, SimpleNamespace(shelf=SHELF))  # as MSAS runs it
    assert fake_simulator.calls.count("move_gripper") == 3
    assert out.success
    assert out.fell_or_left == []
    assert fake_simulator.gripper_pose()[2, 3] > 1.0, "parked out of the workspace"


def test_a_real_pybullet_nudge_moves_the_object_sideways(plugin_manager):
    """Observe a potted meat can from three views, take a proposed nudge, execute it under physics."""
    cam = CameraConfig(width_px=160, height_px=120)
    sim = plugin_manager.build("simulator", "pybullet", camera=cam, seed=0)
    observe = plugin_manager.build("belief-model", "analytic-observation", camera=cam)
    can = ObjectSpec(id=0, class_name="potted_meat_can", position_m=(0.0, 0.06, 0.0))
    scene = SceneSpec(name="nudge", objects=(can,))
    views = generate_viewpoints(ViewpointConfig(), scene.shelf)
    try:
        sim.reset(scene)
        belief = EvidentialMap.empty(GRID)
        for v in (155, 165, 145):
            belief = observe.update(belief, sim.observe(views[v]))
        skill = NudgeSkill(NudgeConfig())
        acts = skill.sample(belief, scene.shelf, np.random.default_rng(0))
        assert acts, "the can is low and at the front: it should be nudgeable"
        action: NudgeAction = next(a for a in acts if a.direction[0] > 0)
        before = sim.object_poses()[0]
        out = execute_measured(skill, sim, action, SimpleNamespace(shelf=scene.shelf))
        after = sim.object_poses()[0]
    finally:
        sim.close()
    dx, dy = after[:2, 3] - before[:2, 3]
    assert out.success
    assert out.fell_or_left == []
    planned = action.nudge_m
    assert dx == pytest.approx(planned, abs=0.015), f"moved {dx * 100:.1f} cm, planned {planned * 100:.1f}"
    assert abs(dy) < 0.01
    assert after[2, 2] > 0.98, "still upright"

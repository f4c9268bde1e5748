"""msmem-nudge's own tests, written with msmem's testing kit (``msmem_core.testing``): the conformance
suites for the skill (executed in PyBullet) and the effect model, proposals and predictions on beliefs
built from boxes, the travel-cost term, one MSAS decision between a view and a nudge, and a real
PyBullet nudge from observed views. Fixtures (``plugin_manager``, ``fake_simulator``) load automatically."""

from __future__ import annotations

import numpy as np
import pytest
from msmem_nudge.effect import NudgeEffect
from msmem_nudge.skill import NudgeAction, NudgeConfig, NudgeSkill
from msmem_nudge.travel import TravelCost, TravelCostConfig
from msmem_view.skill import ViewAction

from msmem_core.interfaces import CandidateBatch
from msmem_core.map.belief import EvidentialMap
from msmem_core.msas import execute_measured
from msmem_core.testing import (
    belief_of_scene,
    belief_with_boxes,
    decision_context,
    default_workspace,
    effect_model_conformance,
    one_decision,
    skill_conformance,
)
from msmem_core.world.camera import CameraConfig
from msmem_core.world.scene import ObjectSpec, SceneSpec, object_class
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

WS = default_workspace(voxel_m=0.01)
SHELF, GRID = WS.shelf, WS.grid
CAN = object_class("potted_meat_can").class_id
SCENE = SceneSpec(name="nudge", objects=(ObjectSpec(id=0, class_name="potted_meat_can", position_m=(0.0, 0.06, 0.0)),))
"""A low can at the front: nudgeable."""
FRONT = ((-0.5, -0.2, -0.1), (0.5, 0.12, 0.4))
"""The front of the shelf, seen; behind it the belief is the prior."""


def box_belief(x: tuple[float, float], y: tuple[float, float], top: float, cls: int = CAN) -> EvidentialMap:
    """A belief that has seen a box's front and top: occupied and confident inside it, free above it,
    the prior elsewhere."""
    return belief_with_boxes(GRID, [((x[0], y[0], 0.0), (x[1], y[1], top), cls)],
                             free=[((x[0], y[0], top), (x[1], y[1], SHELF.height_m))])


def test_the_package_registers_a_skill_an_effect_model_and_a_term(plugin_manager):
    reg = {kind: plugin_manager.registered(kind) for kind in ("skill", "belief-model", "objective-term")}
    assert reg["skill"]["nudge"].distribution == "msmem-nudge"
    assert reg["skill"]["nudge"].spec.effect_model == "nudge-effect"
    assert "effect" in reg["belief-model"]["nudge-effect"].spec.roles
    assert reg["objective-term"]["travel-cost"].distribution == "msmem-nudge"
    skill = plugin_manager.build("skill", "nudge")
    assert isinstance(skill, NudgeSkill)
    assert skill.category == "manipulation"


def test_the_skill_conforms_and_nudges_in_pybullet():
    """msmem's skill suite: actions named ``nudge`` that survive JSON, reproducible from ``ctx.rng``,
    none when manipulation is not allowed; one executed in PyBullet returns a valid Outcome."""
    report = skill_conformance(NudgeSkill, "nudge", belief=belief_of_scene(SCENE, GRID), scene=SCENE, workspace=WS)
    assert report.outcomes[0].success


def test_the_effect_model_conforms():
    """msmem's effect-model suite: one sparse, sorted, in-range change per action, evidence >= 1,
    the belief it was given untouched."""
    prediction = effect_model_conformance(NudgeEffect, lambda ctx: NudgeSkill().propose(ctx),
                                          belief=box_belief((-0.05, 0.05), (0.03, 0.08), 0.09), workspace=WS)
    assert len(prediction) > 0


def test_nudges_are_proposed_beside_a_seen_object_at_70_percent_of_its_height():
    belief = box_belief((-0.05, 0.05), (0.03, 0.08), 0.09)
    acts = NudgeSkill().propose(decision_context(belief, workspace=WS))
    assert acts, "a low confident object at the front should get nudge candidates"
    assert {a.direction for a in acts} == {(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)}  # type: ignore[attr-defined]
    for a in acts:
        assert isinstance(a, NudgeAction)
        assert a.start_m[2] == pytest.approx(0.7 * 0.09, abs=1e-9)
        assert 0.03 <= a.nudge_m <= 0.05
        side = a.start_m[0] < -0.05 if a.direction[0] > 0 else a.start_m[0] > 0.05
        assert side, "the fingers start beside the object, on the side they push from"
        assert a.approach_z_m > a.top_m


def test_no_nudge_for_objects_too_tall_for_the_gripper_or_likely_to_tip():
    tall = box_belief((-0.08, 0.08), (0.03, 0.09), 0.21)  # a cracker box: no room above it
    assert NudgeSkill().propose(decision_context(tall, workspace=WS)) == []
    thin = box_belief((-0.01, 0.01), (0.03, 0.12), 0.15)  # 2 cm wide, 15 cm tall: it would tip
    assert NudgeSkill().propose(decision_context(thin, workspace=WS)) == []


def test_the_effect_model_shifts_the_object_and_frees_what_it_left():
    belief = box_belief((-0.05, 0.05), (0.03, 0.08), 0.09)
    acts = [a for a in NudgeSkill().propose(decision_context(belief, workspace=WS)) if a.direction[0] > 0]  # type: ignore[attr-defined]
    pred = NudgeEffect().predict(belief, acts[:1], WS)
    after = pred.belief(0)
    n = round(acts[0].nudge_m / GRID.voxel_m)  # type: ignore[attr-defined]
    occ_before = belief.expected_occupancy() > 0.5
    occ_after = after.expected_occupancy() > 0.5
    assert np.array_equal(np.roll(occ_before, n, axis=0), occ_after)
    assert pred.changed[0].sum() == 2 * n * occ_before.any(axis=0).sum()
    left = occ_before & ~occ_after
    assert np.allclose(after.expected_occupancy()[left], 0.5), "vacated voxels return to the prior"


def test_travel_cost_charges_camera_travel_from_the_previous_view_and_time_per_kind():
    term = TravelCost(TravelCostConfig(seconds_per_kind={"view": 1.0, "nudge": 8.0}))
    ctx = decision_context(box_belief((-0.05, 0.05), (0.03, 0.08), 0.09), workspace=WS, visited={0})
    views = CandidateBatch("view", "perception", [ViewAction(view=0), ViewAction(view=3)],
                           view_indices=np.array([0, 3]))
    here, far = term.score(ctx, views)
    assert here == pytest.approx(-1.0)
    assert far < here - 1.0, "the camera travels from view 0 to view 3"
    nudge = NudgeSkill().propose(ctx)[:1]
    cost = term.score(ctx, CandidateBatch("nudge", "manipulation", nudge))
    assert cost[0] < -8.0, "8 s plus the tool's path"


@pytest.mark.parametrize(("view_seconds", "winner"), [(1.0, "view"), (1000.0, "nudge")])
def test_one_msas_decision_between_a_view_and_a_nudge(plugin_manager, view_seconds, winner):
    """nudge.yaml's objective on a belief that has seen only the front: a cheap view wins on information
    gain; with a camera slow to move (slow_camera.yaml) the nudge wins."""
    belief = belief_of_scene(SCENE, GRID, known=FRONT)
    objective = [("ig", 1.0, plugin_manager.build("objective-term", "ig")),
                 ("travel-cost", 2.0, TravelCost(TravelCostConfig(seconds_per_kind={"view": view_seconds,
                                                                                     "nudge": 8.0})))]
    skills = [("view", plugin_manager.build("skill", "view")), ("nudge", NudgeSkill(), NudgeEffect())]
    decision = one_decision(skills, belief, objective, workspace=WS)
    assert decision.candidates["nudge"] > 0
    assert decision.skill.name == winner, decision.best
    assert decision.terms["ig"] > 0


def test_execute_composes_simulator_moves_and_parks(fake_simulator):
    belief = box_belief((-0.05, 0.05), (0.03, 0.08), 0.09)
    ctx = decision_context(belief, workspace=WS)
    action = NudgeSkill().propose(ctx)[0]
    fake_simulator.reset(SceneSpec(name="empty"))
    out = execute_measured(NudgeSkill(), fake_simulator, action, ctx)  # as MSAS runs it
    assert fake_simulator.calls.count("move_gripper") == 3
    assert out.success
    assert out.fell_or_left == []
    assert fake_simulator.gripper_pose()[2, 3] > 1.0, "parked out of the workspace"


def test_a_real_pybullet_nudge_from_observed_views_moves_the_object_sideways(plugin_manager):
    """Observe the can from three views, take a proposed nudge, execute it under physics."""
    cam = CameraConfig(width_px=160, height_px=120)
    sim = plugin_manager.build("simulator", "pybullet", camera=cam, seed=0)
    observe = plugin_manager.build("belief-model", "analytic-observation", camera=cam)
    views = generate_viewpoints(ViewpointConfig(), SHELF)
    try:
        sim.reset(SCENE)
        belief = EvidentialMap.empty(GRID)
        for v in (155, 165, 145):
            belief = observe.update(belief, sim.observe(views[v]))
        ctx = decision_context(belief, workspace=WS)
        acts = NudgeSkill(NudgeConfig()).propose(ctx)
        assert acts, "the can is low and at the front: it should be nudgeable"
        action = next(a for a in acts if isinstance(a, NudgeAction) and a.direction[0] > 0)
        before = sim.object_poses()[0]
        out = execute_measured(NudgeSkill(), sim, action, ctx)
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

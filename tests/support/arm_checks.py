"""Scripted arm moves both physics backends are held to (``tests/test_arm_execution.py``, parametrised
over PyBullet and SAPIEN): the same robot, the same moves, the same outcomes."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from msmem_core.interfaces import Robot, Simulator
from msmem_core.testing.conformance import single_object_scene
from msmem_core.world.scene import ObjectSpec, SceneSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

INTO_SHELF = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Gripper frame pointing into the shelf (+y), fingers closing along x."""


def hand(x: float, y: float, z: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = INTO_SHELF
    t[:3, 3] = (x, y, z)
    return t


def joints(sim: Simulator) -> np.ndarray:
    """The simulated arm's joint positions (``RobotModel.joint_names`` order)."""
    return sim._arm.joint_positions()  # type: ignore[attr-defined]


def check_grasp_and_carry_out(sim: Simulator, robot: Robot) -> None:
    """The arm grasps a soup can 10 cm deep and carries it out of the shelf."""
    sim.reset(single_object_scene("tomato_soup_can", (0.2, 0.10, 0.0)))
    start = sim.object_poses()[7]
    sim.move_gripper([hand(0.2, -0.08, 0.05)], opening_m=0.08, speed_mps=0.1)
    reached = sim.move_gripper([hand(0.2, 0.10, 0.05)], speed_mps=0.05)
    assert np.linalg.norm(reached[:3, 3] - (0.2, 0.10, 0.05)) < 0.002  # joint control tracks the path
    assert np.linalg.norm(sim.object_poses()[7][:3, 3] - start[:3, 3]) < 0.005  # the open hand slid around it
    closed = sim.set_gripper(0.0)
    assert 0.06 < closed < 0.07  # stopped by the can (6.6 cm across)
    assert sim.held_object() == 7
    sim.move_gripper([hand(0.2, 0.10, 0.08)], speed_mps=0.05)
    sim.move_gripper([hand(0.2, -0.15, 0.08)], speed_mps=0.1)
    assert sim.held_object() == 7
    assert sim.object_poses()[7][1, 3] < -0.1  # out of the shelf with the hand
    assert sim.robot_notes() == []
    # the gripper frame is the robot's own forward kinematics of the simulated joints, times its tool mount
    np.testing.assert_allclose(sim.gripper_pose(), robot.flange_pose(joints(sim)) @ robot.tool_mount(),  # type: ignore[attr-defined]
                               atol=1e-5)


def check_the_grasp_skill_plans_a_grasp_the_arm_makes(sim: Simulator, robot: Robot, observe: Simulator) -> None:
    """The grasp skill with the Panda's grasp settings (``examples/robots/panda-grasp.yaml``) plans on a
    belief from real depth images (``observe``: a floating-camera backend with the same scene) grasps from
    the front, at least one of which the arm follows; the arm makes it, and the can leaves the shelf in
    the hand. The planner sees the hand: its grasps' swept volumes hold the 20 cm hand."""
    import yaml
    from msmem_analytic.observation import AnalyticObservationModel
    from msmem_grasp.skill import GraspConfig, GraspSkill

    from msmem_core.interfaces import DecisionContext, Workspace
    from msmem_core.map.belief import EvidentialMap
    from msmem_core.msas import execute_measured
    from msmem_core.world.grid import GridSpec
    from msmem_core.world.gripper import GripperSpec

    scene = SceneSpec(objects=(ObjectSpec(id=7, class_name="tomato_soup_can", position_m=(-0.2, 0.07, 0.0)),
                               ObjectSpec(id=8, class_name="cracker_box", position_m=(0.0, 0.25, 0.0))))
    shelf = scene.shelf
    grid = GridSpec.around_box(shelf.interior_lower, shelf.interior_upper, 0.01)
    observe.reset(scene)
    vps = generate_viewpoints(ViewpointConfig())
    belief, model = EvidentialMap.empty(grid), AnalyticObservationModel()
    for v in (150, 5, 94, 105, 194, 205, 255, 45):
        belief = model.update(belief, observe.observe(vps[v]))
    config = Path(__file__).parents[2] / "examples" / "robots" / "panda-grasp.yaml"
    params = yaml.safe_load(config.read_text())["skill_params"]["grasp"]
    skill = GraspSkill(GraspConfig(**params))
    ws = Workspace(grid, shelf, GripperSpec(), robot=robot)
    ctx = DecisionContext(5, belief, None, np.zeros((0, 4, 4)), set(), ws,  # type: ignore[arg-type]
                          np.random.default_rng(0), True, 0.5)
    grasps = skill.propose(ctx)
    assert grasps, "no grasp proposed for a lone soup can at the front"
    for g in grasps:
        assert g.matrix[1, 2] >= np.cos(np.radians(30)) - 1e-9  # approach within 30 deg of straight in
        assert g.hand_m == tuple(params["hand_m"])
        assert g.pose[2][3] >= params["min_height_m"]
    reach = [robot.reach_path(skill.tool_path(g, ws), shelf) for g in grasps]
    reached = [g for g, r in zip(grasps, reach, strict=True) if r.reachable]
    assert reached, "the arm follows none of the proposed grasps"
    g = reached[0]
    palm_only = g.model_copy(update={"hand_m": None})
    assert g.swept_volume(ws).sum() > palm_only.swept_volume(ws).sum() + 100  # the hand sweeps more than a palm
    sim.reset(scene)
    out = execute_measured(skill, sim, g, ctx)
    assert out.success
    assert out.removed == [7]
    assert sim.robot_notes() == []
    assert out.displacement_m.get(8, 0.0) < 0.005  # the box behind stays


def check_push_and_exact_restore(sim: Simulator, restore_atol: float) -> None:
    """A hand driven into a box moves it (not a brick elsewhere); restoring and repeating is bit-exact."""
    scene = SceneSpec(objects=(ObjectSpec(id=0, class_name="sugar_box", position_m=(0.25, 0.12, 0.0)),
                               ObjectSpec(id=1, class_name="foam_brick", position_m=(-0.2, 0.2, 0.0))))
    sim.reset(scene)
    sim.move_gripper([hand(0.25, -0.08, 0.08)], opening_m=0.08)
    token = sim.snapshot()
    before = sim.object_poses()

    def push() -> dict[int, np.ndarray]:
        sim.move_gripper([hand(0.25, 0.16, 0.08)], speed_mps=0.1)
        sim.step(0.5)
        return sim.object_poses()

    after = push()
    assert np.linalg.norm(after[0][:3, 3] - before[0][:3, 3]) > 0.03  # the hand entered where the box stood
    assert np.linalg.norm(after[1][:3, 3] - before[1][:3, 3]) < 1e-3  # the brick is elsewhere
    sim.restore(token)
    for oid, pose in sim.object_poses().items():
        np.testing.assert_allclose(pose, before[oid], atol=restore_atol)
    np.testing.assert_allclose(sim.gripper_pose(), hand(0.25, -0.08, 0.08), atol=2e-3)  # the arm came back
    again = push()
    sim.restore(token)
    third = push()
    for oid, pose in third.items():  # restoring and repeating the same calls gives the same result, bit for bit
        np.testing.assert_array_equal(pose, again[oid])
        assert np.linalg.norm(pose[:3, 3] - after[oid][:3, 3]) < 0.01  # (the live run differs by solver warm starts)


def check_unreachable_start_is_not_made(sim: Simulator) -> None:
    """A move whose first waypoint is out of reach is not made, and the note says why (once)."""
    sim.reset(single_object_scene("foam_brick", (0.0, 0.2, 0.0)))
    sim.park_gripper()
    parked = sim.gripper_pose()
    got = sim.move_gripper([hand(0.0, -3.0, 0.1), hand(0.0, 0.2, 0.1)], opening_m=0.08)
    np.testing.assert_allclose(got, parked, atol=1e-4)  # no teleport, no motion (the hand opened meanwhile)
    notes = sim.robot_notes()
    assert len(notes) == 1
    assert notes[0].startswith("the first waypoint: no IK answer within")
    assert "the arm did not move" in notes[0]
    assert sim.robot_notes() == []  # taken once


def check_view_moves_the_wrist_camera(sim: Simulator, robot: Robot, bare: Callable[[], Simulator]) -> None:
    """A view puts the wrist camera there, and the fingers are in the picture (against ``bare()``, the
    same backend without the arm)."""
    scene = single_object_scene("foam_brick", (0.0, 0.2, 0.0))
    sim.reset(scene)
    views = generate_viewpoints(ViewpointConfig(), scene.shelf)
    view = views[int(np.flatnonzero(robot.reachable_views(views, scene.shelf))[0])]
    obs = sim.observe(view)
    camera = robot.flange_pose(joints(sim)) @ robot.camera_mount()  # type: ignore[attr-defined]
    assert np.linalg.norm(camera[:3, 3] - view[:3, 3]) < 0.006
    assert np.degrees(np.arccos(np.clip((np.trace(camera[:3, :3].T @ view[:3, :3]) - 1) / 2, -1, 1))) < 2.5
    floating = bare()
    floating.reset(scene)
    free = floating.observe(view)
    floating.close()
    own = (obs.depth > 0) & (obs.depth < 0.15) & ~((free.depth > 0) & (free.depth < 0.15))
    assert 0.005 < own.mean() < 0.1  # the fingers in front of the lens occlude a few per cent, as a real one's
    assert (obs.labels[own] == 0).all()
    assert (obs.object_ids[own] == -1).all()


def check_forward_pushes_of_the_push_skill(sim: Simulator, robot: Robot) -> None:
    """The push skill's forward tool (``examples/robots/panda-push.yaml``) executed by the arm: a cracker
    box pushed straight in from the shelf front and a soup can pushed sideways by the fingers; each
    moves by what the analytic effect model predicts (within 2 cm), stays standing, and the hand ends
    within 2 mm of the push's end."""
    from types import SimpleNamespace

    from msmem_push.effect import AnalyticPushEffect
    from msmem_push.skill import PushAction, PushConfig, PushSkill

    from msmem_core.interfaces import Workspace
    from msmem_core.map.belief import EvidentialMap
    from msmem_core.world.grid import GridSpec
    from msmem_core.world.scene import ShelfSpec
    from msmem_core.world.voxelize import voxelize

    shelf = ShelfSpec()
    grid = GridSpec.around_box(shelf.interior_lower, shelf.interior_upper, 0.01)
    cfg = PushConfig(palm="forward", hand_m=(0.204, 0.063, 0.066), tool_height_m=0.085, min_tool_height_m=0.045)
    skill = PushSkill(cfg)
    for obj, start, direction, length in (
        (ObjectSpec(id=0, class_name="cracker_box", position_m=(-0.2, 0.1, 0.0)), (-0.2, 0.0), (0.0, 1.0), 0.1),
        (ObjectSpec(id=1, class_name="tomato_soup_can", position_m=(-0.15, 0.07, 0.0)), (-0.235, 0.07),
         (1.0, 0.0), 0.13),
    ):
        sim.reset(SceneSpec(objects=(obj,)))
        gt, cls = voxelize([obj], grid)
        belief = EvidentialMap.empty(grid)  # the object known exactly: what the effect model would move
        belief.alpha[gt], belief.beta[gt] = 21.0, 1.0
        belief.eta[:, gt] = 1.0
        idx = np.nonzero(gt)
        belief.eta[(cls[idx], *idx)] = 21.0
        a = PushAction(start_m=start, direction=direction, length_m=length, height_m=0.085, palm="forward",
                       hand_m=cfg.hand_m)
        path = skill.waypoints(a)
        assert robot.reach_path(path, shelf).reachable
        camera = path[1] @ np.linalg.inv(robot.tool_mount()) @ robot.camera_mount()
        assert camera[2, 3] > path[1][2, 3] + 0.03  # the wrist camera rides above the hand, clear of the floor
        before = sim.object_poses()[obj.id]
        out = skill.execute(sim, a, SimpleNamespace(shelf=shelf))
        assert out.success, out.info
        assert out.info["tool_end_error_m"] < 0.002
        assert sim.robot_notes() == []
        after = sim.object_poses()[obj.id]
        moved = (after[:2, 3] - before[:2, 3]) @ np.asarray(direction)
        predicted = AnalyticPushEffect().displacements(belief, a, Workspace(grid, shelf))
        assert len(predicted) == 1
        print(obj.class_name, "moved", round(float(moved), 4), "predicted", round(predicted[0][1], 4))
        assert moved > 0.025
        assert abs(moved - predicted[0][1]) < 0.02, (moved, predicted[0][1])
        assert after[2, 2] > 0.95, (obj.class_name, moved, after[:3, :3])  # still standing

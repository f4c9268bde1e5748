"""The arm in physics: the PyBullet backend drives the run's robot by joint control (docs/robots.md,
"Execution by the arm"). Real Panda, real Bullet contacts, no mocks."""

from __future__ import annotations

import numpy as np
import pytest
from msmem_pybullet.simulator import PyBulletSimulator
from msmem_robots.floating import FloatingRobot
from msmem_robots.panda import PandaRobot

from msmem_core.errors import UserError
from msmem_core.testing import FakeSimulator
from msmem_core.testing.conformance import single_object_scene
from msmem_core.world.scene import ObjectSpec, SceneSpec

INTO_SHELF = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Gripper frame pointing into the shelf (+y), fingers closing along x."""


def hand(x: float, y: float, z: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = INTO_SHELF
    t[:3, 3] = (x, y, z)
    return t


@pytest.fixture(scope="module")
def panda() -> PandaRobot:
    return PandaRobot()


@pytest.fixture
def arm_sim(panda):
    sim = PyBulletSimulator()
    sim.attach_robot(panda)
    yield sim
    sim.close()


def test_the_arm_grasps_a_can_and_carries_it_out_of_the_shelf(arm_sim, panda):
    arm_sim.reset(single_object_scene("tomato_soup_can", (0.2, 0.10, 0.0)))
    start = arm_sim.object_poses()[7]
    arm_sim.move_gripper([hand(0.2, -0.08, 0.05)], opening_m=0.08, speed_mps=0.1)
    reached = arm_sim.move_gripper([hand(0.2, 0.10, 0.05)], speed_mps=0.05)
    assert np.linalg.norm(reached[:3, 3] - (0.2, 0.10, 0.05)) < 0.002  # joint control tracks the path
    assert np.linalg.norm(arm_sim.object_poses()[7][:3, 3] - start[:3, 3]) < 0.005  # the open hand slid around it
    closed = arm_sim.set_gripper(0.0)
    assert 0.06 < closed < 0.07  # stopped by the can (6.6 cm across)
    assert arm_sim.held_object() == 7
    arm_sim.move_gripper([hand(0.2, 0.10, 0.08)], speed_mps=0.05)
    arm_sim.move_gripper([hand(0.2, -0.15, 0.08)], speed_mps=0.1)
    assert arm_sim.held_object() == 7
    assert arm_sim.object_poses()[7][1, 3] < -0.1  # out of the shelf with the hand
    assert arm_sim.robot_notes() == []
    # the gripper frame is the robot's own forward kinematics of the simulated joints, times its tool mount
    joints = arm_sim._arm.joint_positions()
    np.testing.assert_allclose(arm_sim.gripper_pose(), panda.flange_pose(joints) @ panda.tool_mount(), atol=1e-6)


def test_the_arm_pushes_what_is_in_its_way_and_restores_exactly(arm_sim):
    scene = SceneSpec(objects=(ObjectSpec(id=0, class_name="sugar_box", position_m=(0.25, 0.12, 0.0)),
                               ObjectSpec(id=1, class_name="foam_brick", position_m=(-0.2, 0.2, 0.0))))
    arm_sim.reset(scene)
    arm_sim.move_gripper([hand(0.25, -0.08, 0.08)], opening_m=0.08)
    token = arm_sim.snapshot()
    before = arm_sim.object_poses()

    def push() -> dict[int, np.ndarray]:
        arm_sim.move_gripper([hand(0.25, 0.16, 0.08)], speed_mps=0.1)
        arm_sim.step(0.5)
        return arm_sim.object_poses()

    after = push()
    moved = np.linalg.norm(after[0][:3, 3] - before[0][:3, 3])
    assert moved > 0.03  # the hand entered where the box stood: physics moved it
    assert np.linalg.norm(after[1][:3, 3] - before[1][:3, 3]) < 1e-3  # the brick is elsewhere
    arm_sim.restore(token)
    for oid, pose in arm_sim.object_poses().items():
        np.testing.assert_allclose(pose, before[oid], atol=1e-9)
    np.testing.assert_allclose(arm_sim.gripper_pose(), hand(0.25, -0.08, 0.08), atol=2e-3)  # the arm came back
    again = push()
    arm_sim.restore(token)
    third = push()
    for oid, pose in third.items():  # restoring and repeating the same calls gives the same result, bit for bit
        np.testing.assert_array_equal(pose, again[oid])
        assert np.linalg.norm(pose[:3, 3] - after[oid][:3, 3]) < 0.01  # (the live run differs by solver warm starts)


def test_a_move_the_arm_cannot_start_is_not_made_and_says_why(arm_sim):
    arm_sim.reset(single_object_scene("foam_brick", (0.0, 0.2, 0.0)))
    arm_sim.park_gripper()
    parked = arm_sim.gripper_pose()
    got = arm_sim.move_gripper([hand(0.0, -3.0, 0.1), hand(0.0, 0.2, 0.1)], opening_m=0.08)
    np.testing.assert_allclose(got, parked, atol=1e-4)  # no teleport, no motion (the hand opened meanwhile)
    notes = arm_sim.robot_notes()
    assert len(notes) == 1
    assert notes[0].startswith("the first waypoint: no IK answer within")
    assert "the arm did not move" in notes[0]
    assert arm_sim.robot_notes() == []  # taken once


def test_a_view_puts_the_wrist_camera_there_and_the_arm_is_in_the_picture(arm_sim, panda):
    from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

    scene = single_object_scene("foam_brick", (0.0, 0.2, 0.0))
    arm_sim.reset(scene)
    views = generate_viewpoints(ViewpointConfig(), scene.shelf)
    view = views[int(np.flatnonzero(panda.reachable_views(views, scene.shelf))[0])]
    obs = arm_sim.observe(view)
    camera = panda.flange_pose(arm_sim._arm.joint_positions()) @ panda.camera_mount()
    assert np.linalg.norm(camera[:3, 3] - view[:3, 3]) < 0.006
    assert np.degrees(np.arccos(np.clip((np.trace(camera[:3, :3].T @ view[:3, :3]) - 1) / 2, -1, 1))) < 2.5
    floating = PyBulletSimulator()
    floating.reset(scene)
    free = floating.observe(view)
    floating.close()
    own = (obs.depth > 0) & (obs.depth < 0.15) & ~((free.depth > 0) & (free.depth < 0.15))
    assert 0.005 < own.mean() < 0.1  # the fingers in front of the lens occlude a few per cent, as a real one's
    assert (obs.labels[own] == 0).all()
    assert (obs.object_ids[own] == -1).all()


def test_a_robot_without_an_arm_keeps_the_floating_gripper():
    sim = PyBulletSimulator()
    sim.attach_robot(FloatingRobot())
    sim.reset(single_object_scene("foam_brick", (0.0, 0.2, 0.0)))
    assert sim._arm is None
    assert sim.robot_notes() == []
    sim.close()


def test_a_backend_that_cannot_load_robots_refuses_in_one_line(panda):
    with pytest.raises(UserError) as err:
        FakeSimulator().attach_robot(panda)
    msg = str(err.value)
    assert "\n" not in msg
    assert "cannot drive robot 'panda'" in msg
    assert "URDF" in msg
    assert "floating" in msg

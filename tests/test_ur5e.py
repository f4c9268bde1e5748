"""The UR5e with a Robotiq 2F-85 (``msmem_robots.ur5e``, docs/explanation/robots.md "The UR5e"): its URDF joined from
airo-models' files, the robot conformance suite with an independent forward kinematics, and the arm in
PyBullet making the same scripted moves as the Panda (``tests/support/arm_checks.py``) with its linkage
hand. Real pybullet, no mocks."""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from msmem_pybullet.simulator import PyBulletSimulator
from msmem_robots.config import UR5eConfig
from msmem_robots.ur5e import GRIPPER_GEARING, GRIPPER_JOINTS, UR5eRobot, joined_urdf

from msmem_core.errors import UserError
from msmem_core.testing import robot_conformance
from tests.support import arm_checks


@pytest.fixture(scope="module")
def ur5e() -> UR5eRobot:
    return UR5eRobot()


def test_the_joined_urdf_has_the_gripper_at_tool0_and_no_drake_tags(tmp_path, monkeypatch):
    monkeypatch.setenv("MSMEM_CACHE_DIR", str(tmp_path))
    path = joined_urdf()
    assert path.parent == tmp_path / "robots"
    text = path.read_text()
    assert "drake" not in text
    assert 'name="tool0-gripper"' in text
    assert all(f'name="{j}"' in text for j in GRIPPER_JOINTS)
    meshes = [m.get("filename", "") for m in ET.parse(path).getroot().iter("mesh")]
    assert meshes
    assert all(m.startswith("/") for m in meshes)
    assert all(os.path.isfile(m) for m in meshes)
    stamp = path.stat().st_mtime_ns
    assert joined_urdf() == path
    assert path.stat().st_mtime_ns == stamp


def test_the_ur5e_conforms_and_reaches_more_views_than_the_panda():
    report = robot_conformance(lambda: UR5eRobot(UR5eConfig(disk_cache=False)))
    assert (report.name, report.arm, report.views) == ("ur5e", True, 300)
    assert report.reachable_views == 288  # docs/explanation/robots.md (the Panda: 265)
    assert report.checked == 6


def test_the_linkage_hand_opens_85_mm_and_its_joints_follow_the_driver(ur5e):
    m = ur5e.model()
    assert m.finger_joints == GRIPPER_JOINTS
    assert m.finger_gearing == GRIPPER_GEARING
    q, w = np.array(m.finger_opening).T
    assert q[0] == 0.0
    assert np.all(np.diff(q) > 0)
    assert np.all(np.diff(w) < 0)  # the driving joint closes the hand
    assert w[0] == pytest.approx(0.085, abs=0.002)  # the 2F-85's stroke
    assert w[-1] < 0.005
    assert m.finger_pads == ("left_inner_finger_pad", "right_inner_finger_pad")


CHECKS = {
    "grasp and carry out": lambda sim, bot: arm_checks.check_grasp_and_carry_out(sim, bot),
    "push and restore exactly": lambda sim, bot: arm_checks.check_push_and_exact_restore(sim, 1e-9),
    "the push skill's forward pushes": lambda sim, bot: arm_checks.check_forward_pushes_of_the_push_skill(sim, bot),
    "an unreachable start is not made": lambda sim, bot: arm_checks.check_unreachable_start_is_not_made(sim),
    "a view moves the wrist camera": lambda sim, bot: arm_checks.check_view_moves_the_wrist_camera(
        sim, bot, PyBulletSimulator),
}


@pytest.mark.parametrize("check", list(CHECKS))
def test_the_ur5e_makes_the_panda_s_moves_in_pybullet(ur5e, check):
    sim = PyBulletSimulator()
    sim.attach_robot(ur5e)
    try:
        CHECKS[check](sim, ur5e)
    finally:
        sim.close()


def test_the_grasp_skill_plans_front_grasps_the_ur5e_makes(ur5e):
    sim, observe = PyBulletSimulator(), PyBulletSimulator()
    sim.attach_robot(ur5e)
    try:
        arm_checks.check_the_grasp_skill_plans_a_grasp_the_arm_makes(sim, ur5e, observe)
    finally:
        sim.close()
        observe.close()


def test_sapien_refuses_the_linkage_hand_in_one_line(ur5e):
    pytest.importorskip("sapien")
    from msmem_sapien.config import SapienConfig
    from msmem_sapien.simulator import SapienSimulator

    sim = SapienSimulator(SapienConfig(renderer="native"))
    try:
        with pytest.raises(UserError) as err:
            sim.attach_robot(ur5e)
    finally:
        sim.close()
    msg = str(err.value)
    assert "\n" not in msg
    assert "linkage" in msg
    assert "'ur5e'" in msg
    assert "pybullet" in msg

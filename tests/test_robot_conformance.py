"""The robot conformance suite (``msmem_core.testing.robot_conformance``): both shipped robots pass it, and
each rule catches a robot that breaks it (real pybullet IK and forward kinematics, no mocks)."""

from __future__ import annotations

import numpy as np
import pytest
from msmem_robots.config import PandaConfig
from msmem_robots.floating import FloatingRobot
from msmem_robots.panda import STARTS, PandaRobot

from msmem_core.interfaces import Reach
from msmem_core.testing import ConformanceError, ConformanceUsageError, robot_conformance


def panda(cls: type[PandaRobot] = PandaRobot):
    return lambda: cls(PandaConfig(disk_cache=False))


def test_the_panda_conforms_and_its_answers_are_verified_independently():
    report = robot_conformance(panda())
    assert report.name == "panda"
    assert report.arm
    assert report.views == 300
    assert report.reachable_views == 265  # docs/explanation/robots.md
    assert report.checked == 6


def test_floating_conforms_by_its_registered_name():
    report = robot_conformance("floating")
    assert (report.arm, report.reachable_views, report.checked) == (False, 300, 0)


def test_a_robot_instance_is_not_a_factory():
    with pytest.raises(ConformanceUsageError, match="pass a factory"):
        robot_conformance(FloatingRobot())


class _OutsideLimits(PandaRobot):
    def ik(self, flange_pose, shelf):
        r = super().ik(flange_pose, shelf)
        if not r.reachable:
            return r
        q = list(r.joints)
        q[3] = self.model().joint_upper[3] + 0.3
        return Reach(True, tuple(q), r.position_error_m, r.orientation_error_deg)


class _Liar(PandaRobot):
    """Says reachable with a configuration that puts the flange elsewhere."""

    def ik(self, flange_pose, shelf):
        r = super().ik(flange_pose, shelf)
        return Reach(True, STARTS[0]) if r.reachable else r


class _NoCollisionCheck(PandaRobot):
    def _hits(self):
        return []


class _OptimisticViews(PandaRobot):
    def reachable_views(self, viewpoints, shelf):
        return np.ones(len(viewpoints), dtype=bool)


class _ShyFloating(FloatingRobot):
    def reachable_views(self, viewpoints, shelf):
        out = np.ones(len(viewpoints), dtype=bool)
        out[0] = False
        return out


class _VaguePaths(PandaRobot):
    def reach_path(self, tool_poses, shelf, step_m=0.02):
        r = super().reach_path(tool_poses, shelf, step_m)
        return r if r.reachable else Reach(False, None, reason="no")


class _ArmBesideItself(PandaRobot):  # draws the arm 20 cm off to the side
    def link_points(self, joints):
        return super().link_points(joints) + np.array([0.2, 0.0, 0.0])


class _ArmWithoutTheHand(PandaRobot):  # draws the arm only up to its elbow
    def link_points(self, joints):
        return super().link_points(joints)[:4]


@pytest.mark.parametrize(("factory", "rule"), [
    (panda(_ArmBesideItself), "link_points must start at the base"),
    (panda(_ArmWithoutTheHand), "link_points does not pass the flange"),
    (panda(_OutsideLimits), "leaves the joint limits at panda_joint4"),
    (panda(_Liar), "forward kinematics of the URDF puts the flange"),
    (panda(_NoCollisionCheck), "inside the shelf's bottom board was called reachable|inside a shelf board"),
    (panda(_OptimisticViews), "reachable_views says view .* is reachable, reach_camera says not"),
    (panda(_VaguePaths), "must name the path point"),
    (_ShyFloating, "without an arm .* must reach every view; it reaches 299 of 300"),
])
def test_each_rule_catches_a_robot_that_breaks_it(factory, rule):
    with pytest.raises(ConformanceError, match=rule):
        robot_conformance(factory)

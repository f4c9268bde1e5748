"""The arm in physics: the PyBullet and SAPIEN backends drive the run's robot by joint control
(docs/explanation/robots.md, "Execution by the arm"). Real Panda, real Bullet and PhysX contacts, no mocks: the same
scripted moves (``tests/support/arm_checks.py``) hold both backends to the same outcomes. SAPIEN's
cases need the optional extra and SAPIEN's renderer (its URDF loader builds visuals; ``make sapien``
sets up a CPU Vulkan driver) and are skipped without them."""

from __future__ import annotations

import pytest
from msmem_pybullet.simulator import PyBulletSimulator
from msmem_robots.floating import FloatingRobot
from msmem_robots.panda import PandaRobot

from msmem_core.errors import UserError
from msmem_core.testing import FakeSimulator
from msmem_core.testing.conformance import single_object_scene
from tests.support.arm_checks import (
    check_forward_pushes_of_the_push_skill,
    check_grasp_and_carry_out,
    check_push_and_exact_restore,
    check_the_grasp_skill_plans_a_grasp_the_arm_makes,
    check_unreachable_start_is_not_made,
    check_view_moves_the_wrist_camera,
)


@pytest.fixture(scope="module")
def panda() -> PandaRobot:
    return PandaRobot()


def _sapien_ready() -> tuple[bool, str]:
    try:
        from msmem_sapien.camera import native_renderer
    except ImportError:
        return False, "the SAPIEN backend needs the optional extra: pip install 'msmem[sapien]'"
    ok, detail = native_renderer()
    return ok, f"{detail}: SAPIEN loads URDFs only with its renderer (`make sapien` installs a CPU Vulkan driver)"


SAPIEN_OK, SAPIEN_WHY = _sapien_ready()
BACKENDS = [pytest.param("pybullet"),
            pytest.param("sapien", marks=pytest.mark.skipif(not SAPIEN_OK, reason=SAPIEN_WHY))]


def bare(backend: str):  # type: ignore[no-untyped-def]
    """A simulator of ``backend`` with the floating gripper (no robot attached)."""
    if backend == "pybullet":
        return PyBulletSimulator()
    from msmem_sapien.config import SapienConfig
    from msmem_sapien.simulator import SapienSimulator

    return SapienSimulator(SapienConfig(renderer="native"))


@pytest.fixture(params=BACKENDS)
def backend(request) -> str:
    return request.param


@pytest.fixture
def arm_sim(panda, backend):
    sim = bare(backend)
    sim.attach_robot(panda)
    yield sim
    sim.close()


def test_the_arm_grasps_a_can_and_carries_it_out_of_the_shelf(arm_sim, panda):
    check_grasp_and_carry_out(arm_sim, panda)


def test_the_grasp_skill_plans_front_grasps_the_arm_makes(arm_sim, panda):
    observe = PyBulletSimulator()
    try:
        check_the_grasp_skill_plans_a_grasp_the_arm_makes(arm_sim, panda, observe)
    finally:
        observe.close()


def test_the_arm_pushes_what_is_in_its_way_and_restores_exactly(arm_sim, backend):
    check_push_and_exact_restore(arm_sim, restore_atol=1e-9 if backend == "pybullet" else 1e-6)


def test_the_arm_makes_the_push_skills_forward_pushes_as_predicted(arm_sim, panda):
    check_forward_pushes_of_the_push_skill(arm_sim, panda)


def test_a_move_the_arm_cannot_start_is_not_made_and_says_why(arm_sim):
    check_unreachable_start_is_not_made(arm_sim)


def test_a_view_puts_the_wrist_camera_there_and_the_arm_is_in_the_picture(arm_sim, panda, backend):
    check_view_moves_the_wrist_camera(arm_sim, panda, lambda: bare(backend))


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

"""The PyBullet backend: conformance suite, structured seeded label noise, a scripted push and a top grasp."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pybullet")

from msmem_pybullet.simulator import PyBulletConfig, PyBulletSimulator

from msmem_core.testing.conformance import push_along_y, simulator_conformance, single_object_scene
from tests.support.sim_checks import (
    check_label_noise_relabels_whole_objects_and_follows_the_seed,
    check_restoring_a_snapshot_and_repeating_a_push_reproduces_it_exactly,
    check_top_grasp_lifts_by_friction,
    check_two_simulators_in_one_process_do_not_interfere,
)


def test_pybullet_backend_passes_the_simulator_conformance_suite() -> None:
    simulator_conformance(lambda: PyBulletSimulator(PyBulletConfig(label_noise=0.0)), noise_free=True)


def test_label_noise_relabels_whole_objects_and_follows_the_seed() -> None:
    check_label_noise_relabels_whole_objects_and_follows_the_seed(
        lambda seed: PyBulletSimulator(label_noise=0.5, seed=seed)
    )


def test_closed_gripper_pushes_a_box_back_without_toppling_it() -> None:
    scene = single_object_scene("potted_meat_can", (0.0, 0.12, 0.0))
    box = scene.objects[0]
    sim = PyBulletSimulator(label_noise=0.0)
    try:
        sim.reset(scene)
        before = sim.object_poses()[box.id]
        half_depth = box.object_class.parts[0].size_m[1] / 2  # the fingers first touch the front face
        push_along_y(sim, box, 0.10 + box.object_class.footprint_radius_m - half_depth, height_m=0.03)
        after = sim.object_poses()[box.id]
    finally:
        sim.close()
    moved = after[:3, 3] - before[:3, 3]
    assert 0.05 < moved[1] < 0.15, f"box moved {moved[1] * 100:.1f} cm along +y"
    assert abs(moved[0]) < 0.02
    assert after[2, 2] > np.cos(np.radians(10)), "box tipped over"


def test_top_grasp_lifts_a_sugar_box_by_friction_alone() -> None:
    sim = PyBulletSimulator(label_noise=0.0)
    try:
        check_top_grasp_lifts_by_friction(sim, single_object_scene("sugar_box", (-0.1, 0.2, 0.0)), 0.13, 0.185, 0.19)
    finally:
        sim.close()


def test_restoring_a_snapshot_and_repeating_a_push_reproduces_it_exactly() -> None:
    check_restoring_a_snapshot_and_repeating_a_push_reproduces_it_exactly(PyBulletSimulator(label_noise=0.0))


def test_two_simulators_in_one_process_do_not_interfere() -> None:
    check_two_simulators_in_one_process_do_not_interfere(lambda: PyBulletSimulator(label_noise=0.0))


def test_config_rejects_unknown_options() -> None:
    with pytest.raises(ValueError, match="extra"):
        PyBulletConfig(labelnoise=0.1)  # type: ignore[call-arg]

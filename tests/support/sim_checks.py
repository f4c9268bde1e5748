"""Checks the PyBullet and SAPIEN backend tests share, beyond ``msmem_core.testing.conformance``:
seeded per-object label noise, exact repeats after ``restore``, independent instances and a top grasp."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from msmem_core.interfaces import GRIPPER_ID, Simulator
from msmem_core.testing.conformance import (
    conformance_scene,
    front_view,
    gripper_pose,
    push_along_y,
    single_object_scene,
)
from msmem_core.world.scene import ObjectSpec, SceneSpec, object_class


def labels_per_view(noisy: Callable[[int], Simulator], seed: int, views: int = 6) -> list[dict[int, int]]:
    """The label each visible object carries in each of ``views`` renders of the same view, by the
    simulator ``noisy(seed)`` (label noise on) of the conformance scene."""
    scene = conformance_scene()
    sim = noisy(seed)
    try:
        sim.reset(scene)
        out = []
        for _ in range(views):
            obs = sim.observe(front_view(scene))
            assert obs.object_ids is not None
            per_object = {}
            for oid in np.unique(obs.object_ids[obs.object_ids >= 0]):
                labels = np.unique(obs.labels[obs.object_ids == oid])
                assert len(labels) == 1, f"object {oid} carries labels {labels} in one view"
                per_object[int(oid)] = int(labels[0])
            out.append(per_object)
        return out
    finally:
        sim.close()


def check_label_noise_relabels_whole_objects_and_follows_the_seed(noisy: Callable[[int], Simulator]) -> None:
    """``noisy(seed)``: a simulator with label noise 0.5 and that seed."""
    scene = conformance_scene()
    first = labels_per_view(noisy, seed=3)
    for views in first:
        assert views, "objects should be visible"
        for oid, label in views.items():
            cls = scene.objects[oid].object_class
            assert label in (cls.class_id, object_class(cls.confusable_with or cls.name).class_id)
    flips = [label != scene.objects[oid].class_id for views in first for oid, label in views.items()]
    assert any(flips), "with noise 0.5 some objects should be relabelled"
    assert not all(flips), "with noise 0.5 some objects should keep their class"
    assert labels_per_view(noisy, seed=3) == first, "the same seed must give the same noise"
    assert labels_per_view(noisy, seed=4) != first, "another seed should give other noise"


def check_restoring_a_snapshot_and_repeating_a_push_reproduces_it_exactly(sim: Simulator) -> None:
    """Object and gripper poses after restore + push + 0.2 s match bit for bit (closes ``sim``)."""
    scene = conformance_scene()
    try:
        sim.reset(scene)
        token = sim.snapshot()
        runs = []
        for _ in range(2):
            sim.restore(token)
            push_along_y(sim, scene.objects[1], 0.05)
            sim.step(0.2)
            runs.append((sim.object_poses(), sim.gripper_pose()))
    finally:
        sim.close()
    for oid in runs[0][0]:
        np.testing.assert_array_equal(runs[0][0][oid], runs[1][0][oid])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def check_two_simulators_in_one_process_do_not_interfere(make: Callable[[], Simulator]) -> None:
    a, b = make(), make()
    try:
        a.reset(single_object_scene("foam_brick", (0.1, 0.2, 0.0), object_id=1))
        b.reset(SceneSpec(objects=(ObjectSpec(id=2, class_name="sugar_box", position_m=(-0.2, 0.2, 0.0)),)))
        a.remove_object(1)
        assert a.object_poses() == {}
        assert set(b.object_poses()) == {2}
        assert not np.any(a.observe(front_view(conformance_scene())).object_ids == 2)
        with pytest.raises(ValueError, match="not a snapshot"):
            a.restore(b.snapshot())
    finally:
        a.close()
        b.close()


def check_top_grasp_lifts_by_friction(
    sim: Simulator, scene: SceneSpec, tip_z: float, start_z: float, lift_z: float
) -> np.ndarray:
    """Reset to ``scene`` (one object at x, y = -0.1, 0.2), come down from ``start_z`` to ``tip_z``
    open, close across the object's y side, lift to ``lift_z``: the object is held and rises by more
    than 5 cm. Returns the lifted gripper pose."""
    obj = scene.objects[0]
    width = obj.object_class.parts[0].size_m[1]

    def above(z: float) -> np.ndarray:
        return gripper_pose((-0.1, 0.2, z), (0, 0, -1), (0, 1, 0))  # close across the y side

    sim.reset(scene)
    z0 = sim.object_poses()[obj.id][2, 3]
    sim.move_gripper([above(start_z), above(tip_z)], opening_m=0.08)
    assert abs(sim.set_gripper(0.0) - width) < 0.004
    assert sim.held_object() == obj.id
    lifted = sim.move_gripper([above(lift_z)])
    assert abs(lifted[2, 3] - lift_z) < 0.005
    rose = sim.object_poses()[obj.id][2, 3] - z0
    name = sim.capabilities().name
    assert rose > 0.05, f"{name}: {obj.class_name} rose {rose * 100:.1f} cm with a {(lift_z - tip_z) * 100:.0f} cm lift"
    assert sim.held_object() == obj.id
    assert any(GRIPPER_ID in (c.body_a, c.body_b) and obj.id in (c.body_a, c.body_b) for c in sim.contacts())
    return lifted

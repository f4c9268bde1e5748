"""The SAPIEN backend: conformance on both camera paths, and consistency with the PyBullet reference on
seeded scenes (settled poses, depth images, a scripted push, top grasps) and through whole episodes."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from scipy import ndimage

with warnings.catch_warnings():  # SAPIEN warns when it falls back to its bundled Vulkan loader
    warnings.simplefilter("ignore", UserWarning)
    pytest.importorskip("sapien", reason="the SAPIEN backend needs the optional extra: pip install 'msmem[sapien]'")
pytest.importorskip("pybullet", reason="the cross-backend checks compare with the PyBullet backend")

from msmem_pybullet.simulator import PyBulletConfig, PyBulletSimulator
from msmem_sapien.config import SapienConfig
from msmem_sapien.simulator import SapienSimulator, native_renderer

from msmem_core.camera import CameraConfig
from msmem_core.config import load_config
from msmem_core.geometry import rotation_angle_deg
from msmem_core.interfaces import GRIPPER_ID, Simulator
from msmem_core.plugins import get_plugin_manager
from msmem_core.plugins.manager import ComponentRef
from msmem_core.runner import build_episode, run_episode
from msmem_core.scene import ObjectSpec, SceneSpec, object_class
from msmem_core.scenegen import SceneGenConfig, generate_scene
from msmem_core.testing.conformance import (
    conformance_scene,
    front_view,
    gripper_pose,
    push_along_y,
    simulator_conformance,
    single_object_scene,
)
from msmem_core.viewpoints import ViewpointConfig, default_start_view, generate_viewpoints

SMALL_CAMERA = CameraConfig(width_px=160, height_px=120)
SEEDS = (0, 1)
VIEWS = (17, 150, 283)
"""Viewpoints compared besides the start view: left, middle and right grids."""

NATIVE_OK, NATIVE_DETAIL = native_renderer()
needs_native = pytest.mark.skipif(
    not NATIVE_OK,
    reason=f"{NATIVE_DETAIL}: SAPIEN's renderer needs a Vulkan device; on a CPU run "
    "simulators/msmem_sapien/setup_lavapipe.sh (or `make sapien`) to install Mesa 25 lavapipe",
)
RENDERERS = [pytest.param("raycast"), pytest.param("native", marks=needs_native)]


def sapien_sim(renderer: str = "raycast", **kwargs: Any) -> SapienSimulator:
    return SapienSimulator(SapienConfig(label_noise=0.0, renderer=renderer, **kwargs))


@pytest.fixture(scope="module")
def seeded_scenes() -> list[SceneSpec]:
    return [generate_scene(seed, SceneGenConfig(require_hard=False)) for seed in SEEDS]


@pytest.fixture(scope="module")
def pybullet_small() -> Iterator[PyBulletSimulator]:
    sim = PyBulletSimulator(PyBulletConfig(label_noise=0.0, camera=SMALL_CAMERA))
    yield sim
    sim.close()


# ------------------------------------------------------------------------------------------- conformance
@pytest.mark.parametrize("renderer", RENDERERS)
def test_sapien_backend_passes_the_simulator_conformance_suite(renderer: str) -> None:
    simulator_conformance(lambda: sapien_sim(renderer), noise_free=True)


@needs_native
def test_native_renderer_and_raycast_camera_see_the_same_picture() -> None:
    scene = conformance_scene()
    native, raycast = sapien_sim("native"), sapien_sim("raycast")
    try:
        assert native.camera_path == "native"
        assert raycast.camera_path == "raycast"
        native.reset(scene)
        raycast.reset(scene)
        a, b = native.observe(front_view(scene)), raycast.observe(front_view(scene))
    finally:
        native.close()
        raycast.close()
    assert a.meta["camera"] == "native"
    assert b.meta["camera"] == "raycast"
    assert a.object_ids is not None
    assert b.object_ids is not None
    assert np.mean(a.object_ids == b.object_ids) > 0.998
    both = (a.depth > 0) & (b.depth > 0)
    assert np.mean(both == ((a.depth > 0) | (b.depth > 0))) > 0.998
    assert np.quantile(np.abs(a.depth - b.depth)[both], 0.99) < 1e-3


def _labels_per_view(seed: int, views: int = 6) -> list[dict[int, int]]:
    """The label each visible object carries in each of ``views`` renders of the same view."""
    scene = conformance_scene()
    sim = SapienSimulator(label_noise=0.5, seed=seed, renderer="raycast")
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


def test_label_noise_relabels_whole_objects_and_follows_the_seed() -> None:
    scene = conformance_scene()
    first = _labels_per_view(seed=3)
    for views in first:
        assert views, "objects should be visible"
        for oid, label in views.items():
            cls = scene.objects[oid].object_class
            assert label in (cls.class_id, object_class(cls.confusable_with or cls.name).class_id)
    flips = [label != scene.objects[oid].class_id for views in first for oid, label in views.items()]
    assert any(flips), "with noise 0.5 some objects should be relabelled"
    assert not all(flips), "with noise 0.5 some objects should keep their class"
    assert _labels_per_view(seed=3) == first, "the same seed must give the same noise"
    assert _labels_per_view(seed=4) != first, "another seed should give other noise"


def test_restoring_a_snapshot_and_repeating_a_push_reproduces_it_exactly() -> None:
    scene = conformance_scene()
    sim = sapien_sim()
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


def test_two_simulators_in_one_process_do_not_interfere() -> None:
    a, b = sapien_sim(), sapien_sim()
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


def test_config_rejects_unknown_options_and_the_plugin_builds_the_backend() -> None:
    with pytest.raises(ValueError, match="extra"):
        SapienConfig(labelnoise=0.1)  # type: ignore[call-arg]
    sim = get_plugin_manager().build("simulator", ComponentRef(name="sapien", params={"renderer": "raycast"}))
    try:
        assert isinstance(sim, SapienSimulator)
        assert sim.capabilities().name == "sapien"
        assert "ray-cast" in sim.capabilities().notes
    finally:
        sim.close()


# ------------------------------------------------------------------------------------------- vs PyBullet
def test_settled_poses_agree_with_pybullet(seeded_scenes: list[SceneSpec], pybullet_small: PyBulletSimulator) -> None:
    sim = sapien_sim(camera=SMALL_CAMERA)
    try:
        for scene in seeded_scenes:
            pybullet_small.reset(scene)
            sim.reset(scene)
            a, b = pybullet_small.object_poses(), sim.object_poses()
            assert set(a) == set(b)
            agree = [
                bool(np.linalg.norm(a[i][:3, 3] - b[i][:3, 3]) < 0.01) and rotation_angle_deg(a[i], b[i]) < 5.0
                for i in a
            ]
            assert np.mean(agree) >= 0.9, f"scene {scene.name}: only {np.mean(agree):.0%} of objects agree"
    finally:
        sim.close()


def depth_agreement(a: np.ndarray, b: np.ndarray, far: float, jump_m: float = 0.02, margin_px: int = 2) -> float:
    """Fraction of pixels more than ``margin_px`` from a depth discontinuity (a jump over ``jump_m``
    between neighbours, or the edge of the returns, in either image) whose depths agree within 1 cm."""
    edges = np.zeros(a.shape, dtype=bool)
    for d in (a, b):
        d = np.where(d > 0, d, 2 * far)  # no return: farther than anything
        gx = np.abs(np.diff(d, axis=1)) > jump_m
        gy = np.abs(np.diff(d, axis=0)) > jump_m
        edges[:, 1:] |= gx
        edges[:, :-1] |= gx
        edges[1:] |= gy
        edges[:-1] |= gy
    keep = ~ndimage.binary_dilation(edges, iterations=margin_px)
    return float(np.mean(np.abs(a - b)[keep] < 0.01))


@pytest.mark.parametrize("renderer", RENDERERS)
def test_depth_images_agree_with_pybullet(
    renderer: str, seeded_scenes: list[SceneSpec], pybullet_small: PyBulletSimulator
) -> None:
    sim = sapien_sim(renderer, camera=SMALL_CAMERA)
    vp_cfg = ViewpointConfig()
    try:
        for scene in seeded_scenes:
            pybullet_small.reset(scene)
            sim.reset(scene)
            viewpoints = generate_viewpoints(vp_cfg, scene.shelf)
            for v in (default_start_view(vp_cfg), *VIEWS):
                a, b = pybullet_small.observe(viewpoints[v]), sim.observe(viewpoints[v])
                agree = depth_agreement(a.depth, b.depth, SMALL_CAMERA.far_m)
                assert agree > 0.99, f"scene {scene.name}, view {v}: depth agrees on {agree:.2%} of pixels"
    finally:
        sim.close()


def _push_distance(sim: Simulator, scene: SceneSpec, target: ObjectSpec, distance: float) -> float:
    sim.reset(scene)
    before = sim.object_poses()[target.id]
    push_along_y(sim, target, distance)
    after = sim.object_poses()[target.id]
    assert after[2, 2] > np.cos(np.radians(10)), "the pushed object tipped over"
    return float(np.linalg.norm(after[:2, 3] - before[:2, 3]))


@pytest.mark.parametrize(
    ("class_name", "distance"), [("potted_meat_can", 0.12), ("tomato_soup_can", 0.10), ("sugar_box", 0.08)]
)
def test_scripted_push_moves_the_target_alike(class_name: str, distance: float) -> None:
    scene = single_object_scene(class_name, (0.05, 0.12, 0.0))
    pb, sp = PyBulletSimulator(label_noise=0.0), sapien_sim()
    try:
        moved = [_push_distance(sim, scene, scene.objects[0], distance) for sim in (pb, sp)]
    finally:
        pb.close()
        sp.close()
    assert moved[0] > 0.03, f"pybullet moved the {class_name} only {moved[0] * 100:.1f} cm"
    assert abs(moved[1] - moved[0]) <= 0.3 * moved[0], f"moved {moved[1] * 100:.1f} cm vs {moved[0] * 100:.1f} cm"


def _front_object_with_a_neighbour_behind(scene: SceneSpec) -> ObjectSpec:
    """The front-most object that a push along +y drives into another one (so collateral motion counts)."""
    for o in sorted(scene.objects, key=lambda o: o.position_m[1]):
        r = o.object_class.footprint_radius_m
        for other in scene.objects:
            dx, dy = other.position_m[0] - o.position_m[0], other.position_m[1] - o.position_m[1]
            if abs(dx) < r and 0 < dy < r + other.object_class.footprint_radius_m + 0.03:
                return o
    raise AssertionError(f"scene {scene.name}: no object has a neighbour right behind it")


def test_scripted_push_in_a_seeded_scene_moves_target_and_neighbours_alike(seeded_scenes: list[SceneSpec]) -> None:
    pb, sp = PyBulletSimulator(label_noise=0.0), sapien_sim()
    try:
        for scene in seeded_scenes:
            target = _front_object_with_a_neighbour_behind(scene)
            moved = []
            for sim in (pb, sp):
                sim.reset(scene)
                before = sim.object_poses()
                push_along_y(sim, target, 0.08)
                after = sim.object_poses()
                d = {i: float(np.linalg.norm(after[i][:2, 3] - before[i][:2, 3])) for i in before}
                moved.append((d[target.id], sum(d.values()) - d[target.id]))
            (t_pb, n_pb), (t_sp, n_sp) = moved
            what = f"scene {scene.name}, {target.class_name}: target {t_sp * 100:.1f} vs {t_pb * 100:.1f} cm"
            assert t_pb > 0.02, what
            assert abs(t_sp - t_pb) <= 0.3 * t_pb, what
            assert abs(n_sp - n_pb) <= 0.3 * n_pb + 0.005, f"{what}; neighbours {n_sp * 100:.1f} vs {n_pb * 100:.1f} cm"
    finally:
        pb.close()
        sp.close()


@pytest.mark.parametrize(("class_name", "tip_z"), [("sugar_box", 0.13), ("foam_brick", 0.015)])
def test_top_grasp_of_an_isolated_object_succeeds_on_both_backends(class_name: str, tip_z: float) -> None:
    scene = single_object_scene(class_name, (-0.1, 0.2, 0.0))
    obj = scene.objects[0]
    width = obj.object_class.parts[0].size_m[1]

    def above(z: float) -> np.ndarray:
        return gripper_pose((-0.1, 0.2, z), (0, 0, -1), (0, 1, 0))  # close across the narrow side

    for make in (lambda: PyBulletSimulator(label_noise=0.0), sapien_sim):
        sim: Simulator = make()
        try:
            sim.reset(scene)
            z0 = sim.object_poses()[obj.id][2, 3]
            sim.move_gripper([above(tip_z + 0.06), above(tip_z)], opening_m=0.08)
            assert abs(sim.set_gripper(0.0) - width) < 0.004
            assert sim.held_object() == obj.id
            lifted = sim.move_gripper([above(tip_z + 0.06)])  # the palm then stays clear of the top board
            assert abs(lifted[2, 3] - (tip_z + 0.06)) < 0.005
            rose = sim.object_poses()[obj.id][2, 3] - z0
            assert rose > 0.05, f"{sim.capabilities().name}: {class_name} rose {rose * 100:.1f} cm with a 6 cm lift"
            assert sim.held_object() == obj.id
            assert any(GRIPPER_ID in (c.body_a, c.body_b) and obj.id in (c.body_a, c.body_b) for c in sim.contacts())
            out = lifted.copy()
            out[1, 3] = -0.25  # retreat out of the shelf front
            sim.move_gripper([out])
            assert sim.held_object() == obj.id, f"{sim.capabilities().name}: dropped during the retreat"
        finally:
            sim.close()


# ------------------------------------------------------------------------------------------- episodes
EPISODE = {
    "camera": {"width_px": 160, "height_px": 120},
    "ig": {"ray_stride_px": 4},
    "scene": {"generator": {"require_hard": False}},
    "steps": 3,
    "seed": 5,
}


def _episode_scene() -> SceneSpec:
    return SceneSpec(name="three", objects=(
        ObjectSpec(id=0, class_name="cracker_box", position_m=(-0.15, 0.08, 0.0)),
        ObjectSpec(id=1, class_name="tomato_soup_can", position_m=(-0.15, 0.25, 0.0)),
        ObjectSpec(id=2, class_name="sugar_box", position_m=(0.2, 0.2, 0.0)),
    ))


@pytest.mark.parametrize("simulator", ["pybullet", "sapien"])
def test_view_only_episode_runs_unchanged_on_each_backend(simulator: str, tmp_path) -> None:
    cfg = load_config("view-only", None, {**EPISODE, "simulator": {"name": simulator}})
    ep = build_episode(cfg, get_plugin_manager(), scene=_episode_scene())
    assert ep.sim.capabilities().name == simulator
    final = run_episode(ep, tmp_path)
    ep.sim.close()
    assert final["actions"] == {"view": 3}
    assert len({r["action"]["view"] for r in ep.records}) == 3
    assert final["occupancy_iou"] > final["initial"]["occupancy_iou"]
    assert final["observable_iou"] > 0.3
    assert (tmp_path / "steps.jsonl").is_file()

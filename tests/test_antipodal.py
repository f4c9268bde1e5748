"""Antipodal ground truth: kept grasps are antipodal, narrow enough and collision-free (rechecked by
independent means), every class the gripper can span has grasps, neighbours and shelf boards veto
grasps in a scene, and the per-class cache round-trips."""

from __future__ import annotations

import msmem_grasp.antipodal as ap
import numpy as np
import pytest
import trimesh
from msmem_grasp.antipodal import AntipodalConfig, GraspSet, Solids, class_grasps, grasps_in_scene, gripper_boxes

from msmem_core.testing.builders import convex_copy
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.meshes import class_mesh
from msmem_core.world.scene import OBJECT_CLASSES, ObjectSpec, SceneSpec, object_class

GRIPPER = GripperSpec()
COS_CONE = 1 / np.sqrt(1 + 0.5**2)  # friction cone half-angle atan(0.5)


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory):
    return tmp_path_factory.mktemp("antipodal")


def _box_normal(points: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Outward normal of the nearest face of an axis-aligned box centred at (0, 0, half_z)."""
    local = points - [0.0, 0.0, half[2]]
    gap = half - np.abs(local)  # distance to the face pair of each axis
    axis = np.argmin(gap, axis=1)
    n = np.zeros_like(points)
    n[np.arange(len(points)), axis] = np.sign(local[np.arange(len(points)), axis])
    return n


def _gripper_hits(grasps: GraspSet, solids: Solids, rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """Independent check: points sampled in the finger/palm volumes that fall inside any solid."""
    opening = np.minimum(grasps.width + 0.01, GRIPPER.max_opening_m)
    centre, rot, half = gripper_boxes(grasps.poses(), opening, GRIPPER)
    hit = np.zeros(len(centre), dtype=bool)
    for j in range(len(centre)):
        pts = rng.uniform(-1, 1, (n, 3)) * half[j] @ rot[j].T + centre[j]
        hit[j] = solids.contains(pts).any()
    return hit.reshape(-1, 3).any(axis=1)


def test_box_grasps_are_antipodal_narrow_and_collision_free(cache):
    name = "potted_meat_can"  # a 10.1 x 5.1 x 8.3 cm box
    grasps = class_grasps(name, directory=cache)
    half = np.asarray(object_class(name).parts[0].size_m) / 2
    assert len(grasps) > 1000
    assert (grasps.width <= GRIPPER.max_opening_m).all()
    assert (grasps.width > 0).all()
    np.testing.assert_allclose(np.linalg.norm(grasps.opposite - grasps.contacts, axis=1), grasps.width, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(grasps.baseline, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", grasps.approach, grasps.baseline), 0.0, atol=1e-12)
    # both contacts lie on the box surface and b is inside both friction cones
    local = grasps.contacts - [0.0, 0.0, half[2]]
    assert np.abs(np.abs(local) - half).min(axis=1).max() < 1e-9
    n_c, n_o = _box_normal(grasps.contacts, half), _box_normal(grasps.opposite, half)
    assert (np.einsum("ij,ij->i", -n_c, grasps.baseline) >= COS_CONE - 1e-9).all()
    assert (np.einsum("ij,ij->i", n_o, grasps.baseline) >= COS_CONE - 1e-9).all()
    # the gripper does not touch the object: trimesh/fcl on the meshes, and volume sampling
    rng = np.random.default_rng(0)
    sample = grasps.subset(rng.choice(len(grasps), 200, replace=False))
    manager = trimesh.collision.CollisionManager()
    manager.add_object("object", class_mesh(name))
    opening = np.minimum(sample.width + 0.01, GRIPPER.max_opening_m)
    centre, rot, box_half = gripper_boxes(sample.poses(), opening, GRIPPER)
    for c, r, h in zip(centre, rot, box_half, strict=True):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = r, c
        assert not manager.in_collision_single(trimesh.creation.box(extents=2 * h), transform=pose)
    assert not _gripper_hits(sample, Solids.from_parts(object_class(name).parts), rng).any()


def _random_grasps(rng: np.random.Generator, n: int) -> GraspSet:
    """n grasps at random centres around the object, random baselines and approaches, widths 0-7 cm."""
    c = rng.uniform(-0.1, 0.1, (n, 3)) + np.array([0.0, 0.0, 0.05])
    b = rng.normal(size=(n, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a = rng.normal(size=(n, 3))
    a -= np.einsum("ij,ij->i", a, b)[:, None] * b
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    w = rng.uniform(0, 0.07, n)
    return GraspSet(c, c + w[:, None] * b, a, b, w)


def test_collision_test_agrees_with_volume_sampling_on_random_poses():
    rng = np.random.default_rng(1)
    solids = Solids.from_parts(object_class("mug").parts)  # boxes and a cylinder, non-convex
    n = 300
    grasps = _random_grasps(rng, n)
    ours = ap.grasp_collides(grasps, solids, GRIPPER, 0.01)
    sampled = _gripper_hits(grasps, solids, rng)
    assert not (sampled & ~ours).any()  # never misses a collision that sampling finds
    assert 0.2 * n < ours.sum()
    assert (ours & ~sampled).sum() <= 0.05 * n


def test_every_class_the_gripper_can_span_has_grasps(cache):
    counts = {c.name: len(class_grasps(c.name, directory=cache)) for c in OBJECT_CLASSES}
    print("\nantipodal grasps per class:", counts)
    # master_chef_can (10.2 cm diameter, 14 cm tall) and wood_block (8.5 x 8.5 x 20 cm) are wider
    # than the 8 cm opening in every direction: no antipodal grasp exists
    assert {k for k, v in counts.items() if v == 0} == {"master_chef_can", "wood_block"}
    assert min(v for v in counts.values() if v) > 1000
    wide = GripperSpec(max_opening_m=0.11)
    assert len(class_grasps("wood_block", gripper=wide, directory=cache)) > 0
    assert len(class_grasps("master_chef_can", gripper=wide, directory=cache)) > 0


def test_mug_has_rim_and_handle_grasps(cache):
    grasps = class_grasps("mug", directory=cache)
    assert (grasps.width < 0.008).any()  # across the 6 mm wall
    rim = grasps.subset(grasps.width < 0.008)
    assert (rim.approach[:, 2] < -0.9).any()  # some from the top


def _foam_scene(neighbour_gap_m: float | None) -> SceneSpec:
    objects = [ObjectSpec(id=0, class_name="foam_brick", position_m=(0.0, 0.15, 0.0))]
    if neighbour_gap_m is not None:  # a second brick beside the first along x
        objects.append(ObjectSpec(id=1, class_name="foam_brick", position_m=(0.075 + neighbour_gap_m, 0.15, 0.0)))
    return SceneSpec(objects=tuple(objects))


def test_a_grasp_whose_finger_would_enter_a_neighbour_is_discarded(cache):
    alone = grasps_in_scene(_foam_scene(None), directory=cache)[0]
    crowded = grasps_in_scene(_foam_scene(0.01), directory=cache)[0]
    assert 0 < len(crowded) < len(alone)
    # in isolation, grasps close on the +x face from the side; with the neighbour 1 cm away the
    # finger (1 cm thick, 5 mm clearance) would enter it, so every such grasp is gone
    side = lambda g: (np.abs(g.baseline[:, 0]) > 0.99) & (np.abs(g.approach[:, 2]) < 0.1)  # noqa: E731
    assert side(alone).sum() > 10
    assert side(crowded).sum() == 0
    neighbour = Solids.from_parts(object_class("foam_brick").parts, _foam_scene(0.01).objects[1].pose())
    rng = np.random.default_rng(2)
    assert _gripper_hits(alone, neighbour, rng).sum() > 10
    assert not _gripper_hits(crowded, neighbour, rng).any()
    # the boards veto too: nothing in the alone set reaches into the bottom board
    board = Solids.from_boxes(_foam_scene(None).shelf.boards()[:1])
    assert not _gripper_hits(alone, board, rng).any()
    # the neighbour's own grasps are in the world frame around it
    other = grasps_in_scene(_foam_scene(0.01), directory=cache)[1]
    assert np.all(other.contacts[:, 0] > 0.085 - 0.04)


def test_poses_override_the_spec(cache):
    scene = _foam_scene(None)
    moved = scene.objects[0].pose()
    moved[:3, 3] += [0.1, 0.0, 0.0]
    a = grasps_in_scene(scene, directory=cache)[0]
    b = grasps_in_scene(scene, poses={0: moved}, directory=cache)[0]
    np.testing.assert_allclose(b.contacts, a.contacts + np.array([0.1, 0.0, 0.0]), atol=1e-12)


def test_the_cache_round_trips(tmp_path, monkeypatch):
    config = AntipodalConfig(samples_per_m2=20_000)
    monkeypatch.setenv("MSMEM_CACHE_DIR", str(tmp_path))
    first = class_grasps("gelatin_box", config)
    files = list((tmp_path / "antipodal").glob("gelatin_box-*.npz"))
    assert len(files) == 1

    def refuse(*_args, **_kwargs):
        raise AssertionError("generated again instead of loading the cache")

    monkeypatch.setattr(ap, "sample_antipodal", refuse)
    again = class_grasps("gelatin_box", config)
    for field in ("contacts", "opposite", "approach", "baseline", "width"):
        np.testing.assert_array_equal(getattr(first, field), getattr(again, field))
    # another config is another key
    with pytest.raises(AssertionError, match="generated again"):
        class_grasps("gelatin_box", AntipodalConfig(samples_per_m2=20_000, friction=0.4))
    assert ap.cache_key(object_class("gelatin_box"), config, GRIPPER) in files[0].name


def test_a_convex_hull_solid_is_the_box_it_spans_for_inside_and_collision_tests():
    """A mesh class's pieces (convex hulls) answer ``contains`` and the gripper collision test as the
    primitive they span does: the same points inside, the same colliding grasps."""
    box = object_class("potted_meat_can").parts[0]
    pose = np.eye(4)
    pose[:3, :3] = trimesh.transformations.rotation_matrix(0.4, [0.2, 0.3, 1.0])[:3, :3]
    pose[:3, 3] = [0.02, -0.01, 0.03]
    prim, hull = Solids.from_parts([box], pose), Solids.from_parts([convex_copy(box)], pose)
    assert hull.hull[0] is not None
    assert prim.hull[0] is None
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.08, 0.12, (20000, 3))
    inside = prim.contains(pts)
    assert 1000 < inside.sum()
    np.testing.assert_array_equal(hull.contains(pts), inside)
    n = 400
    grasps = _random_grasps(rng, n)
    want = ap.grasp_collides(grasps, prim, GRIPPER, 0.01)
    assert 0.2 * n < want.sum() < n
    np.testing.assert_array_equal(ap.grasp_collides(grasps, hull, GRIPPER, 0.01), want)


def test_a_mesh_class_has_antipodal_grasps_on_its_pieces(cache):
    """The mesh25 duck (6 CoACD pieces): grasps exist, each contact lies on the pieces' outer surface,
    and volume sampling finds no gripper box inside a piece."""
    from msmem_core.run.bench import suite_scenes

    scene = next(s for s in suite_scenes("mesh25") if any(o.class_name == "duck" for o in s.objects))
    duck = scene.object_class("duck")
    assert len(duck.parts) > 1
    assert all(p.kind == "convex" for p in duck.parts)
    # fewer samples and approaches than the default: python-fcl tests each candidate against a hull
    grasps = class_grasps(duck, AntipodalConfig(samples_per_m2=20_000.0, n_approach=3), directory=cache)
    assert len(grasps) > 50
    assert (grasps.width <= GRIPPER.max_opening_m).all()
    solids = Solids.from_parts(duck.parts)
    eps = 1e-3
    for pts, n_dir in ((grasps.contacts, grasps.baseline), (grasps.opposite, -grasps.baseline)):
        assert not solids.contains(pts - eps * n_dir).any()  # just outside, against the baseline
        assert solids.contains(pts + eps * n_dir).mean() > 0.95  # just inside, along it
    rng = np.random.default_rng(0)
    sample = grasps.subset(rng.choice(len(grasps), 200, replace=False))
    assert not _gripper_hits(sample, solids, rng).any()

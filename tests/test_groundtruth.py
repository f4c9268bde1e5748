"""Ground truth: exact voxelisation, visibility of objects and the observable mask agree with rays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import look_at, pose_matrix, yaw_quat
from msmem_core.world.grid import GridSpec
from msmem_core.world.meshes import object_mesh, shelf_meshes
from msmem_core.world.placement import load_scene
from msmem_core.world.scene import ObjectSpec, ShelfSpec, object_class
from msmem_core.world.viewpoints import ViewpointConfig, default_start_view, generate_viewpoints
from msmem_core.world.visibility import (
    HIT_NUDGE_VOXELS,
    _box_ray_indices,
    _rays_at,
    count_views_seeing,
    hidden_objects,
    object_pixel_counts,
    observable_mask,
    ray_table,
    visible_objects,
)
from msmem_core.world.voxelize import current_pose, interior_mask, object_voxels, voxelize, voxelize_instances

SHELF = ShelfSpec()
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.01)
SMALL_CAMERA = CameraConfig(width_px=160, height_px=120)

unit_quats = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: 0.1 < np.linalg.norm(q))
offsets = st.tuples(*[st.floats(-0.05, 0.05)] * 3)


def _count_at(class_name: str, quat: tuple[float, ...], offset: tuple[float, ...], voxel: float) -> int:
    obj = ObjectSpec(id=0, class_name=class_name, position_m=(0.0, 0.0, 0.0))
    grid = GridSpec(origin_m=(-0.2, -0.2, -0.2), voxel_m=voxel, shape=(int(0.4 / voxel),) * 3)
    centre = -np.asarray(obj.object_class.parts[0].position_m)  # put the part's centre near the origin
    pose = pose_matrix(offset, np.asarray(quat) / np.linalg.norm(quat)) @ pose_matrix(centre)
    return len(object_voxels(obj, grid, pose))


@settings(max_examples=12, derandomize=True, deadline=None)
@given(quat=unit_quats, offset=offsets)
def test_voxelised_box_volume_lies_within_one_voxel_layer(quat: tuple[float, ...], offset: tuple[float, ...]) -> None:
    s = 0.01
    x, y, z = object_class("cracker_box").parts[0].size_m
    count = _count_at("cracker_box", quat, offset, s)
    shrunk = (x - 2 * s) * (y - 2 * s) * (z - 2 * s)
    grown = (x + 2 * s) * (y + 2 * s) * (z + 2 * s)
    assert shrunk <= count * s**3 <= grown


@settings(max_examples=12, derandomize=True, deadline=None)
@given(quat=unit_quats, offset=offsets)
def test_voxelised_cylinder_volume_lies_within_one_voxel_layer(
    quat: tuple[float, ...], offset: tuple[float, ...]
) -> None:
    s = 0.01
    r, h = object_class("master_chef_can").parts[0].size_m
    count = _count_at("master_chef_can", quat, offset, s)
    shrunk = np.pi * (r - s) ** 2 * (h - 2 * s)
    grown = np.pi * (r + s) ** 2 * (h + 2 * s)
    assert shrunk <= count * s**3 <= grown


def test_axis_aligned_box_on_voxel_boundaries_fills_exactly_its_voxels() -> None:
    """A 16 x 6 x 21 cm box resting on z = 0 with faces on voxel boundaries touches no outside layer."""
    grid = GridSpec(origin_m=(-0.2, -0.1, -0.01), voxel_m=0.01, shape=(40, 20, 30))
    obj = ObjectSpec(id=0, class_name="cracker_box", position_m=(0.0, 0.0, 0.0))
    occ, cls = voxelize([obj], grid)
    assert occ.sum() == 16 * 6 * 21
    assert not occ[:, :, 0].any()  # the layer under the floor stays free
    assert set(np.unique(cls[occ])) == {object_class("cracker_box").class_id}


def test_mug_is_hollow() -> None:
    s = 0.005
    grid = GridSpec(origin_m=(-0.1, -0.1, -0.01), voxel_m=s, shape=(40, 40, 22))
    mug = ObjectSpec(id=0, class_name="mug", position_m=(0.0, 0.0, 0.0))
    occ, _ = voxelize([mug], grid)
    c = grid.centers()
    radial = np.hypot(c[..., 0], c[..., 1])
    inside = (radial < 0.034 - s) & (c[..., 2] > 0.008 + s) & (c[..., 2] < 0.088)
    assert inside.sum() > 50
    assert not occ[inside].any()
    wall = (np.abs(radial - 0.037) < 0.002) & (c[..., 2] > 0.02) & (c[..., 2] < 0.08)
    assert occ[wall].all()


def _random_objects(rng: np.random.Generator) -> list[ObjectSpec]:
    """A few objects at random yaws, slightly lifted, so no face lies exactly on a voxel boundary."""
    names = ["cracker_box", "master_chef_can", "mug", "bleach_cleanser", "tuna_fish_can"]
    xs = np.linspace(-0.28, 0.28, len(names))
    return [
        ObjectSpec(
            id=i,
            class_name=n,
            position_m=(float(x), float(rng.uniform(0.1, 0.25)), float(rng.uniform(0, 0.004))),
            quat_xyzw=tuple(float(v) for v in yaw_quat(rng.uniform(0, 2 * np.pi))),  # type: ignore[arg-type]
        )
        for i, (n, x) in enumerate(zip(names, xs, strict=True))
    ]


@pytest.mark.parametrize("view", [0, 155, 299])
def test_camera_rays_hit_surfaces_inside_occupied_voxels_of_the_right_class(view: int) -> None:
    objects = _random_objects(np.random.default_rng(view))
    pose = generate_viewpoints(ViewpointConfig(), SHELF)[view]
    camera = CameraConfig()
    scene = o3d.t.geometry.RaycastingScene()
    for m in [object_mesh(o) for o in objects] + shelf_meshes(SHELF):
        scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)), o3d.core.Tensor(m.faces.astype(np.uint32)))
    d_cam = camera.pixel_rays(2).reshape(-1, 3)
    d = d_cam @ pose[:3, :3].T
    rays = np.concatenate([np.broadcast_to(pose[:3, 3], d.shape), d], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    depth, gid = ans["t_hit"].numpy().astype(np.float64), ans["geometry_ids"].numpy().astype(np.int64)
    on_object = np.isfinite(depth) & (gid < len(objects))
    assert on_object.sum() > 1000
    # z-depth -> camera-frame point -> world, then the voxel just past the surface (the update's rule).
    pts = (d_cam[on_object] * depth[on_object, None]) @ pose[:3, :3].T + pose[:3, 3]
    unit = d[on_object] / np.linalg.norm(d[on_object], axis=1, keepdims=True)
    idx = GRID.index_of(pts + HIT_NUDGE_VOXELS * GRID.voxel_m * unit)
    occ, cls = voxelize(objects, GRID)
    assert occ[tuple(idx.T)].all()
    expected = np.array([o.class_id for o in objects])[gid[on_object]]
    assert (cls[tuple(idx.T)] == expected).all()


def test_poses_override_the_spec_pose() -> None:
    obj = ObjectSpec(id=3, class_name="sugar_box", position_m=(0.0, 0.1, 0.0))
    moved = pose_matrix((0.2, 0.25, 0.0), yaw_quat(0.3))
    ids = voxelize_instances([obj], GRID, {3: moved})
    assert ids.max() == 3
    assert np.array_equal(
        ids == 3,
        voxelize([obj.model_copy(update={"position_m": (0.2, 0.25, 0.0), "quat_xyzw": tuple(yaw_quat(0.3))})], GRID)[0],
    )


def test_interior_mask_excludes_the_boards() -> None:
    m = interior_mask(SHELF, GRID)
    assert not m[:, :, 0].any()
    assert not m[0].any()
    assert not m[-1].any()
    assert m[5:-5, 5:-5, 5:-5].all()


def test_an_object_inside_another_is_hidden_and_the_big_one_is_seen() -> None:
    big = ObjectSpec(id=7, class_name="cracker_box", position_m=(0.0, 0.15, 0.0))
    inner = ObjectSpec(id=9, class_name="foam_brick", position_m=(0.0, 0.15, 0.05))
    views = generate_viewpoints(ViewpointConfig(grid=3), SHELF)
    vis = visible_objects([big, inner], SHELF, views, SMALL_CAMERA, stride=2)
    assert vis.object_ids == (7, 9)
    assert vis.visible()[:, 0].all()
    assert not vis.visible()[:, 1].any()
    assert vis.per_view()[0] == {7}
    assert hidden_objects([big, inner], SHELF, views, SMALL_CAMERA, stride=2) == [9]
    counts = object_pixel_counts([big, inner], [9, 7], SHELF, views, SMALL_CAMERA, stride=2)
    assert counts == {9: 0, 7: int(vis.pixel_counts[:, 0].sum())}


def test_shelf_boards_occlude() -> None:
    """An object standing outside, behind the back board, is hidden by it."""
    behind = ObjectSpec(id=0, class_name="tuna_fish_can", position_m=(0.0, SHELF.depth_m + 0.1, 0.05))
    views = generate_viewpoints(ViewpointConfig(grid=3), SHELF)
    assert hidden_objects([behind], SHELF, views, SMALL_CAMERA, stride=2) == [0]


def test_count_views_seeing_points() -> None:
    big = ObjectSpec(id=0, class_name="cracker_box", position_m=(0.0, 0.1, 0.0))
    views = generate_viewpoints(ViewpointConfig(grid=3), SHELF)
    pts = np.array([[0.0, 0.1, 0.1], [0.0, 0.2, 0.25], [0.0, 0.15, 0.01]])  # inside; high up; right behind
    n = count_views_seeing(pts, [big], SHELF, views, CameraConfig())
    assert n[0] == 0
    assert n[1] > 0
    assert n[2] == 0


def test_observable_mask_drops_only_self_occluded_interiors() -> None:
    box = ObjectSpec(id=0, class_name="wood_block", position_m=(0.0, 0.15, 0.0))
    views = generate_viewpoints(ViewpointConfig(grid=4), SHELF)
    occ, _ = voxelize([box], GRID)
    mask = observable_mask([box], None, SHELF, views, SMALL_CAMERA, GRID, stride=1)
    assert mask[~occ].all()  # free voxels always count
    hidden = occ & ~mask
    assert hidden.sum() > 0.5 * occ.sum()  # the interior of an 8.5 x 8.5 x 20 cm block
    centre = GRID.index_of([[0.0, 0.15, 0.1]])[0]
    front = GRID.index_of([[0.0, 0.15 - 0.0415, 0.1]])[0]  # just behind the front face
    assert not mask[tuple(centre)]
    assert mask[tuple(front)]


def test_default_viewpoints_are_in_front_and_look_at_their_targets() -> None:
    cfg = ViewpointConfig()
    views = generate_viewpoints(cfg, SHELF)
    assert views.shape == (300, 4, 4)
    assert views.dtype == np.float64
    assert np.all(views[:, 1, 3] < 0)
    for g, tx in enumerate(cfg.targets_x_m):
        target = np.array([tx, cfg.target_y_m, cfg.target_z_m])
        for v in views[g * 100 : (g + 1) * 100 : 17]:
            assert np.allclose(v, look_at(v[:3, 3], target))
            assert np.linalg.norm(v[:3, 3] - target) == pytest.approx(cfg.radius_m)
    start = views[default_start_view(cfg)]
    assert abs(start[0, 3]) < 0.1  # middle grid
    assert start[2, 3] > cfg.target_z_m  # slightly above the target


def _observable_mask_numpy(objects, poses, shelf, viewpoints, camera, grid, stride=4):  # type: ignore[no-untyped-def]
    """The observable mask in plain numpy, each object's rays computed for it (the reference)."""
    occ, _ = voxelize(objects, grid, poses)
    seen = np.zeros(grid.size, dtype=bool)
    boards = shelf_meshes(shelf)
    for obj in objects:
        mesh = object_mesh(obj, current_pose(obj, poses))
        scene = o3d.t.geometry.RaycastingScene()
        target, *_ = [scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                                          o3d.core.Tensor(m.faces.astype(np.uint32))) for m in [mesh, *boards]]
        rays = _rays_at(_box_ray_indices(mesh.bounds, viewpoints, camera, stride), viewpoints, camera, stride)
        ans = scene.cast_rays(o3d.core.Tensor(rays))
        t, gid = ans["t_hit"].numpy(), ans["geometry_ids"].numpy()
        hit = (gid == target) & (t <= camera.far_m - camera.near_m)
        r = rays[hit].astype(np.float64)
        d = r[:, 3:]
        nudge = HIT_NUDGE_VOXELS * grid.voxel_m
        pts = r[:, :3] + (t[hit][:, None] + nudge / np.linalg.norm(d, axis=1, keepdims=True)) * d
        idx = grid.index_of(pts)
        idx = idx[grid.contains_index(idx)]
        seen[np.ravel_multi_index(idx.T, grid.shape)] = True
    return (~occ) | seen.reshape(grid.shape)


def test_observable_mask_equals_the_numpy_reference_to_the_voxel() -> None:
    # a shipped scene at its poses and with every object nudged by up to a few mm, as a grasp leaves them
    scene = load_scene(str(Path(__file__).parents[1] / "msmem_core/suites/hard25/scene_07.json"))
    views = generate_viewpoints(ViewpointConfig(), scene.shelf)
    camera, grid = CameraConfig(width_px=320, height_px=240), GridSpec()
    rng = np.random.default_rng(3)
    poses = {o.id: current_pose(o, None) for o in scene.objects}
    cut = GridSpec(origin_m=(0.0, 0.05, 0.0), shape=(30, 20, 20))  # objects cross all its faces
    for trial in range(2):
        mask = observable_mask(list(scene.objects), poses, scene.shelf, views, camera, grid)
        ref = _observable_mask_numpy(list(scene.objects), poses, scene.shelf, views, camera, grid)
        assert np.array_equal(mask, ref)
        assert (~mask).sum() > 1000  # object interiors are left out
        if trial == 0:
            mask = observable_mask(list(scene.objects), poses, scene.shelf, views, camera, cut)
            assert np.array_equal(mask, _observable_mask_numpy(list(scene.objects), poses, scene.shelf, views, camera,
                                                               cut))
        poses = {k: v.copy() for k, v in poses.items()}
        for v in poses.values():
            v[:2, 3] += rng.normal(0.0, 0.003, 2)


def test_ray_table_rows_equal_the_rays_of_any_subset() -> None:
    views = generate_viewpoints(ViewpointConfig(grid=4), SHELF)
    table = ray_table(views, SMALL_CAMERA, 4)
    assert table.shape == (len(views) * 40 * 30, 6)
    ids = np.sort(np.random.default_rng(0).choice(len(table), 5000, replace=False))
    assert np.array_equal(table[ids], _rays_at(ids, views, SMALL_CAMERA, 4))
    assert ray_table(views, SMALL_CAMERA, 4) is table  # kept
    assert not table.flags.writeable

"""Frontier point projection: points lie on the believed surface (within a voxel of voxels with p > 0.5,
nothing believed occupied in front of them), flat walls come out flat with the right normals, an
empty or unknown belief gives no points, sampling is seeded, and the fused numba kernel with
normals at the drawn points only gives what the earlier array implementation (kept here as a
reference) gave."""

from __future__ import annotations

import numpy as np
import pytest
from msmem_grasp.fpp import (
    FPPConfig,
    SurfaceCloud,
    _trilinear,
    camera_rays,
    frontier_points,
    occupancy_normals,
    project_surface,
    sample_cloud,
    shelf_bounds,
    virtual_front_views,
)

from msmem_core.map import raycast
from msmem_core.map.belief import EvidentialMap
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, front_views, generate_viewpoints

GRID = GridSpec.around_box(ShelfSpec().interior_lower, ShelfSpec().interior_upper, 0.01, 1)
SMALL = FPPConfig(ray_stride_px=8, num_points=2000)


def _belief(occupied: np.ndarray, free: np.ndarray) -> EvidentialMap:
    """A belief with p = 21/22 on ``occupied`` voxels, 1/22 on ``free`` ones, 0.5 (unknown) elsewhere."""
    b = EvidentialMap.empty(GRID)
    b.alpha[occupied] += 20.0
    b.beta[free & ~occupied] += 20.0
    return b


def _boxes_scene() -> EvidentialMap:
    """Two boxes on the floor, free space in front of them, unknown behind."""
    c = GRID.centers()
    occ = (c[..., 2] < 0.0)  # floor board
    occ |= (np.abs(c[..., 0] + 0.1) < 0.05) & (np.abs(c[..., 1] - 0.15) < 0.04) & (c[..., 2] < 0.12)
    occ |= (np.abs(c[..., 0] - 0.12) < 0.04) & (np.abs(c[..., 1] - 0.10) < 0.03) & (c[..., 2] < 0.18)
    free = (c[..., 1] < 0.06) & ~occ
    return _belief(occ, free)


def test_points_lie_on_the_believed_surface_and_nothing_occupied_is_in_front():
    belief = _boxes_scene()
    poses = virtual_front_views()
    cloud = frontier_points(belief, poses, SMALL, seed=0)
    assert 100 < len(cloud) <= SMALL.num_points
    p = belief.expected_occupancy()
    occ_idx = np.argwhere(p > 0.5)
    s = GRID.voxel_m
    # within a voxel of a believed-occupied voxel (distance from the point to that voxel's cube)
    lo = GRID.origin + occ_idx * s
    from scipy.spatial import cKDTree

    _, near = cKDTree(lo + 0.5 * s).query(cloud.points.astype(np.float64), k=8)
    gap = np.maximum(np.maximum(lo[near] - cloud.points[:, None], cloud.points[:, None] - (lo[near] + s)), 0.0)
    assert np.linalg.norm(gap, axis=-1).min(axis=1).max() <= s + 1e-6
    # in front of them: from the camera, no believed-occupied voxel starts more than a voxel before the point
    origins = poses[cloud.view, :3, 3]
    dirs = cloud.points.astype(np.float64) - origins
    g0, s_, n = raycast.grid_params(GRID)
    t_in, _, hit = raycast.first_hit(np.ascontiguousarray((p > 0.5).ravel().astype(np.uint8)),
                                     np.ascontiguousarray(origins), np.ascontiguousarray(dirs), g0, s_, n, 0.0, 2.0)
    assert (hit >= 0).all()
    dist = np.linalg.norm(dirs, axis=1)
    assert ((1.0 - t_in) * dist <= s + 1e-6).all()  # the first occupied voxel is at most a voxel before the point
    # normals are unit and face their camera
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-5)
    assert (np.einsum("ij,ij->i", cloud.normals, dirs) <= 1e-6).all()
    assert ((cloud.occupancy > 0.5) & (cloud.occupancy < 1.0)).all()


def test_a_flat_wall_gives_points_on_its_plane_with_its_normal():
    c = GRID.centers()
    wall_y = 0.20  # a voxel boundary
    occ = c[..., 1] > wall_y
    belief = _belief(occ, ~occ)
    pose = virtual_front_views()[1:2]  # straight in front of the middle
    cfg = FPPConfig(ray_stride_px=8, surface_offset_voxels=0.0)
    exact = project_surface(belief.expected_occupancy(), GRID, pose, cfg)
    inner = (np.abs(exact.points[:, 0]) < 0.3) & (exact.points[:, 2] > 0.03) & (exact.points[:, 2] < 0.25)
    assert inner.sum() > 200
    np.testing.assert_allclose(exact.points[inner, 1], wall_y, atol=1e-4)
    np.testing.assert_allclose(exact.normals[inner], np.tile([0.0, -1.0, 0.0], (inner.sum(), 1)), atol=1e-3)
    shifted = project_surface(belief.expected_occupancy(), GRID, pose, FPPConfig(ray_stride_px=8))
    # the default moves points half a voxel along the ray, into the voxel that holds the surface
    assert (shifted.points[:, 1] > wall_y).all()
    assert (shifted.points[:, 1] < wall_y + GRID.voxel_m).all()


@pytest.mark.parametrize("kind", ["prior", "free", "no-views"])
def test_an_empty_or_unknown_belief_gives_no_points(kind: str):
    belief = EvidentialMap.empty(GRID)  # p = 0.5 everywhere: nothing is believed occupied
    poses = virtual_front_views()
    if kind == "free":
        belief.beta += 20.0
    if kind == "no-views":
        belief = _boxes_scene()
        poses = np.zeros((0, 4, 4))
    cloud = frontier_points(belief, poses, SMALL)
    assert len(cloud) == 0
    assert cloud.points.shape == (0, 3)
    assert cloud.features().shape == (0, 4)


def test_sampling_is_seeded_and_deterministic():
    belief = _boxes_scene()
    cfg = FPPConfig(ray_stride_px=8, num_points=300)
    a = frontier_points(belief, None, cfg, seed=3)
    b = frontier_points(belief, None, cfg, seed=3)
    c = frontier_points(belief, None, cfg, seed=4)
    assert len(a) == 300
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert not np.array_equal(a.points, c.points)
    full = project_surface(belief.expected_occupancy(), GRID, virtual_front_views(), cfg)
    assert len(full) > 300
    assert len(np.unique(np.floor(full.points / (0.5 * GRID.voxel_m)), axis=0)) == len(full)  # deduplicated


def test_shelf_bounds_drop_surfaces_outside_the_shelf():
    c = GRID.centers()
    occ = (c[..., 2] > ShelfSpec().height_m) | (c[..., 2] < 0.0)  # top and bottom board layers of the grid
    belief = _belief(occ, ~occ)
    high = virtual_front_views()
    high[:, 2, 3] += 0.3  # cameras above the shelf also see the top board's upper face
    everything = frontier_points(belief, high, SMALL)
    inside = frontier_points(belief, high, SMALL, shelf=ShelfSpec())
    lo, hi = shelf_bounds(ShelfSpec())
    assert (everything.points[:, 2] > hi[2] + 0.005).any()
    assert len(inside) > 0
    assert (inside.points[:, 2] <= hi[2] + GRID.voxel_m).all()
    assert np.isneginf(lo[1])


# ------------------------------------------------------------------------------ reference (before numba)
def _project_surface_reference(p, grid, poses, config=None, bounds=None) -> SurfaceCloud:  # type: ignore[no-untyped-def]
    """``project_surface`` as it was before the fused kernel: camera rays as arrays, ``raycast.first_hit``,
    all sub-voxel samples with scipy, normals from the whole-grid filter at every point."""
    cfg = config or FPPConfig()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    p = np.asarray(p, dtype=np.float32)
    occ = np.ascontiguousarray((p > cfg.threshold).ravel().astype(np.uint8))
    if len(poses) == 0 or not occ.any():
        return SurfaceCloud.empty()
    origins, dirs, view = camera_rays(poses, cfg.camera, cfg.ray_stride_px)
    g0, s, n = raycast.grid_params(grid)
    t_in, t_out, idx = raycast.first_hit(occ, origins, dirs, g0, s, n, cfg.camera.near_m, cfg.camera.far_m)
    hit = idx >= 0
    if not hit.any():
        return SurfaceCloud.empty()
    o, d, t_in, t_out, idx, view = origins[hit], dirs[hit], t_in[hit], t_out[hit], idx[hit], view[hit]
    dn = np.linalg.norm(d, axis=1)
    t_voxel = s / dn
    k = 2 * cfg.samples_per_voxel + 1
    t_start = np.maximum(t_in - t_voxel, cfg.camera.near_m)
    frac = np.linspace(0.0, 1.0, k)
    ts = t_start[:, None] + frac[None] * (t_out - t_start)[:, None]
    vals = _trilinear(p, grid, o[:, None, :] + ts[..., None] * d[:, None, :])
    above = vals > cfg.threshold
    first = np.argmax(above, axis=1)
    found = above[np.arange(len(first)), first]
    prev = np.maximum(first - 1, 0)
    rows = np.arange(len(first))
    v0, v1 = vals[rows, prev], vals[rows, first]
    w = np.where(v1 > v0, (cfg.threshold - v0) / np.where(v1 > v0, v1 - v0, 1.0), 0.0)
    t_cross = ts[rows, prev] + np.clip(w, 0.0, 1.0) * (ts[rows, first] - ts[rows, prev])
    t_cross = np.where(first == 0, ts[:, 0], t_cross)
    t_cross = np.where(found, t_cross, t_in)
    if bounds is not None:
        at = o + t_cross[:, None] * d
        tol = 0.5 * s
        inside = np.all((at >= np.asarray(bounds[0]) - tol) & (at <= np.asarray(bounds[1]) + tol), axis=1)
        if not inside.any():
            return SurfaceCloud.empty()
        o, d, dn, t_voxel, t_cross, idx, view = (a[inside] for a in (o, d, dn, t_voxel, t_cross, idx, view))
    t_surf = t_cross + cfg.surface_offset_voxels * t_voxel
    pts = o + t_surf[:, None] * d
    cell_m = cfg.dedup_m or 0.5 * s
    cells = np.floor((pts - grid.origin) / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    key = np.ravel_multi_index(cells.T, tuple(int(v) + 1 for v in cells.max(axis=0)))
    _, keep = np.unique(key, return_index=True)
    keep = np.sort(keep)
    pts, d, dn, idx, view = pts[keep], d[keep], dn[keep], idx[keep], view[keep]
    grad = occupancy_normals(p, cfg.normal_sigma_voxels)
    nrm = np.stack([_trilinear(grad[a], grid, pts) for a in range(3)], axis=1)
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    unit_d = d / dn[:, None]
    nrm = np.where(length > 1e-6, nrm / np.maximum(length, 1e-12), -unit_d)
    facing = np.einsum("ij,ij->i", nrm, unit_d)
    nrm = np.where(facing[:, None] > 0.0, -nrm, nrm)
    return SurfaceCloud(points=pts.astype(np.float32), normals=nrm.astype(np.float32),
                        occupancy=p.ravel()[idx].astype(np.float32), voxel=idx.astype(np.int64),
                        view=view.astype(np.int64))


def _assert_same_cloud(a: SurfaceCloud, b: SurfaceCloud) -> None:
    assert len(a) == len(b)
    np.testing.assert_array_equal(a.voxel, b.voxel)
    np.testing.assert_array_equal(a.view, b.view)
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.normals, b.normals, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.occupancy, b.occupancy, rtol=0, atol=1e-6)


@pytest.mark.parametrize("noisy", [False, True])
def test_the_kernel_gives_the_reference_clouds(noisy: bool):
    belief = _boxes_scene()
    rng = np.random.default_rng(11)
    if noisy:  # generic evidence: every sample of p differs
        belief.alpha += rng.uniform(0.0, 4.0, belief.alpha.shape).astype(np.float32)
        belief.beta += rng.uniform(0.0, 4.0, belief.beta.shape).astype(np.float32)
    views = generate_viewpoints(ViewpointConfig())
    poses = np.concatenate([views[rng.choice(len(views), 6, replace=False)], virtual_front_views()])
    p = belief.expected_occupancy()
    cfg = FPPConfig(ray_stride_px=6, num_points=1500, seed=5)
    for bounds in (None, shelf_bounds(ShelfSpec())):
        ref = _project_surface_reference(p, GRID, poses, cfg, bounds)
        assert len(ref) > 2 * cfg.num_points
        _assert_same_cloud(project_surface(p, GRID, poses, cfg, bounds), ref)
    # frontier_points draws first and computes normals for the drawn points only: the same cloud
    _assert_same_cloud(frontier_points(belief, poses, cfg, shelf=ShelfSpec()), sample_cloud(ref, cfg.num_points, 5))


def test_virtual_front_views_are_the_configs_front_views_and_a_callers_copy():
    """Generated once per viewpoint config: the same poses as generating the set, and changing the
    returned array does not change the next call's."""
    for cfg in (ViewpointConfig(), ViewpointConfig(grid=3, radius_m=0.5)):
        want = generate_viewpoints(cfg)[front_views(cfg)]
        got = virtual_front_views(cfg)
        np.testing.assert_array_equal(got, want)
        got[:] = 0.0
        np.testing.assert_array_equal(virtual_front_views(cfg), want)

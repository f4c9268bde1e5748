"""``msmem perf ig``: time 300-view IG sweeps against the brute-force float64 reference.

The belief is mid-episode-like: a random block scene on the shelf floor, observed from four of the
candidate views with the analytic evidence rule (free before the return, occupied + class at it),
so free space, seen surfaces and unknown occluded regions all occur. The batch is that belief and
push-like predictions of it (one block's region reset to the prior, the block placed elsewhere), as
an effect model's candidates are.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

import numba
import numpy as np
from numpy.typing import NDArray

from msmem_core.map import raycast
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGConfig, IGService, shelf_wall_mask
from msmem_core.map.ig_reference import ig_views_reference
from msmem_core.world.camera import CameraConfig, Observation
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import NUM_CLASSES, ShelfSpec


def block_scene(
    grid: GridSpec, shelf: ShelfSpec, rng: np.random.Generator, num_blocks: int = 12
) -> tuple[NDArray[np.bool_], NDArray[np.int16]]:
    """Random axis-aligned blocks standing on the shelf floor, plus the boards: occupancy, class [X,Y,Z]."""
    c = grid.centers()
    occ = shelf_wall_mask(grid, shelf)
    cls = np.zeros(grid.shape, np.int16)
    lo, hi = shelf.interior_lower, shelf.interior_upper
    for _ in range(num_blocks):
        size = rng.uniform([0.04, 0.04, 0.04], [0.16, 0.10, 0.22])
        size[2] = min(size[2], hi[2] - 0.01)
        low = rng.uniform(lo[:2], hi[:2] - size[:2])
        box = np.all((c[..., :2] >= low) & (c[..., :2] < low + size[:2]), axis=-1) & (c[..., 2] < size[2])
        occ |= box
        cls[box] = int(rng.integers(1, NUM_CLASSES))
    return occ, cls


def render_voxels(
    occ: NDArray[np.bool_], cls: NDArray[np.int16], grid: GridSpec, camera: CameraConfig, pose: NDArray[np.floating]
) -> Observation:
    """Synthetic depth + label frame of a voxel scene (return at the middle of the first occupied voxel)."""
    k = camera.intrinsics
    v, u = np.mgrid[0 : camera.height_px, 0 : camera.width_px]
    cam = np.stack([(u + 0.5 - k[0, 2]) / k[0, 0], (v + 0.5 - k[1, 2]) / k[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
    c2w = np.asarray(pose, dtype=np.float64)
    dirs = np.ascontiguousarray(cam @ c2w[:3, :3].T)
    origins = np.ascontiguousarray(np.broadcast_to(c2w[:3, 3], dirs.shape))
    g0, s, n = raycast.grid_params(grid)
    occ8 = occ.ravel().astype(np.uint8)
    t_in, t_out, idx = raycast.first_hit(occ8, origins, dirs, g0, s, n, camera.near_m, camera.far_m)
    hit = idx >= 0
    depth = np.where(hit, 0.5 * (t_in + t_out), 0.0).astype(np.float32)
    labels = np.where(hit, cls.ravel()[np.maximum(idx, 0)], 0).astype(np.int16)
    shape = (camera.height_px, camera.width_px)
    return Observation(depth.reshape(shape), labels.reshape(shape), k, c2w)


def integrate_evidence(belief: EvidentialMap, obs: Observation, weight: float = 10.0, stride: int = 2) -> EvidentialMap:
    """The analytic evidence rule (as plugin ``analytic-observation`` with equal weights), for perf beliefs."""
    depth, labels = obs.depth[::stride, ::stride], obs.labels[::stride, ::stride]
    k = obs.intrinsics
    v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]]
    u, v = u * stride + 0.5, v * stride + 0.5  # pixel centres
    cam = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones(u.shape)], -1)
    dirs = np.ascontiguousarray(cam.reshape(-1, 3) @ obs.camera_to_world[:3, :3].T)
    origins = np.ascontiguousarray(np.broadcast_to(obs.camera_to_world[:3, 3], dirs.shape))
    d = depth.ravel().astype(np.float64)
    g0, s, n = raycast.grid_params(belief.grid)
    free, occ, seen = raycast.integrate_rays(
        origins, dirs, d, d > 0, labels.ravel().astype(np.int16), belief.num_classes, g0, s, n, 0.0, 1.5
    )
    shape = tuple(belief.grid.shape)
    occ_m = occ.reshape(shape).astype(bool)
    free_m = free.reshape(shape).astype(bool) & ~occ_m
    out = belief.copy()
    out.alpha += np.float32(weight) * occ_m
    out.beta += np.float32(weight) * free_m
    out.eta += np.float32(weight) * seen.reshape(out.eta.shape)
    out.eta[0] += np.float32(weight) * free_m
    return out


def mid_episode_belief(
    grid: GridSpec, shelf: ShelfSpec, camera: CameraConfig, viewpoints: NDArray[np.floating], seed: int = 0
) -> EvidentialMap:
    """A block scene seen from 4 random candidate views (free space, seen surfaces, occluded unknowns)."""
    rng = np.random.default_rng(seed)
    occ, cls = block_scene(grid, shelf, rng)
    b = EvidentialMap.empty(grid)
    for v in rng.choice(len(viewpoints), size=4, replace=False):
        b = integrate_evidence(b, render_voxels(occ, cls, grid, camera, viewpoints[v]))
    return b


def candidate_beliefs(base: EvidentialMap, shelf: ShelfSpec, count: int, seed: int = 0) -> list[EvidentialMap]:
    """``count`` push-like predictions of ``base``: a block-sized region reset to the prior and an
    occupied block of that size placed 5-15 cm away (what an effect model's candidates look like)."""
    rng = np.random.default_rng(seed)
    c = base.grid.centers()
    lo, hi = shelf.interior_lower, shelf.interior_upper
    out = []
    for _ in range(count):
        b = base.copy()
        size = rng.uniform([0.05, 0.05, 0.05], [0.12, 0.10, 0.20])
        a = rng.uniform(lo[:2], hi[:2] - size[:2])
        shift = rng.uniform(0.05, 0.15) * np.array([np.cos(th := rng.uniform(0, 2 * np.pi)), np.sin(th)])
        dst = np.clip(a + shift, lo[:2], hi[:2] - size[:2])
        src_m = np.all((c[..., :2] >= a) & (c[..., :2] < a + size[:2]), axis=-1) & (c[..., 2] < size[2])
        dst_m = np.all((c[..., :2] >= dst) & (c[..., :2] < dst + size[:2]), axis=-1) & (c[..., 2] < size[2])
        b.alpha[src_m], b.beta[src_m], b.eta[:, src_m] = 1.0, 1.0, 1.0
        b.alpha[dst_m] += 20.0
        out.append(b)
    return out


def default_viewpoints(shelf: ShelfSpec) -> NDArray[np.float64]:
    """The 300 candidate views (``msmem_core.world.viewpoints``)."""
    from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

    return generate_viewpoints(ViewpointConfig(), shelf)


def _best_time(fn: Callable[[], object], repeats: int) -> float:
    best = np.inf
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return float(best)


def _time_grid(
    grid: GridSpec, shelf: ShelfSpec, camera: CameraConfig, views: NDArray[np.float64], config: IGConfig,
    repeats: int, reference_views: int, batch: int,
) -> dict[str, float]:
    svc = IGService(grid, camera, views, shelf, config)
    base = mid_episode_belief(grid, shelf, camera, views)
    fields = [svc.prepare(b) for b in [base, *candidate_beliefs(base, shelf, batch - 1)]]
    svc.view_ig(fields[0])  # compile / warm up
    svc.view_ig(fields[:2])
    out = {
        "k1": _best_time(lambda: svc.view_ig(fields[0]), repeats),
        "exact": _best_time(lambda: svc.view_ig(fields[0], exact=True), repeats),
        "batch": _best_time(lambda: svc.view_ig(fields), max(1, repeats // 2)),
        "prepare": _best_time(lambda: svc.prepare(base), repeats),
    }
    sel = np.linspace(0, svc.num_views - 1, reference_views).astype(int)
    t = time.perf_counter()
    ref = ig_views_reference(fields[0].p, fields[0].H, svc.origins[sel], svc.dirs[sel], grid, svc.t_min, svc.t_max)
    out["reference"] = (time.perf_counter() - t) * svc.num_views / len(sel)
    fast = svc.view_ig(fields[0], exact=True)[sel]
    out["max_rel_err_vs_reference"] = float(np.max(np.abs(fast - ref) / np.maximum(ref, 1e-12)))
    out["rays_per_view"] = float(svc.rays_per_view)
    return out


def perf_ig(
    repeats: int = 3, report: Callable[[str], None] = print, reference_views: int = 2, batch: int = 16
) -> dict[str, float]:
    """Time one 300-view IG sweep (1 and ``batch`` beliefs; 1 cm and 5 mm grids; every 8th pixel).

    Wall-clock best of ``repeats``; the brute-force reference is timed on ``reference_views`` views
    and extrapolated to all. Returns seconds per sweep under ``<grid>/k1`` (one belief),
    ``<grid>/exact`` (early exit off), ``<grid>/k16`` and ``<grid>/k16_per_belief`` (batched),
    ``<grid>/prepare``, ``<grid>/reference``, plus ``<grid>/ratio`` = reference / k1 and
    ``<grid>/max_rel_err_vs_reference`` (exact kernel vs reference), for grid in ``1cm``, ``5mm``.
    """
    shelf, camera, config = ShelfSpec(), CameraConfig(), IGConfig()
    views = default_viewpoints(shelf)
    grids = {"1cm": GridSpec(), "5mm": GridSpec.around_box(shelf.interior_lower, shelf.interior_upper, 0.005)}
    load = os.getloadavg()[0]
    results: dict[str, float] = {}
    rows = []
    for name, grid in grids.items():
        r = _time_grid(grid, shelf, camera, views, config, repeats, reference_views, batch)
        results |= {
            f"{name}/k1": r["k1"], f"{name}/exact": r["exact"], f"{name}/k{batch}": r["batch"],
            f"{name}/k{batch}_per_belief": r["batch"] / batch, f"{name}/prepare": r["prepare"],
            f"{name}/reference": r["reference"], f"{name}/ratio": r["reference"] / r["k1"],
            f"{name}/max_rel_err_vs_reference": r["max_rel_err_vs_reference"],
        }
        rows.append((name, grid.size, int(r["rays_per_view"]), r))
    report(
        f"IG sweep: {len(views)} views, every {config.ray_stride_px}th pixel, early exit {config.early_exit:g}; "
        f"wall-clock best of {repeats}, {numba.get_num_threads()} numba threads, load average {load:.1f} at start; "
        f"reference extrapolated from {reference_views} views"
    )
    report(
        f"{'grid':5} {'voxels':>8} {'rays/view':>9} {'k=1 s':>7} {'exact s':>8} {f'k={batch} s':>8} "
        f"{'s/belief':>8} {'reference s':>11} {'ref/k=1':>8} {'rel err':>8}"
    )
    for name, size, nr, r in rows:
        report(
            f"{name:5} {size:>8} {nr:>9} {r['k1']:7.3f} {r['exact']:8.3f} {r['batch']:8.3f} {r['batch'] / batch:8.3f} "
            f"{r['reference']:11.1f} {r['reference'] / r['k1']:8.0f} {r['max_rel_err_vs_reference']:8.1e}"
        )
    return results

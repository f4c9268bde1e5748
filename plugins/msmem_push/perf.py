"""``msmem perf push`` (registered by this plugin): time the push skill's per-step work on a mid-episode belief.

Stages: sampling (UPS, ``push`` skill), prediction (the push skill's default effect model, or the one
named by ``effect_model``), and scoring
(``ig`` term on all 300 views, as configured by default: screened at every 2nd ray, finalists
re-scored at full density; plus ``semantic-entropy``). For comparison: the incremental ``ig`` term
without screening (exact for every candidate) and the brute-force reference, a full batched IG
re-score of every predicted belief; the report gives their ratio and the largest difference
between the exact incremental values and the reference.

The belief: a generated hard scene (``msmem_core.world.scenegen``), voxelised with the shelf boards, seen
from ``views`` candidate viewpoints by a synthetic depth camera over the voxels
(``msmem_core.perf.ig.render_voxels``) and integrated with the analytic evidence rule: free space,
seen surfaces and hidden regions as mid-episode. Components come from the plugin manager, so the
effect model timed can be any registered one (``--effect-model``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

from msmem_core.interfaces import CandidateBatch, DecisionContext, Workspace
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGConfig, IGService, shelf_wall_mask
from msmem_core.perf.ig import integrate_evidence, render_voxels
from msmem_core.plugins.manager import ComponentRef, get_plugin_manager
from msmem_core.world.camera import CameraConfig
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.scene import SceneSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints
from msmem_core.world.voxelize import voxelize


def mid_episode_scene_belief(
    scene: SceneSpec, grid: GridSpec, camera: CameraConfig, viewpoints: np.ndarray, views: int, seed: int
) -> EvidentialMap:
    """The scene's objects and shelf boards seen from ``views`` random candidate views."""
    occ, cls = voxelize(list(scene.objects), grid)
    walls = shelf_wall_mask(grid, scene.shelf)
    occ = np.asarray(occ, dtype=bool) | walls
    cls = np.where(walls, 0, np.asarray(cls)).astype(np.int16)
    rng = np.random.default_rng(seed)
    b = EvidentialMap.empty(grid)
    for v in rng.choice(len(viewpoints), size=views, replace=False):
        b = integrate_evidence(b, render_voxels(occ, cls, grid, camera, viewpoints[v]))
    return b


def _best(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    best, out = np.inf, None
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return float(best), out


def perf_push(
    repeats: int = 3, samples: int = 80, scene_seed: int = 0, views: int = 4, reference: bool = True,
    report: Callable[[str], None] = print, effect_model: str | None = None,
) -> dict[str, float]:
    """Time sampling, prediction and scoring of ``samples`` push candidates on all candidate views."""
    from msmem_core.world.scenegen import generate_scene

    pm = get_plugin_manager()
    camera, ig_cfg = CameraConfig(), IGConfig()
    t_setup = time.perf_counter()
    scene = generate_scene(scene_seed)
    grid = GridSpec.around_box(scene.shelf.interior_lower, scene.shelf.interior_upper, 0.01)
    viewpoints = generate_viewpoints(ViewpointConfig(), scene.shelf)
    belief = mid_episode_scene_belief(scene, grid, camera, viewpoints, views, scene_seed)
    ig = IGService(grid, camera, viewpoints, scene.shelf, ig_cfg)
    skill = pm.build("skill", ComponentRef(name="push", params={"max_samples": samples}))
    effect_name = effect_model or pm.skills()["push"].effect_model or "push-analytic"
    effect = pm.build("belief-model", effect_name)
    ig_term = pm.build("objective-term", "ig")
    exact_term = pm.build("objective-term", ComponentRef(name="ig", params={"screen_ray_step": 1}))
    dh_term = pm.build("objective-term", "semantic-entropy")
    setup_s = time.perf_counter() - t_setup

    workspace = Workspace(grid, scene.shelf, GripperSpec())

    def ctx(seed: int = 0) -> DecisionContext:
        return DecisionContext(5, belief, ig, viewpoints, set(), workspace, np.random.default_rng(seed), True, 0.5)

    base = ctx()
    t_prep, _ = _best(lambda: ig.prepare(belief), repeats)
    field = base.field  # computed once per step for every skill (views need it too)
    ig.view_ig(field)
    t_sweep, _ = _best(lambda: ig.view_ig(field), repeats)
    # warm up the kernels (numba caches compiled code on disk; the first call in a process loads it)
    warm = skill.propose(ctx())
    wb = CandidateBatch("push", "manipulation", warm[:2], prediction=effect.predict(belief, warm[:2], workspace))
    ig_term.score(base, wb)
    exact_term.score(base, wb)
    base.cache.clear()

    t_sample, actions = _best(lambda: skill.propose(ctx()), repeats)
    t_predict, pred = _best(lambda: effect.predict(belief, actions, workspace), repeats)
    batch = CandidateBatch("push", "manipulation", actions, prediction=pred)

    def score(term: Any) -> Any:
        base.cache.clear()
        return term.score(base, batch)

    t_ig, ig_scores = _best(lambda: score(ig_term), repeats)
    t_dh, _ = _best(lambda: score(dh_term), repeats)
    t_exact, exact = _best(lambda: score(exact_term), max(1, repeats // 2))
    res: dict[str, float] = {
        "candidates": float(len(actions)), "prepare_s": t_prep, "sweep_s": t_sweep, "sample_s": t_sample,
        "predict_s": t_predict,
        "score_ig_s": t_ig, "score_dh_s": t_dh, "score_ig_exact_s": t_exact,
        "total_s": t_sample + t_predict + t_ig + t_dh,
        "changed_voxels_mean": float(np.mean([len(d.idx) for d in pred.changes])) if actions else 0.0,
        "screened_best_is_exact_best": float(int(np.argmax(ig_scores)) == int(np.argmax(exact))) if actions else 1.0,
    }
    if reference and actions:
        t = time.perf_counter()
        full = ig.view_ig([ig.prepare(b, before=field) for b in pred.beliefs]).max(axis=1)
        res["reference_s"] = time.perf_counter() - t
        res["reference_over_exact"] = res["reference_s"] / t_exact
        res["reference_over_screened"] = res["reference_s"] / t_ig
        res["max_abs_diff_exact_vs_reference"] = float(np.abs(full - exact).max())
        res["max_rel_diff_exact_vs_reference"] = float((np.abs(full - exact) / np.maximum(full, 1e-12)).max())
    load = os.getloadavg()[0]
    report(
        f"push candidates on scene gen-{scene_seed} ({len(scene.objects)} objects), belief from {views} views, "
        f"{grid.shape} voxels of {grid.voxel_m * 100:g} cm, {ig.num_views} views x {ig.rays_per_view} rays; "
        f"wall-clock best of {repeats}, {numba.get_num_threads()} numba threads, load average {load:.1f}; "
        f"setup {setup_s:.1f} s; 'sweeps' = seconds / one IG sweep, comparable across machine loads"
    )
    report(f"  {'stage':52} {'seconds':>8} {'sweeps':>7}")
    rows = [
        ("ig.prepare (once per step, shared with views)", t_prep),
        ("one IG sweep: base belief, all views (unit)", t_sweep),
        (f"sample (UPS): {len(actions)} candidates", t_sample),
        (f"predict ({effect_name}), mean {res['changed_voxels_mean']:.0f} changed voxels", t_predict),
        ("score: ig (screened, 8 finalists exact)", t_ig),
        ("score: semantic-entropy", t_dh),
        ("total: sample + predict + score", res["total_s"]),
        ("  ig without screening (incremental, exact)", t_exact),
    ]
    if "reference_s" in res:
        rows.append(("  ig reference (full re-score of every belief)", res["reference_s"]))
    for name, sec in rows:
        report(f"  {name:52} {sec:8.3f} {sec / t_sweep:7.1f}")
    if "reference_s" in res:
        report(
            f"  reference / incremental: {res['reference_over_exact']:.1f}x (/ screened: "
            f"{res['reference_over_screened']:.1f}x); incremental vs reference max abs diff "
            f"{res['max_abs_diff_exact_vs_reference']:.2e} (rel {res['max_rel_diff_exact_vs_reference']:.1e}); "
            f"screened argmax == exact argmax: {bool(res['screened_best_is_exact_best'])}"
        )
    return res

"""``msmem eval belief-models``: calibration of predicted beliefs against the real ground truth after
the action, for the learned CNABU model, its analytic twin and "no change", and prediction speed.

Models (all through their belief-model classes, exactly as ``msmem run`` uses them):

| kind | learned | analytic twin | no change |
| --- | --- | --- | --- |
| observe | ``cnabu-observe`` | ``analytic-observation`` (on the same ray masks) | the belief before |
| push | ``cnabu-push`` | ``push-analytic`` | the belief before |
| grasp | ``cnabu-grasp`` | ``grasp-analytic`` | the belief before |

Metrics per voxel, pooled over every sample of the held-out shards, on two regions:
``all`` (every voxel but the shelf's boards) and ``affected`` (the GT change and the action's own
voxels, dilated by one voxel, without the boards: where the models differ).

- occupancy: NLL ``-log p(y)`` (p = alpha / (alpha + beta), clipped to [1e-6, 1 - 1e-6]), Brier
  ``(p - y)^2``, ECE of the top label (confidence max(p, 1 - p), 15 equal-width bins);
- semantics: NLL ``-log q_y`` of the expected class probabilities (GT class 0 = free/background),
  Brier ``sum_c (q_c - y_c)^2``, top-label ECE (15 bins).

Timing (push, grasp): the learned model and the twin predict ``candidates`` candidates (the first
held-out state's actions, repeated) in one call, best of ``repeats``; simulate-and-remap of one
candidate = simulator snapshot, execute the action under physics, re-observe from the state's last
view, integrate it (analytic update), restore; mean over ``repeats`` candidates on the shard's
scene. Speed-up = simulate-and-remap of one candidate / learned prediction time per candidate (and
per the whole batch). Observe: learned vs analytic update time per view on the same masks.

The simulator is the one named by ``simulator`` (``--sim``, default ``pybullet``), built by the
plugin manager; the closed-loop episodes (observe) and ``threshold_agreement`` run on it too.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from msmem_cnabu.features import dilate, grid_interior, wall_mask
from msmem_cnabu.learn.datagen import CNABUShard, list_shards, load_shard
from msmem_core.errors import UserError
from msmem_core.plugins import ComponentRef

BINS = 15
MODELS = ("learned", "analytic", "no-change")
REGIONS = ("affected", "all")


class Calibration:
    """Pooled NLL, Brier and top-label ECE of occupancy and semantics over many voxels."""

    def __init__(self) -> None:
        self.n = 0
        self.sums = {"occ_nll": 0.0, "occ_brier": 0.0, "sem_nll": 0.0, "sem_brier": 0.0}
        self.bins = {k: np.zeros((3, BINS)) for k in ("occ", "sem")}  # count, confidence sum, correct sum

    def _bin(self, key: str, conf: NDArray[np.float64], correct: NDArray[np.bool_]) -> None:
        b = np.minimum((conf * BINS).astype(np.int64), BINS - 1)
        self.bins[key][0] += np.bincount(b, minlength=BINS)
        self.bins[key][1] += np.bincount(b, weights=conf, minlength=BINS)
        self.bins[key][2] += np.bincount(b, weights=correct.astype(np.float64), minlength=BINS)

    def add(self, p: NDArray[np.floating], y: NDArray[np.bool_], q: NDArray[np.floating],
            c: NDArray[np.integer]) -> None:
        """``p`` [N] expected occupancy, ``y`` [N] GT occupancy, ``q`` [C, N] class probabilities,
        ``c`` [N] GT class."""
        if len(p) == 0:
            return
        p = np.clip(np.asarray(p, np.float64), 1e-6, 1 - 1e-6)
        yf = np.asarray(y, np.float64)
        q = np.asarray(q, np.float64)
        c = np.asarray(c, np.int64)
        n = len(p)
        self.n += n
        self.sums["occ_nll"] += float(-(yf * np.log(p) + (1 - yf) * np.log(1 - p)).sum())
        self.sums["occ_brier"] += float(((p - yf) ** 2).sum())
        qy = np.clip(q[c, np.arange(n)], 1e-6, 1.0)
        self.sums["sem_nll"] += float(-np.log(qy).sum())
        self.sums["sem_brier"] += float(((q**2).sum(0) - 2 * q[c, np.arange(n)] + 1.0).sum())
        self._bin("occ", np.maximum(p, 1 - p), (p > 0.5) == (yf > 0.5))
        self._bin("sem", q.max(0), q.argmax(0) == c)

    def result(self) -> dict[str, float]:
        out = {k: v / max(self.n, 1) for k, v in self.sums.items()}
        for key in ("occ", "sem"):
            cnt, conf, corr = self.bins[key]
            out[f"{key}_ece"] = float(np.abs(conf - corr).sum() / max(cnt.sum(), 1.0))
        out["voxels"] = float(self.n)
        return out


def _score(cal: dict[str, Calibration], belief: Any, gt_occ: NDArray[np.bool_], gt_cls: NDArray[np.integer],
           regions: dict[str, NDArray[np.bool_]]) -> None:
    p = belief.expected_occupancy().reshape(-1)
    q = belief.class_probs().reshape(belief.num_classes, -1)
    y, c = gt_occ.reshape(-1), gt_cls.reshape(-1).astype(np.int64)
    for name, m in regions.items():
        i = np.flatnonzero(m.reshape(-1))
        cal[name].add(p[i], y[i], q[:, i], c[i])


class _ReplayObservation:
    """``analytic-observation`` fed with stored ray masks (its own ``update`` code, exact)."""

    def __init__(self) -> None:
        from msmem_analytic.observation import AnalyticObservationModel

        class Replay(AnalyticObservationModel):
            masks_given: tuple[Any, Any, Any] = (None, None, None)

            def masks(self, belief: Any, observation: Any) -> tuple[Any, Any, Any]:
                return self.masks_given

        self.model = Replay()

    def update(self, belief: Any, masks: tuple[Any, Any, Any]) -> Any:
        self.model.masks_given = masks
        return self.model.update(belief, None)  # type: ignore[arg-type]


def build_models(kind: str, weights: Path | None, change_threshold: float, change_epsilon: float = 0.0
                 ) -> tuple[Any, Any]:
    """(learned, analytic twin) belief models of ``kind``."""
    from msmem_cnabu.configs import CNABUEffectConfig, CNABUObserveConfig

    if kind == "observe":
        from msmem_cnabu.models import CNABUObservationModel

        return CNABUObservationModel(CNABUObserveConfig(weights=weights)), _ReplayObservation()
    if kind == "push":
        from msmem_push.effect import AnalyticPushEffect

        from msmem_cnabu.models import CNABUPushEffect

        return CNABUPushEffect(CNABUEffectConfig(weights=weights, change_threshold=change_threshold,
                                                 change_epsilon=change_epsilon)), AnalyticPushEffect()
    from msmem_grasp.effect import AnalyticGraspEffect

    from msmem_cnabu.models import CNABUGraspEffect

    return CNABUGraspEffect(CNABUEffectConfig(weights=weights, change_threshold=change_threshold,
                                              change_epsilon=change_epsilon)), AnalyticGraspEffect()


def _predict_state(kind: str, learned: Any, twin: Any, shard: CNABUShard, samples: list[int], belief: Any
                   ) -> dict[str, list[Any]]:
    if kind == "observe":
        return {
            "learned": [learned.update_masks(belief, *shard.masks(i)) for i in samples],
            "analytic": [twin.update(belief, shard.masks(i)) for i in samples],
        }
    actions = [shard.action(i) for i in samples]
    return {"learned": list(learned.predict(belief, actions, shard.workspace).beliefs),
            "analytic": list(twin.predict(belief, actions, shard.workspace).beliefs)}


def evaluate(
    kind: str,
    data_dir: str | Path,
    weights: str | Path | None = None,
    change_threshold: float = 0.85,
    timing: bool = True,
    candidates: int = 40,
    repeats: int = 3,
    threads: int = 2,
    log: Callable[[str], None] = print,
    episodes: int = 2,
    episode_steps: int = 40,
    simulator: str | ComponentRef = "pybullet",
    change_epsilon: float = 0.0,
) -> dict[str, Any]:
    """All metrics (see the module docstring) as a JSON-able dict. observe: also the rollout of each
    scene's recorded views and, with ``episodes`` > 0, closed-loop view-only episodes of
    ``episode_steps`` on generated scenes 10000, 10001, ... (``episode_nll``), whose NLL then decides
    ``better_nll`` (else the rollout's). ``simulator``: the backend of the timing and the episodes."""
    sim = _sim_ref(simulator)
    if (kind == "observe" and episodes > 0) or (kind != "observe" and timing):
        from msmem_core.sim.build import check_simulator

        check_simulator(sim)  # a bad --sim fails now, not after the metrics
    torch.set_num_threads(threads)
    paths = list_shards(data_dir, kind)
    learned, twin = build_models(kind, Path(weights) if weights is not None else None, change_threshold,
                                 change_epsilon)
    cal = {m: {r: Calibration() for r in REGIONS} for m in MODELS}
    changed = {m: 0.0 for m in MODELS}
    n_samples = n_scenes = 0
    first: CNABUShard | None = None
    for path in paths:
        shard = load_shard(path)
        if shard.kind != kind:
            raise UserError(f"{path} holds {shard.kind!r} samples, not {kind!r}")
        if not len(shard):
            continue
        n_scenes += 1
        first = first or shard
        valid = ~wall_mask(shard.grid, shard.interior)
        for s in range(shard.num_states):
            samples = [int(i) for i in np.flatnonzero(shard.state == s)]
            if not samples:
                continue
            belief = shard.belief(s)
            preds = _predict_state(kind, learned, twin, shard, samples, belief)
            preds["no-change"] = [belief] * len(samples)
            for j, i in enumerate(samples):
                gt_change = (shard.gt_occ[i] != shard.gt_occ_before[s]) | (shard.gt_cls[i] != shard.gt_cls_before[s])
                regions = {"affected": dilate(gt_change | shard.act_vox[i].any(0), 1) & valid, "all": valid}
                for m in MODELS:
                    b = preds[m][j]
                    _score(cal[m], b, shard.gt_occ[i], shard.gt_cls[i], regions)
                    diff = (b.alpha != belief.alpha) | (b.beta != belief.beta) | np.any(b.eta != belief.eta, axis=0)
                    changed[m] += float(diff.sum())
                n_samples += 1
    if first is None:
        raise UserError(f"the shards in {data_dir} hold no samples (no scene had a candidate); generate more scenes")
    result: dict[str, Any] = {
        "kind": kind, "data": str(data_dir), "scenes": n_scenes, "samples": n_samples,
        "weights": str(learned.meta.get("weights")), "weights_sha256": learned.meta.get("sha256"),
        "change_threshold": change_threshold, "change_epsilon": change_epsilon, "simulator": sim.model_dump(),
        "metrics": {m: {r: cal[m][r].result() for r in REGIONS} for m in MODELS},
        "changed_voxels_per_sample": {m: changed[m] / max(n_samples, 1) for m in MODELS},
    }
    nll = {m: result["metrics"][m]["affected"]["occ_nll"] + result["metrics"][m]["affected"]["sem_nll"]
           for m in ("learned", "analytic")}
    result["better_nll"] = result["better_nll_one_step"] = min(nll, key=nll.__getitem__)
    if kind == "observe":
        # the observe role is applied recursively (every view of an episode goes through it): it is
        # judged after integrating a scene's recorded views one after the other, each model on its own output
        result["rollout"] = rollout(learned, twin, paths)
        judged = result["rollout"]
        if episodes > 0:  # closed loop: the MSAS chooses the views on the model's own belief
            judged = result["episodes"] = episode_nll(weights, tuple(range(10000, 10000 + episodes)),
                                                      episode_steps, log=log, simulator=sim)
        r_nll = {m: judged["metrics"][m]["occ_nll"] + judged["metrics"][m]["sem_nll"] for m in ("learned", "analytic")}
        result["better_nll"] = min(r_nll, key=r_nll.__getitem__)
    if timing:
        result["timing"] = time_models(kind, learned, twin, first, candidates, repeats, log, sim)
    return result


def rollout(learned: Any, twin: Any, paths: list[Path]) -> dict[str, Any]:
    """observe: from each scene's first recorded belief, integrate all its recorded views in order with
    each model (the learned one on its own outputs, as in an episode); calibration of the final beliefs
    against the ground truth on all voxels but the boards, pooled over scenes ("no-change": the first
    belief), and the largest evidence each model reached."""
    cal = {m: Calibration() for m in MODELS}
    top = {m: 0.0 for m in MODELS}
    views = 0
    for path in paths:
        shard = load_shard(path)
        if not len(shard):
            continue
        valid = ~wall_mask(shard.grid, shard.interior)
        first = shard.belief(int(shard.state[0]))
        out = {"learned": first, "analytic": first, "no-change": first}
        for i in range(len(shard)):
            masks = shard.masks(i)
            out["learned"] = learned.update_masks(out["learned"], *masks)
            out["analytic"] = twin.update(out["analytic"], masks)
        views += len(shard)
        last = len(shard) - 1
        for m, b in out.items():
            _score({"all": cal[m]}, b, shard.gt_occ[last], shard.gt_cls[last], {"all": valid})
            top[m] = max(top[m], float(b.alpha.max()), float(b.beta.max()), float(b.eta.sum(0).max()))
    return {"views": views, "metrics": {m: cal[m].result() for m in MODELS}, "max_evidence": top}


def episode_nll(
    weights: str | Path | None = None,
    scene_seeds: tuple[int, ...] = (10000,),
    steps: int = 40,
    method: str = "view-only",
    log: Callable[[str], None] = print,
    simulator: str | ComponentRef = "pybullet",
) -> dict[str, Any]:
    """observe, closed loop: ``method`` episodes of ``steps`` actions on generated scenes (``scene_seeds``:
    10000 and up, never used for training data) with the learned and with the analytic observation
    model, each integrating every view into its own belief and the MSAS choosing the views on it, as
    ``msmem run`` does; calibration of the final belief against the final ground truth (all voxels
    but the boards), pooled over the scenes, plus the episodes' own metrics. The episodes run on
    ``simulator`` (``msmem_core.run.runner``)."""
    import tempfile

    from msmem_core.config import load_config
    from msmem_core.map.belief import EvidentialMap
    from msmem_core.plugins.manager import get_plugin_manager
    from msmem_core.run.runner import build_episode, run_episode

    sim = _sim_ref(simulator).model_dump()
    models = {"learned": {"name": "cnabu-observe", "params": {} if weights is None else {"weights": str(weights)}},
              "analytic": {"name": "analytic-observation"}}
    cal = {m: Calibration() for m in models}
    episodes: dict[str, list[dict[str, Any]]] = {m: [] for m in models}
    for seed in scene_seeds:
        for m, ref in models.items():
            cfg = load_config(method, None, {"scene": {"seed": seed, "file": None}, "steps": steps,
                                             "observation_model": ref, "simulator": sim})
            ep = build_episode(cfg, get_plugin_manager())
            with tempfile.TemporaryDirectory() as tmp:
                final = run_episode(ep, Path(tmp))
                belief = EvidentialMap.load(Path(tmp) / "belief_final.npz")
                gt = np.load(Path(tmp) / "gt_final.npz")
                gt_occ, gt_cls = gt["occupancy"] > 0, gt["classes"]
            valid = ~wall_mask(belief.grid, grid_interior(belief.grid, cfg.grid.margin_voxels))
            _score({"all": cal[m]}, belief, gt_occ, gt_cls, {"all": valid})
            episodes[m].append({"scene_seed": seed, **{k: v for k, v in final.items() if isinstance(v, float)}})
            log(f"episode {method} scene seed {seed}, {m} observation model: observable IoU "
                f"{final['observable_iou']:.3f}, semantic mIoU {final['semantic_miou']:.3f}")
    return {"method": method, "steps": steps, "scene_seeds": list(scene_seeds),
            "metrics": {m: cal[m].result() for m in models}, "episodes": episodes}


def _sim_ref(simulator: str | ComponentRef) -> ComponentRef:
    return ComponentRef(name=simulator) if isinstance(simulator, str) else simulator


def _best_of(fn: Callable[[], Any], repeats: int) -> float:
    best = np.inf
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return float(best)


def time_models(kind: str, learned: Any, twin: Any, shard: CNABUShard, candidates: int, repeats: int,
                log: Callable[[str], None] = print, simulator: str | ComponentRef = "pybullet") -> dict[str, Any]:
    """Prediction times of the learned model and its twin, and simulate-and-remap (see the module docstring)."""
    s = int(shard.state[0])
    samples = [int(i) for i in np.flatnonzero(shard.state == s)]
    belief = shard.belief(s)
    if kind == "observe":
        masks = shard.masks(samples[0])
        t_l = _best_of(lambda: learned.update_masks(belief, *masks), repeats)
        t_a = _best_of(lambda: twin.update(belief, masks), repeats)
        return {"learned_update_s": t_l, "analytic_update_s": t_a, "speedup_vs_analytic": t_a / t_l,
                "note": "both need the view's ray masks (the same traversal), not included"}
    actions = [shard.action(samples[j % len(samples)]) for j in range(candidates)]
    ws = shard.workspace
    learned.predict(belief, actions[:1], ws)  # warm-up
    t_l = _best_of(lambda: learned.predict(belief, actions, ws), repeats)
    t_a = _best_of(lambda: twin.predict(belief, actions, ws), repeats)
    t_sim = simulate_and_remap(kind, shard, s, [shard.action(samples[j % len(samples)]) for j in range(repeats)], log,
                               simulator)
    per = t_l / candidates
    return {
        "candidates": candidates,
        "learned_batch_s": t_l, "learned_per_candidate_s": per,
        "analytic_batch_s": t_a, "analytic_per_candidate_s": t_a / candidates,
        "simulate_and_remap_s": t_sim,
        "speedup_per_candidate": t_sim / per,
        "speedup_whole_batch": t_sim / t_l,
    }


def simulate_and_remap(kind: str, shard: CNABUShard, state: int, actions: list[Any],
                       log: Callable[[str], None] = print, simulator: str | ComponentRef = "pybullet") -> float:
    """Mean seconds of: snapshot, execute in ``simulator``, re-observe, integrate, restore (per action).
    The world is the shard's scene after ``reset`` (the state's belief is only a stand-in: the timing
    does not depend on it)."""
    from types import SimpleNamespace

    from msmem_analytic.observation import AnalyticObservationModel

    from msmem_cnabu.learn.datagen import _skill
    from msmem_core.sim.build import build_simulator
    from msmem_core.world.scenegen import SceneGenConfig, generate_scene
    from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

    hard = bool(shard.info.get("config", {}).get("require_hard", False))
    scene = generate_scene(shard.seed, SceneGenConfig(require_hard=hard))
    viewpoints = generate_viewpoints(ViewpointConfig(), scene.shelf)
    view = viewpoints[int(shard.state_view[state])]
    belief = shard.belief(state)
    model = AnalyticObservationModel()
    skill = _skill(kind, shard.seed)
    ctx = SimpleNamespace(shelf=scene.shelf)
    sim = build_simulator(_sim_ref(simulator), seed=shard.seed)
    times = []
    try:
        sim.reset(scene)
        for a in actions:
            t = time.perf_counter()
            token = sim.snapshot()
            skill.execute(sim, a, ctx)
            model.update(belief, sim.observe(view))
            sim.restore(token)
            times.append(time.perf_counter() - t)
    finally:
        sim.close()
    return float(np.mean(times))


def _cal_cells(x: dict[str, float]) -> str:
    """The six calibration cells of a Markdown row."""
    return (f"{x['occ_nll']:.4f} | {x['occ_brier']:.4f} | {x['occ_ece']:.4f} | "
            f"{x['sem_nll']:.4f} | {x['sem_brier']:.4f} | {x['sem_ece']:.4f}")


def format_table(r: dict[str, Any]) -> str:
    """The metrics as a Markdown table plus the timing line(s)."""
    lines = [f"cnabu-{r['kind']} on {r['samples']} samples from {r['scenes']} scenes ({r['data']}); "
             f"weights {r['weights']} (sha256 {str(r['weights_sha256'])[:12]}...)", "",
             "| region | model | occ NLL | occ Brier | occ ECE | sem NLL | sem Brier | sem ECE "
             "| changed voxels/sample |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for reg in REGIONS:
        for m in MODELS:
            x = r["metrics"][m][reg]
            lines.append(f"| {reg} | {m} | {_cal_cells(x)} | {r['changed_voxels_per_sample'][m]:.0f} |")
    if "rollout" in r:
        ro = r["rollout"]
        lines += ["", f"rollout: each scene's recorded views ({ro['views']} in all) integrated one after the other "
                      "(all voxels, final belief)", "",
                  "| model | occ NLL | occ Brier | occ ECE | sem NLL | sem Brier | sem ECE | largest evidence |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for m in MODELS:
            x = ro["metrics"][m]
            lines.append(f"| {m} | {_cal_cells(x)} | {ro['max_evidence'][m]:.0f} |")
        ep = r.get("episodes")
        if ep:
            lines += ["", f"closed loop: {ep['method']} episodes of {ep['steps']} steps on generated scenes "
                          f"{', '.join(map(str, ep['scene_seeds']))}, each model integrating every view into its own "
                          "belief (all voxels, final belief)", "",
                      "| model | occ NLL | occ Brier | occ ECE | sem NLL | sem Brier | sem ECE | observable IoU "
                      "| semantic mIoU |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
            for m, x in ep["metrics"].items():
                eps = ep["episodes"][m]
                lines.append(f"| {m} | {_cal_cells(x)} | {np.mean([e['observable_iou'] for e in eps]):.3f} | "
                             f"{np.mean([e['semantic_miou'] for e in eps]):.3f} |")
        lines += ["", f"better NLL one step (occupancy + semantics, affected region): {r['better_nll_one_step']}",
                  f"better NLL {'in closed loop' if ep else 'after the rollout'} (decides the default): "
                  f"{r['better_nll']}"]
    else:
        lines += ["", f"better NLL (occupancy + semantics, affected region): {r['better_nll']}"]
    t = r.get("timing")
    if t and "learned_batch_s" in t:
        lines.append(
            f"timing: learned {t['candidates']} candidates in {t['learned_batch_s']:.3f} s "
            f"({1000 * t['learned_per_candidate_s']:.1f} ms per candidate), analytic {t['analytic_batch_s']:.3f} s "
            f"({1000 * t['analytic_per_candidate_s']:.1f} ms), simulate-and-remap {t['simulate_and_remap_s']:.2f} s "
            f"per candidate -> speed-up {t['speedup_per_candidate']:.0f}x per candidate "
            f"({t['speedup_whole_batch']:.1f}x for the whole batch of {t['candidates']})")
    elif t:
        lines.append(f"timing: learned update {1000 * t['learned_update_s']:.1f} ms, analytic update "
                     f"{1000 * t['analytic_update_s']:.1f} ms per view (ray masks excluded)")
    return "\n".join(lines)


# ------------------------------------------------------------------------- threshold and decisions
def threshold_agreement(
    kind: str,
    weights: str | Path | None = None,
    thresholds: tuple[float, float] = (0.85, 0.05),
    beliefs: int = 5,
    views: int = 10,
    scene_seed: int = 1,
    threads: int = 2,
    log: Callable[[str], None] = print,
    simulator: str | ComponentRef = "pybullet",
    epsilon: float = 0.0,
) -> dict[str, Any]:
    """How often ``change_threshold`` changes the chosen action (docs/explanation/cnabu.md, "The change threshold").

    On ``beliefs`` mid-episode beliefs (``msmem perf step``'s: generated scene ``scene_seed``, the
    start view plus ``views - 1`` seeded random views, seeds 0, 1, ...), method ``ours`` with the
    learned ``kind`` effect model decides once with each threshold (the MSAS's full ``decide``: views,
    pushes and grasps through OIG and CDC). The first threshold goes with ``change_epsilon`` =
    ``epsilon``, the second (the nearly dense reference) with 0. Returns per belief the two
    decisions and whether they agree,
    and the changed voxels per candidate of the manipulation batch at each threshold. The episode's
    world runs on ``simulator``.
    """
    from msmem_core.config import load_config
    from msmem_core.msas import decide
    from msmem_core.plugins.manager import get_plugin_manager
    from msmem_core.run.runner import build_episode
    from msmem_core.run.states import clone_skills, decision_context, mid_episode_state

    if kind not in ("push", "grasp"):
        raise UserError(f"--threshold-check needs an effect model (push or grasp), not {kind!r}")
    torch.set_num_threads(threads)
    params: dict[str, Any] = {"change_threshold": thresholds[0], "change_epsilon": epsilon}
    if weights is not None:
        params["weights"] = str(weights)
    # the beliefs of the analytic update and MEM's IG for predictions, under which the effect models'
    # thresholds were chosen
    cfg = load_config("ours", None, {"scene": {"seed": scene_seed}, "simulator": _sim_ref(simulator).model_dump(),
                                     "observation_model": {"name": "analytic-observation"},
                                     "ig": {"predicted_entropy": "as-predicted"}})
    skills = [s.model_copy(update={"effect_model": ComponentRef(name=f"cnabu-{kind}", params=params)})
              if s.name == kind else s for s in cfg.skills]
    cfg = cfg.model_copy(update={"skills": skills})
    ep = build_episode(cfg, get_plugin_manager())
    ep.sim.reset(ep.scene)
    bound = next(b for b in ep.skills if b.name == kind)
    model = bound.effect_model
    assert model is not None
    base_cfg = model.config  # type: ignore[attr-defined]
    rows = []
    for b in range(beliefs):
        st = mid_episode_state(ep, views, b)
        row: dict[str, Any] = {"belief": b}
        for t, eps in zip(thresholds, (epsilon, 0.0), strict=True):
            model.config = base_cfg.model_copy(update={"change_threshold": t, "change_epsilon": eps})  # type: ignore[attr-defined]
            ctx = decision_context(ep, st.belief, st.visited, st.step)
            d = decide(ctx, clone_skills(st.skills), ep.objective)
            batch = d.batch if d.skill.name == kind else None
            changed = None
            if batch is not None and batch.prediction is not None and len(batch.actions):
                changed = float(np.mean([len(c.idx) for c in batch.prediction.changes]))
            row[str(t)] = {"skill": d.skill.name, "index": int(d.index), "action": d.action.model_dump(mode="json"),
                           "changed_voxels_per_candidate": changed,
                           "best_per_skill": {k: float(v) for k, v in d.best.items()}}
        a, c = (row[str(t)] for t in thresholds)
        row["same"] = a["skill"] == c["skill"] and a["action"] == c["action"]
        log(f"belief {b}: threshold {thresholds[0]} (epsilon {epsilon}): {a['skill']} #{a['index']}; "
            f"threshold {thresholds[1]}: {c['skill']} #{c['index']} -> {'same' if row['same'] else 'DIFFERENT'}")
        rows.append(row)
    model.config = base_cfg  # type: ignore[attr-defined]
    same = sum(r["same"] for r in rows)
    log(f"the change threshold {thresholds[0]} with epsilon {epsilon} (vs {thresholds[1]}) changed the chosen "
        f"action in {len(rows) - same} of {len(rows)} decisions")
    return {"kind": kind, "thresholds": list(thresholds), "epsilon": epsilon, "beliefs": rows, "same": same,
            "decisions": len(rows)}

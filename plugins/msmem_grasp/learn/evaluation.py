"""Held-out evaluation of FE-vMF against a geometric antipodal heuristic (``msmem eval fe-vmf``).

Metrics (over all points of all scenes; orientation metrics on the positives):
affordance AUROC and ECE (10 bins), precision / recall of the grasps with affordance > 0.5, the
positive rate among the 5 % highest-affordance points (what UGS picks from),
orientation NLL (nats, mean over a point's GT directions, as the training loss) and median / mean
angular error to the nearest GT direction for the approach a (FE-vMF: the projection of eq. proj)
and the directed baseline b, and the width error against the mean GT width.

The heuristic sees the same FPP cloud and learns nothing: at contact c with FPP normal n it takes
b = -n, and looks for an opposite contact among the cloud points within ``max_width_m`` along -n
and ``lateral_m`` of that line; its affordance score is the best alignment n' . (-n) of such a
point's normal n' (0 if none), and it predicts a grasp where that passes the friction-cone test
(>= cos atan(mu)). Its approach is the direction orthogonal to b closest to ``approach_prior``: top-down
(-z) fits the GT of the training scenes best among +-x, +-y, +-z and (0, 0.7, -0.7) (median error 32 deg
on 10 training scenes, 46 deg for -y, 78 deg for +y, the front approach); its one kappa per direction
is the maximum-likelihood value on the evaluation set itself (which flatters its NLL).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from msmem_core.world.geometry import F64
from msmem_grasp.learn.datagen import GraspShard, list_shards, load_shard
from msmem_grasp.metrics import (
    angular_error,
    auroc,
    calibration_bins,
    ece,
    expected_angle_deg,
    kappa_mle,
    precision_recall,
    vmf_nll,
)


class HeuristicConfig(BaseModel):
    """The geometric antipodal baseline."""

    model_config = ConfigDict(extra="forbid")

    max_width_m: float = Field(0.08, gt=0.0)
    min_width_m: float = Field(0.005, ge=0.0)
    lateral_m: float = Field(0.01, gt=0.0)
    """Radius of the cylinder around the line c - t n in which an opposite contact is searched."""
    friction: float = Field(0.5, gt=0.0)
    approach_prior: tuple[float, float, float] = (0.0, 0.0, -1.0)
    """Gripper approach a (palm to fingertips) the heuristic prefers: top-down."""


@dataclass
class Prediction:
    """Per-point outputs of a grasp predictor on one shard (numpy, float64)."""

    affordance: F64  # [N]
    grasp: NDArray[np.bool_]  # [N] predicted graspable
    mu_a: F64  # [N, 3]
    kappa_a: F64  # [N]
    mu_b: F64  # [N, 3]
    kappa_b: F64  # [N]
    width: F64  # [N]


def heuristic_predict(shard: GraspShard, cfg: HeuristicConfig | None = None) -> Prediction:
    """The geometric antipodal heuristic on one cloud (vectorised over point pairs)."""
    cfg = cfg or HeuristicConfig()
    pts = shard.points.astype(np.float64)
    n = shard.normals.astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    b = -n
    score = np.zeros(len(pts))
    width = np.full(len(pts), np.nan)
    if len(pts) > 1:
        pairs = cKDTree(pts).query_pairs(cfg.max_width_m, output_type="ndarray")
        i = np.concatenate([pairs[:, 0], pairs[:, 1]])
        j = np.concatenate([pairs[:, 1], pairs[:, 0]])
        v = pts[j] - pts[i]
        along = np.einsum("pk,pk->p", v, b[i])
        lateral = np.linalg.norm(v - along[:, None] * b[i], axis=1)
        align = np.einsum("pk,pk->p", n[j], b[i])  # outward normal at the far contact along b
        ok = (along >= cfg.min_width_m) & (along <= cfg.max_width_m) & (lateral <= cfg.lateral_m) & (align > 0)
        i, align, along = i[ok], align[ok], along[ok]
        order = np.lexsort((-align, i))  # per i, best alignment first
        i, align, along = i[order], align[order], along[order]
        first = np.r_[True, i[1:] != i[:-1]] if len(i) else np.zeros(0, bool)
        score[i[first]] = align[first]
        width[i[first]] = along[first]
    cos_cone = 1.0 / np.sqrt(1.0 + cfg.friction**2)
    prior = np.broadcast_to(np.asarray(cfg.approach_prior, dtype=np.float64), pts.shape)
    a = prior - np.einsum("pk,pk->p", prior, b)[:, None] * b
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    fallback = np.cross(b, np.where(np.abs(b[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    a = np.where(norm > 1e-6, a / np.maximum(norm, 1e-12), fallback / np.linalg.norm(fallback, axis=1, keepdims=True))
    width = np.where(np.isnan(width), 0.5 * cfg.max_width_m, width)
    ones = np.ones(len(pts))
    return Prediction(score, score >= cos_cone, a, ones, b, ones, width)


def model_predict(model: Any, shard: GraspShard) -> Prediction:
    from msmem_grasp.learn.training import predict_shard

    out = predict_shard(model, shard)
    mu_a, kappa_a = out.approach()
    q = out.affordance.double().numpy()
    return Prediction(q, q > 0.5, mu_a.double().numpy(), kappa_a.double().numpy(), out.mu_b.double().numpy(),
                      out.kappa_b.double().numpy(), out.width.double().numpy())


def _metrics(
    preds: list[Prediction], shards: list[GraspShard], fit_kappa: bool
) -> tuple[dict[str, float], dict[str, F64]]:
    q = np.concatenate([p.affordance for p in preds])
    y = np.concatenate([s.label for s in shards])
    grasp = np.concatenate([p.grasp for p in preds])
    prec, rec = precision_recall(grasp, y)
    keys = ("err_a", "err_b", "ka", "kb", "cos_a", "cos_b", "w_err", "nll_a", "nll_b")
    per: dict[str, list[F64]] = {k: [] for k in keys}
    for p, s in zip(preds, shards, strict=True):
        idx = s.positive_index
        if not len(idx):
            continue
        for name, mu, kappa, tgt in (("a", p.mu_a, p.kappa_a, s.approach), ("b", p.mu_b, p.kappa_b, s.baseline)):
            per[f"err_{name}"].append(angular_error(mu[idx], tgt, s.mask))
            per[f"k{name}"].append(kappa[idx])
            m = s.mask.astype(np.float64)
            mean_t = (tgt * m[..., None]).sum(1) / np.maximum(m.sum(1, keepdims=True), 1.0)
            per[f"cos_{name}"].append(np.einsum("pk,pk->p", mu[idx], mean_t))
            per[f"nll_{name}"].append(vmf_nll(mu[idx], kappa[idx], tgt, s.mask))
        gt_w = (s.width * s.mask).sum(1) / np.maximum(s.mask.sum(1), 1)
        per["w_err"].append(np.abs(p.width[idx] - gt_w))
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in per.items()}
    out: dict[str, float] = {
        "auroc": auroc(q, y), "ece": ece(q, y), "precision": prec, "recall": rec,
        "predicted_fraction": float(grasp.mean()) if len(grasp) else float("nan"),
        "precision_top5": _precision_top(q, y, 0.05),
    }
    for name in ("a", "b"):
        err = np.degrees(cat[f"err_{name}"])
        out[f"err_{name}_median_deg"] = float(np.median(err)) if len(err) else float("nan")
        out[f"err_{name}_mean_deg"] = float(err.mean()) if len(err) else float("nan")
        if fit_kappa:  # one kappa for all points: the MLE on this very set
            k = kappa_mle(float(cat[f"cos_{name}"].mean())) if len(err) else float("nan")
            out[f"kappa_{name}"] = k
            mt = cat[f"cos_{name}"]
            nll = -_log_c(k) - k * mt
        else:
            nll = cat[f"nll_{name}"]
        out[f"nll_{name}"] = float(nll.mean()) if len(nll) else float("nan")
    out["width_mae_mm"] = float(1000 * cat["w_err"].mean()) if len(cat["w_err"]) else float("nan")
    return out, cat


def _precision_top(q: F64, y: F64, fraction: float) -> float:
    """Positive rate among the ``fraction`` of points with the highest affordance (ties broken at random,
    seeded), i.e. how good the grasps UGS would pick first are."""
    k = max(1, round(fraction * len(q)))
    if not len(q):
        return float("nan")
    jitter = np.random.default_rng(0).random(len(q)) * 1e-9
    top = np.argsort(-(q + jitter), kind="stable")[:k]
    return float(np.mean(y[top] > 0.5))


def _log_c(kappa: float) -> float:
    from msmem_grasp.vmf import log_normaliser

    return float(log_normaliser(torch.tensor(kappa, dtype=torch.float64)))


def evaluate(
    data_dir: str | Path,
    weights: str | Path | None = None,
    plot: str | Path | None = None,
    threads: int = 2,
    heuristic: HeuristicConfig | None = None,
    max_scenes: int | None = None,
) -> dict[str, Any]:
    """Metrics of FE-vMF (weights at ``weights``, default the shipped ones) and of the heuristic on
    every shard of ``data_dir``; optionally write the kappa calibration plot."""
    from msmem_core.util.artifacts import sha256_file
    from msmem_grasp.weights import SHIPPED_WEIGHTS, load_fe_vmf

    torch.set_num_threads(threads)
    paths = list_shards(data_dir)[:max_scenes]
    shards = [load_shard(p) for p in paths]
    wpath = Path(weights) if weights is not None else SHIPPED_WEIGHTS
    model = load_fe_vmf(wpath)
    t0 = time.perf_counter()
    model_preds = [model_predict(model, s) for s in shards]
    seconds = (time.perf_counter() - t0) / max(len(shards), 1)
    heur_preds = [heuristic_predict(s, heuristic) for s in shards]
    m_model, cat = _metrics(model_preds, shards, fit_kappa=False)
    m_heur, _ = _metrics(heur_preds, shards, fit_kappa=True)
    m_model["seconds_per_cloud"] = seconds
    calib = {"a": calibration_bins(cat["ka"], cat["err_a"]), "b": calibration_bins(cat["kb"], cat["err_b"])}
    result = {
        "data": str(data_dir),
        "scenes": len(shards),
        "points": int(sum(len(s) for s in shards)),
        "positives": int(sum(len(s.positive_index) for s in shards)),
        "weights": str(wpath),
        "sha256": sha256_file(wpath),
        "fe_vmf": m_model,
        "heuristic": m_heur,
        "calibration": calib,
    }
    if plot is not None:
        calibration_plot(calib, m_heur, plot)
    return result


def calibration_plot(calib: dict[str, dict[str, list[float]]], heur: dict[str, float], path: str | Path) -> None:
    """Predicted kappa (quantile bins) against the observed mean angular error, for a and b, with the
    error a vMF of that kappa implies (perfect calibration) and the heuristic's single kappa."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), constrained_layout=True)
    grid = np.logspace(-1, 3, 200)
    ideal = [expected_angle_deg(k) for k in grid]
    for ax, name, title in ((axes[0], "a", "approach a (projected)"), (axes[1], "b", "baseline b")):
        c = calib[name]
        ax.plot(grid, ideal, color="0.6", lw=1, label="vMF-implied E[angle]")
        ax.plot(c["kappa"], c["error_deg"], "o-", color="C0", label="FE-vMF (quantile bins)")
        k = heur.get(f"kappa_{name}", float("nan"))
        if np.isfinite(k):
            ax.plot([max(k, 0.1)], [heur[f"err_{name}_mean_deg"]], "s", color="C3", label="heuristic (MLE kappa)")
        ax.set_xscale("log")
        ax.set_xlabel("predicted kappa")
        ax.set_ylabel("mean angular error to nearest GT (deg)")
        ax.set_title(title)
        ax.set_ylim(0, 180)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_table(m: dict[str, Any]) -> str:
    """The metrics of FE-vMF and the heuristic side by side."""
    rows = [
        ("affordance AUROC", "auroc", "{:.3f}"), ("affordance ECE", "ece", "{:.3f}"),
        ("precision (q > 0.5)", "precision", "{:.3f}"), ("recall (q > 0.5)", "recall", "{:.3f}"),
        ("precision of the top 5 %", "precision_top5", "{:.3f}"),
        ("approach a NLL (nats)", "nll_a", "{:.2f}"), ("approach a error median (deg)", "err_a_median_deg", "{:.1f}"),
        ("approach a error mean (deg)", "err_a_mean_deg", "{:.1f}"),
        ("baseline b NLL (nats)", "nll_b", "{:.2f}"), ("baseline b error median (deg)", "err_b_median_deg", "{:.1f}"),
        ("baseline b error mean (deg)", "err_b_mean_deg", "{:.1f}"), ("width MAE (mm)", "width_mae_mm", "{:.1f}"),
    ]
    lines = [f"{m['scenes']} scenes, {m['points']} points, {m['positives']} positives; weights {m['weights']}",
             f"{'metric':32s} {'FE-vMF':>9s} {'heuristic':>10s}"]
    for label, key, fmt in rows:
        lines.append(f"{label:32s} {fmt.format(m['fe_vmf'][key]):>9s} {fmt.format(m['heuristic'][key]):>10s}")
    lines.append(f"FE-vMF inference: {m['fe_vmf']['seconds_per_cloud']:.2f} s per cloud")
    return "\n".join(lines)

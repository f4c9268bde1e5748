"""Write ``MODEL_CARD.md`` for FE-vMF weights from their sidecar and an evaluation JSON.

    python -m msmem_grasp.learn.modelcard --weights plugins/msmem_grasp/weights/fe_vmf.pt \\
        --eval runs/grasp-eval.json --notes runs/grasp-notes.json

``--notes`` (optional JSON) adds facts the sidecar cannot know: the data-generation commands and
their throughput, the training command, the machine.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from msmem_core.util.artifacts import sidecar_path
from msmem_grasp.learn.evaluation import format_table


def _ranges(seeds: list[int]) -> str:
    if not seeds:
        return "none"
    seeds = sorted(seeds)
    out, start, prev = [], seeds[0], seeds[0]
    for s in [*seeds[1:], None]:
        if s is not None and s == prev + 1:
            prev = s
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if s is not None:
            start = prev = s
    return ", ".join(out)


def model_card(weights: Path, metrics: dict[str, Any], notes: dict[str, Any] | None = None) -> str:
    side = json.loads(sidecar_path(weights).read_text())
    notes = notes or {}
    best = side["best"]
    train_cfg = side["train"]
    data = side["data"]
    manifest = data.get("manifest") or {}
    gen_cfg = manifest.get("config", {})
    n_params = notes.get("parameters", "?")
    h, m = metrics["heuristic"], metrics["fe_vmf"]
    lines = [
        "# FE-vMF weights: `fe_vmf.pt`",
        "",
        "Full-evidential vMF-Contact grasp network (paper sec. \"Full-Evidential Grasp Learning\"): per point of",
        "an FPP cloud, a vMF over the intermediate approach a_hat and over the directed baseline b, Beta",
        "affordance evidence and a width. Loaded by `msmem_grasp.weights.load_fe_vmf()`, which checks the hash",
        "below against `fe_vmf.json` (the training sidecar: configs, data, per-epoch history).",
        "",
        f"- **sha256**: `{side['sha256']}`",
        f"- **size**: {side['bytes']} bytes (float32 state dict, {n_params} parameters)",
        f"- **architecture**: `{json.dumps(side['model'])}`",
        f"- **input**: FPP points (world frame, metres) + features {side['features']}",
        f"- **torch**: {side['torch']}",
        "",
        "## Data",
        "",
        "Simulated shelf scenes (`msmem_core.world.scenegen`, random arrangements at 30-45 % floor occupancy,",
        f"require_hard={gen_cfg.get('require_hard')}), settled in PyBullet, observed from "
        f"{gen_cfg.get('min_views')}-{gen_cfg.get('max_views')} random viewpoints of the 300",
        "into an analytic evidential belief (1 cm voxels); FPP from the visited views, "
        f"{gen_cfg.get('fpp', {}).get('num_points')} points per scene; a point is",
        "positive within max(2 mm, half a voxel) = 5 mm of a contact of the collision-free antipodal ground truth",
        "(`antipodal.grasps_in_scene` at the settled poses).",
        "",
        f"- training scenes: seeds {_ranges(data['train_scenes'])} ({len(data['train_scenes'])} scenes)",
        f"- validation scenes (seeded split, best epoch chosen on them): seeds {_ranges(data['val_scenes'])}"
        f" ({len(data['val_scenes'])})",
        f"- held-out test scenes (never seen in training or selection): {metrics['scenes']} scenes in"
        f" `{Path(metrics['data']).name}`, {metrics['points']} points, {metrics['positives']} positives",
    ]
    for cmd in notes.get("datagen_commands", []):
        lines.append(f"- `{cmd}`")
    if "datagen" in notes:
        lines.append(f"- throughput: {notes['datagen']}")
    lines += [
        "",
        "## Training",
        "",
        f"- command: `{notes.get('train_command', 'msmem train fe-vmf')}`",
        f"- AdamW, peak lr {train_cfg['lr']}, weight decay {train_cfg['weight_decay']}, warm-up "
        f"{train_cfg['warmup_steps']} steps + cosine decay, {train_cfg['batch_scenes']} scenes per step, "
        f"x-mirror augmentation: {train_cfg['mirror']}, seed {train_cfg['seed']}",
        f"- epochs run: {side['epochs_run']} (of {train_cfg['epochs']} planned); best epoch {best['epoch']}"
        f" (lowest validation loss {best['score']:.4f}, validation AUROC {best['val'].get('auroc', float('nan')):.3f})",
        f"- time: {side['train_seconds'] / 60:.1f} min on {notes.get('machine', 'CPU')}",
        "",
        "## Held-out metrics vs the geometric antipodal heuristic",
        "",
        "Heuristic (no learning, same FPP cloud): b = -normal, affordance from a normal-opposition test",
        "along -normal within 8 cm, approach orthogonal to b closest to top-down; its single kappa per",
        "direction is fitted on the test set itself. See `msmem_grasp.learn.evaluation`.",
        "",
        "| metric | FE-vMF | heuristic |",
        "| --- | ---: | ---: |",
    ]
    rows = [
        ("affordance AUROC", "auroc", "{:.3f}"), ("affordance ECE", "ece", "{:.3f}"),
        ("precision (q > 0.5)", "precision", "{:.3f}"), ("recall (q > 0.5)", "recall", "{:.3f}"),
        ("precision of the top 5 % by affordance", "precision_top5", "{:.3f}"),
        ("approach a NLL (nats)", "nll_a", "{:.2f}"), ("approach a error, median (deg)", "err_a_median_deg", "{:.1f}"),
        ("approach a error, mean (deg)", "err_a_mean_deg", "{:.1f}"), ("baseline b NLL (nats)", "nll_b", "{:.2f}"),
        ("baseline b error, median (deg)", "err_b_median_deg", "{:.1f}"),
        ("baseline b error, mean (deg)", "err_b_mean_deg", "{:.1f}"), ("width MAE (mm)", "width_mae_mm", "{:.1f}"),
    ]
    for label, key, fmt in rows:
        lines.append(f"| {label} | {fmt.format(m[key])} | {fmt.format(h[key])} |")
    lines += [
        "",
        f"Angular errors are to the nearest GT direction at the point; NLL is averaged over the point's GT"
        f" directions (as the loss). Inference: {m['seconds_per_cloud']:.2f} s per"
        f" {metrics['points'] // max(metrics['scenes'], 1)}-point cloud"
        " (1 CPU thread). Calibration plot: `docs/img/fevmf_calibration.png`.",
        "",
        "## Intended use and limits",
        "",
        "- Grasp hypotheses for UGS on beliefs made like the training ones (PyBullet, analytic observation",
        "  model, 1 cm voxels, the 15 procedural classes); not validated on real sensors or other grids.",
        "- Trained on a few hundred scenes on a CPU: a proof of the pipeline, far from the paper's 4e3 scenes.",
        "- Contacts are only labelled where the FPP point lies within 5 mm of a GT contact; the approach is",
        "  multi-modal at most contacts, so kappa_a is low by design.",
        "",
        "## Reproduce",
        "",
        "```",
        *notes.get("datagen_commands", []),
        notes.get("train_command", ""),
        notes.get("eval_command", ""),
        "```",
        "",
        "```",
        format_table(metrics),
        "```",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", type=Path, required=True)
    ap.add_argument("--eval", type=Path, required=True, help="JSON from `msmem eval fe-vmf --json`")
    ap.add_argument("--notes", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None, help="default: MODEL_CARD.md beside the weights")
    args = ap.parse_args()
    notes = json.loads(args.notes.read_text()) if args.notes else None
    text = model_card(args.weights, json.loads(args.eval.read_text()), notes)
    out = args.out or args.weights.parent / "MODEL_CARD.md"
    out.write_text(text)
    print(out)


if __name__ == "__main__":
    main()

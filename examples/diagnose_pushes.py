"""Diagnose the pushes of one episode against the simulator's ground truth.

    .venv/bin/python examples/diagnose_pushes.py METHOD SCENE.json STEPS [CONFIG.yaml]
    .venv/bin/python examples/diagnose_pushes.py push-only msmem_core/suites/tune10/scene_00.json 40

A tracer on the episode (``msmem_core.util.trace``): when the ``execute`` span of a push ends, the
observable-voxel confusion (TP / FP / FN, the counts behind ``observable_iou``) of the belief before
the push and of the effect model's prediction for it (the one MSAS scored), both against the ground
truth *after* the push. At the end, the same for the final belief, and where its false positives
are: how many never received free-space evidence (beta = 1: no ray of any view passed through them
since they became occupied) and how far they lie from the nearest really occupied voxel. Ground
truth is only read for printing; the episode runs as ``msmem run`` runs it.
"""

import sys
from pathlib import Path
from typing import Any

from msmem_push.skill import PushAction
from scipy import ndimage

from msmem_core.config import load_config
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins.manager import get_plugin_manager
from msmem_core.run.metrics import prediction_from_belief
from msmem_core.run.runner import Episode, MetricTracker, build_episode, run_episode
from msmem_core.util.trace import Span, Tracer


def confusion(tracker: MetricTracker, belief: EvidentialMap) -> dict[str, Any]:
    pred, _ = prediction_from_belief(belief.expected_occupancy(), belief.class_probs())
    pred &= ~tracker.walls
    gt, m = tracker.gt_occ, tracker.mask
    tp, fp, fn = (int(x.sum()) for x in (pred & gt & m, pred & ~gt & m, ~pred & gt & m))
    return {"iou": tp / max(tp + fp + fn, 1), "tp": tp, "fp": fp, "fn": fn, "fp_mask": pred & ~gt & m}


def line(label: str, c: dict[str, Any]) -> str:
    return f"  {label:<22} observable IoU {c['iou']:.3f}  TP {c['tp']:6d}  FP {c['fp']:6d}  FN {c['fn']:6d}"


class PushDiagnosis(Tracer):
    def __init__(self, ep: Episode) -> None:
        self.ep = ep
        self.tracker: MetricTracker | None = None

    def end(self, span: Span) -> None:
        if span.stage != "execute" or span.error is not None:
            return
        d, ctx = span.info["decision"], span.info["ctx"]
        if not isinstance(d.action, PushAction) or d.batch.prediction is None:
            return
        tracker = self.tracker = self.tracker or MetricTracker(self.ep)
        tracker(ctx.belief)  # ground truth after the push
        predicted = d.batch.prediction.belief(d.index)
        print(f"step {ctx.step}: push of {d.action.length_m:.3f} m", flush=True)
        print(line("before (no change)", confusion(tracker, ctx.belief)))
        print(line("prediction", confusion(tracker, predicted)), flush=True)


def main(method: str, scene: str, steps: int, config: str | None = None) -> None:
    cfg = load_config(method=method, config_file=config, overrides={"scene": {"file": scene}, "steps": steps})
    ep = build_episode(cfg, get_plugin_manager())
    out_dir = Path("runs") / f"diagnose-pushes-{method}-{Path(scene).stem}"
    final = run_episode(ep, out_dir, tracer=PushDiagnosis(ep))
    tracker = MetricTracker(ep)  # ground truth of the final scene
    belief = EvidentialMap.load(out_dir / "belief_final.npz")
    c = confusion(tracker, belief)
    print("final belief:")
    print(line("final", c))
    fp = c["fp_mask"]
    dist = ndimage.distance_transform_edt(~tracker.gt_occ)[fp]
    never = int((belief.beta[fp] <= 1.0).sum())
    print(f"  of its {c['fp']} false positives: {never} never received free-space evidence (beta = 1); "
          f"distance to the nearest occupied voxel <= 1: {int((dist <= 1).sum())}, <= 2: {int((dist <= 2).sum())}, "
          f"<= 4: {int((dist <= 4).sum())}, > 4: {int((dist > 4).sum())} voxels")
    print({k: round(v, 3) for k, v in final.items() if isinstance(v, float)}, final["actions"])


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] if len(sys.argv) > 4 else None)

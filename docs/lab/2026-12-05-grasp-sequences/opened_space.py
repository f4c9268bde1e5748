"""What the map networks make of the space a grasp opened, on held-out grasp sequences.

    L=docs/lab/2026-12-05-grasp-sequences      # from the repository root
    .venv/bin/python $L/opened_space.py data/map_heldout_grasp msmem_cnabu/weights/cnabu_map.pt runs/map_run15.pt

For every shard whose grasp held its object, each network (raw, as ``msmem eval map`` rolls it out:
the grasp-analytic prediction at the grasp, then the recorded views) and the analytic update are
rolled out; the final beliefs are scored on the removed object's voxels (free after the grasp: mean
expected occupancy, share called occupied) and on the top view of the columns it stood on (share of
columns whose top class is right), besides the whole-map 2-D semantic mIoU.
"""

from __future__ import annotations

import sys

import numpy as np
import torch
from msmem_analytic.observation import AnalyticObservationModel
from msmem_cnabu.learn.datagen import list_shards, load_shard
from msmem_cnabu.learn.rollouts import Effects, manipulate, sequence
from msmem_cnabu.weights import load_map_net, resolve_weights

from msmem_core.map.belief import EvidentialMap
from msmem_core.run.metrics import class_iou_counts, miou_from_counts, top_view_classes


def rollout(step, after, seq, grid, c):  # type: ignore[no-untyped-def]
    b = EvidentialMap.empty(grid, c)
    for t in range(len(seq)):
        if t in seq.manipulations:
            b = after(b, seq.manipulations[t])
        b = step(b, seq.free[t], seq.occ[t], seq.seen[t])
    return b


def score(b: EvidentialMap, seq, opened, cols):  # type: ignore[no-untyped-def]
    p = b.expected_occupancy()
    occ = (p > 0.5) & seq.valid
    cls = np.where(occ, np.argmax(b.class_probs()[1:], 0) + 1, 0)
    top, gtop = top_view_classes(cls), top_view_classes(np.where(seq.gt_occ & seq.valid, seq.gt_cls, 0))
    si, su = class_iou_counts(top, gtop, b.num_classes, seq.valid.any(2))
    return {"p_opened": float(p[opened].mean()), "occupied_opened": float(occ[opened].mean()),
            "top_right_cols": float((top[cols] == gtop[cols]).mean()), "sem_2d": miou_from_counts(si, su)}


def main(data: str, *weights: str) -> None:
    torch.set_num_threads(1)
    effects = Effects()
    analytic = AnalyticObservationModel()
    rows: dict[str, list[dict[str, float]]] = {}
    for path in list_shards(data, "observe"):
        shard = load_shard(path)
        info = shard.info.get("manipulation", {})
        if not info.get("success"):
            continue
        seq = sequence(shard)
        k = info["sample"]
        opened = shard.gt_occ[k - 1] & ~shard.gt_occ[k] & seq.valid
        cols = opened.any(2)
        grid, c = shard.grid, seq.seen.shape[1]
        valid_t = torch.from_numpy(seq.valid)
        ws = seq.workspace
        models = {"analytic-observation": (analytic.apply_masks, lambda b, a, ws=ws: effects.apply(b, a, ws))}
        for w in weights:
            net, _ = load_map_net(resolve_weights(w))

            def step(b, f, o, s, net=net, valid_t=valid_t):  # type: ignore[no-untyped-def]
                t = torch.from_numpy
                with torch.no_grad():
                    a, bb, e = net.step(t(b.alpha)[None], t(b.beta)[None], t(b.eta)[None], t(f)[None], t(o)[None],
                                        t(s)[None], valid_t)
                return EvidentialMap(b.grid, a[0].numpy(), bb[0].numpy(), e[0].numpy())

            def after(b, action, net=net, ws=ws):  # type: ignore[no-untyped-def]
                a, bb, e = (torch.from_numpy(x.copy())[None] for x in (b.alpha, b.beta, b.eta))
                manipulate(net, a, bb, e, 0, action, ws, effects)
                return EvidentialMap(b.grid, a[0].numpy(), bb[0].numpy(), e[0].numpy())

            models[w] = (step, after)
        for name, (step, after) in models.items():
            r = score(rollout(step, after, seq, grid, c), seq, opened, cols)
            rows.setdefault(name, []).append(r)
            print(shard.seed, name, {k2: round(v, 3) for k2, v in r.items()}, flush=True)
    print("mean over", len(next(iter(rows.values()))), "scenes whose grasp held:")
    for name, rs in rows.items():
        print(f"  {name}: " + ", ".join(f"{k2} {np.mean([r[k2] for r in rs]):.3f}" for k2 in rs[0]))


if __name__ == "__main__":
    main(sys.argv[1], *sys.argv[2:])

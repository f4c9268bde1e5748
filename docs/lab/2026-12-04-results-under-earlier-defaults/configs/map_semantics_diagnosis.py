"""Where a cnabu-map network loses 2-D semantic mIoU against the analytic update, on held-out rollouts.

    L=docs/lab/2026-12-04-results-under-earlier-defaults/configs   # from the repository root
    .venv/bin/python $L/map_semantics_diagnosis.py --data data/map_heldout --scenes 10 \
        [--weights plugins/msmem_cnabu/weights/cnabu_map.pt]

Each scene's start view and recorded views are integrated from the empty map by the network (on its
own output) and by the analytic update. The suite-cumulative 2-D semantic mIoU (``run.metrics``) of
the final beliefs is printed for hard maps that mix the two: the network's or the analytic occupancy
(or the truth), with the network's classes, the analytic classes where a ray saw the voxel
("observed"), or the class of the nearest observed voxel. Also: how often the class of truly
occupied but never-observed voxels is right. This separates occupancy errors (which columns have a
top and where) from class errors (which class the top gets).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from msmem_cnabu.learn.datagen import list_shards, load_shard
from msmem_cnabu.learn.maptrain import empty_evidence
from msmem_cnabu.learn.rollouts import sequence
from msmem_cnabu.mapmodel import SHIPPED
from msmem_cnabu.mapnet import analytic_update, bounded_evidence
from msmem_cnabu.weights import load_map_net
from scipy import ndimage

from msmem_core.run.metrics import class_iou_counts, miou_from_counts, top_view_classes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--weights", default=str(SHIPPED))
    ap.add_argument("--scenes", type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, _ = load_map_net(args.weights)
    cfg = net.config
    counts: dict[str, list] = {}
    unobs_right: dict[str, list[int]] = {}
    for path in list_shards(args.data, "observe")[: args.scenes]:
        s = sequence(load_shard(path))
        valid = torch.from_numpy(s.valid)
        c = s.seen.shape[1]
        a, b, e = empty_evidence(1, s.gt_occ.shape, c)
        aa, bb, ee = (x.clone() for x in (a, b, e))
        with torch.no_grad():
            for t in range(len(s)):
                f, o, se = (torch.from_numpy(x[t])[None] for x in (s.free, s.occ, s.seen))
                a, b, e, p, q = bounded_evidence(*net(a, b, e, f, o, se, valid), cfg.s_max, cfg.t_max)
                aa, bb, ee = analytic_update(aa, bb, ee, f, o, se, cfg.w_obs)
        p, q = p[0].numpy(), q[0].numpy()
        pa, ea = (aa / (aa + bb))[0].numpy(), ee[0].numpy()
        observed = (ea[1:] - 1).sum(0) > 0  # some class evidence: a ray ended in the voxel
        net_cls, ana_cls = np.argmax(q[1:], 0) + 1, np.argmax(ea[1:], 0) + 1
        _, idx = ndimage.distance_transform_edt(~observed, return_indices=True)
        nearest = ana_cls[tuple(idx)]
        classes = {"network": net_cls, "analytic where observed, else network": np.where(observed, ana_cls, net_cls),
                   "analytic where observed, else nearest observed": np.where(observed, ana_cls, nearest)}
        occupancies = {"network": p > 0.5, "truth": s.gt_occ}
        keep = s.valid.any(2)
        truth = top_view_classes(np.where(s.valid, s.gt_cls, 0))[keep]
        variants = {("analytic", "analytic"): (pa > 0.5, ana_cls)}
        variants |= {(on, cn): (occ, cls) for on, occ in occupancies.items() for cn, cls in classes.items()}
        for key, (occ, cls) in variants.items():
            top = top_view_classes(np.where(occ & s.valid, cls, 0))[keep]
            i, u = class_iou_counts(top, truth, c)
            old = counts.get(key, [0, 0])
            counts[key] = [old[0] + i, old[1] + u]
        hidden = s.gt_occ & s.valid & ~observed
        for name, cls in (("network", net_cls), ("nearest observed", nearest)):
            r = unobs_right.setdefault(name, [0, 0])
            r[0] += int((cls == s.gt_cls)[hidden].sum())
            r[1] += int(hidden.sum())
    print(f"2-D semantic mIoU (paper), suite-cumulative over {args.scenes} scenes:")
    for (occ, cls), (i, u) in counts.items():
        print(f"  occupancy {occ:9s} classes {cls:48s} {miou_from_counts(i, u):.3f}")
    for name, (ok, n) in unobs_right.items():
        print(f"class of truly occupied, never-observed voxels right ({name}): {ok / max(n, 1):.3f} of {n}")


if __name__ == "__main__":
    main()

"""Where cnabu-map's top view goes wrong: the analytic update's 40 views replayed through both models.

    L=docs/lab/2026-12-04-results-under-earlier-defaults/configs   # from the repository root
    .venv/bin/python $L/map_topview_errors.py --scenes 0,1 [--weights W] [--suite tune10]
    .venv/bin/python $L/map_topview_errors.py --suite mesh25 --scenes 0-4 \
        --config $L/scenes/mesh25-cnabu-map-mesh.yaml      # cnabu-map's params from a run config

For each scene, a view-only episode with the analytic update chooses 40 views; they are replayed
open loop through the analytic update and cnabu-map. Printed per model, over the shelf interior's
columns of the paper's top-view class map: columns with the right object class, a wrong object
class, an object where the truth is free, free where the truth holds an object, and the classes
predicted that are not in the scene (each is a class with IoU 0 in the mean) with their columns; for
cnabu-map also how many of its wrong-class columns the analytic update names right, and how many of
its object-on-free columns the analytic update leaves free.
Last, the 2-D semantic mIoU over the classes in the scene only (background included): the same
mean without the absent classes' zeros. Then two changes to cnabu-map's final hard classes, tried
on the same belief (offline checks, not models): ``smooth3``, each voxel's object-class
distribution averaged with its 3x3x3 neighbours' (weighted by believed occupancy); ``raysD``, a
class kept only within D voxels of one the analytic update has object-class evidence for
(background elsewhere); ``confT``, background where the object-class distribution's top probability
is at most T; ``seen``, only object classes the analytic update has class evidence for anywhere
(``seen+confT``: both); ``colsD``, whole columns abstain (background) unless within D columns of one
in which the analytic update has object-class evidence. The last line sums intersections and unions
over the scenes (suite-cumulative).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from msmem_core.config import load_config
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import parse_range, suite_scenes
from msmem_core.run.metrics import class_iou_counts, miou_from_counts, prediction_from_belief, top_view_classes
from msmem_core.run.runner import MetricTracker, build_episode, run_episode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default="tune10")
    ap.add_argument("--scenes", default="0")
    ap.add_argument("--weights", default=None, help="cnabu-map weights (default: the shipped ones)")
    ap.add_argument("--config", default=None, help="a run config whose observation_model.params (weights, "
                    "class_map) cnabu-map takes, and whose effect_models both episodes use")
    args = ap.parse_args()
    pm = get_plugin_manager()
    scenes = suite_scenes(args.suite)
    totals: dict[str, list[object]] = {}
    # the network's own output, as these offline checks were measured (unlabelled_objects: keep; the default is unknown)
    params: dict[str, object] = {"unlabelled_objects": "keep", **({"weights": args.weights} if args.weights else {})}
    extra: dict[str, object] = {}
    if args.config:
        from msmem_core.config import read_config_file

        given = read_config_file(args.config)
        params = {**given.get("observation_model", {}).get("params", {}), **params}
        extra = {k: v for k, v in given.items() if k == "effect_models"}
    net_cfg = {"observation_model": {"name": "cnabu-map", "params": params}, **extra}
    for i in parse_range(args.scenes, len(scenes)):
        ana_cfg = {"observation_model": {"name": "analytic-observation"}, **extra, "steps": 40, "threads": 1}
        ana = build_episode(load_config("view-only", None, ana_cfg), pm, scene=scenes[i])
        net = build_episode(load_config("view-only", None, {**net_cfg, "steps": 40, "threads": 1}), pm, scene=scenes[i])
        run_episode(ana)
        views = [ana.start_view] + [r["action"]["view"] for r in ana.records]
        net.sim.reset(net.scene)
        truth = MetricTracker(net)
        k = net.scene.num_classes
        bn, ba = EvidentialMap.empty(net.ig.grid, k), EvidentialMap.empty(net.ig.grid, k)
        for v in views:
            obs = net.sim.observe(net.viewpoints[v])
            bn, ba = net.observe_model.update(bn, obs), ana.observe_model.update(ba, obs)
        inside, keep = truth.interior, truth.interior.any(axis=2)
        gt = top_view_classes(np.where(inside, truth.gt_cls, 0))[keep]
        top_a = None
        for name, b in (("analytic", ba), ("cnabu-map", bn)):
            m = truth(b)
            _, cls = prediction_from_belief(b.expected_occupancy(), b.class_probs())
            cls[truth.walls] = 0
            top = top_view_classes(np.where(inside, cls, 0))[keep]
            obj, truth_obj = top > 0, gt > 0
            counts = {"right class": (top == gt) & truth_obj, "wrong class": (top != gt) & truth_obj & obj,
                      "object on free": ~truth_obj & obj, "free on object": truth_obj & ~obj}
            if top_a is None:
                top_a = top
            else:  # where the analytic update (what the rays say) was right and the network is not
                counts["wrong class where analytic right"] = counts["wrong class"] & (top_a == gt)
                counts["object on free where analytic free"] = counts["object on free"] & (top_a == 0)
            inter, union = class_iou_counts(top, gt, b.num_classes)
            present = np.bincount(gt, minlength=b.num_classes) > 0
            absent = np.flatnonzero((union > 0) & ~present)
            print(f"scene {i} {name:10s} 2-D semantic mIoU {m['semantic_miou_2d']:.3f}: "
                  + ", ".join(f"{k} {int(v.sum())}" for k, v in counts.items())
                  + f", classes not in the scene {len(absent)} (columns: {union[absent].tolist()}), "
                  f"mIoU over the scene's classes {np.mean(inter[present] / union[present]):.3f}", flush=True)
            _add(totals, name, inter, union)
        variants = _variants(bn, ba, truth.walls)
        for name, cls in variants.items():
            inter, union = class_iou_counts(top_view_classes(np.where(inside, cls, 0))[keep], gt, bn.num_classes)
            _add(totals, name, inter, union)
        print(f"scene {i} cnabu-map variants: "
              + ", ".join(f"{k} {totals[k][-1]:.3f}" for k in variants), flush=True)
    print("mean over scenes / suite-cumulative: " + ", ".join(
        f"{k} {np.mean(v[2:]):.3f} / {miou_from_counts(v[0], v[1]):.3f}" for k, v in totals.items()))


def _add(totals: dict[str, list[object]], name: str, inter: np.ndarray, union: np.ndarray) -> None:
    """Per name: [summed intersections, summed unions, per-scene mIoU...]."""
    t = totals.setdefault(name, [np.zeros_like(inter), np.zeros_like(union)])
    t[0], t[1] = t[0] + inter, t[1] + union
    t.append(miou_from_counts(inter, union))


def _variants(bn: EvidentialMap, ba: EvidentialMap, walls: np.ndarray) -> dict[str, np.ndarray]:
    """cnabu-map's hard classes changed as the module docstring says."""
    p, q = bn.expected_occupancy(), bn.class_probs()
    out = {}
    weighted = (p * (p > 0.5))[None] * (q[1:] / q[1:].sum(0, keepdims=True))
    smooth = np.stack([ndimage.uniform_filter(w, size=3, mode="constant") for w in weighted])
    q2 = np.concatenate([q[:1], smooth + 1e-12])
    _, out["smooth3"] = prediction_from_belief(p, q2)
    _, cls = prediction_from_belief(p, q)
    known = (ba.eta[1:].sum(0) - ba.eta[1:].sum(0).min()) > 1e-3  # object-class evidence from rays
    dist = ndimage.distance_transform_edt(~known)
    for d in (0, 1, 4):
        out[f"rays{d}"] = np.where(dist > d, 0, cls)
    r = q[1:] / q[1:].sum(0, keepdims=True)  # object class given occupied
    for tau in (0.4, 0.6, 0.8):
        out[f"conf{tau}"] = np.where(r.max(0) > tau, cls, 0)
    seen = np.zeros(q.shape[0], dtype=bool)  # object classes the rays gave evidence for, anywhere
    seen[1:] = (ba.eta[1:] - ba.eta[1:].min()).reshape(q.shape[0] - 1, -1).max(1) > 1.0
    q3 = np.where(seen[:, None, None, None] | (np.arange(q.shape[0]) == 0)[:, None, None, None], q, 0.0)
    _, out["seen"] = prediction_from_belief(p, q3 + 1e-12)
    r3 = q3[1:] / (q3[1:].sum(0, keepdims=True) + 1e-12)
    for tau in (0.5, 0.7):
        out[f"seen+conf{tau}"] = np.where(r3.max(0) > tau, out["seen"], 0)
    # column-level abstention: keep the network's column only within D columns (xy) of one in which the
    # analytic update has object-class evidence, or where the column's top object-class probability > T
    col_known = known.any(axis=2)
    col_dist = ndimage.distance_transform_edt(~col_known)
    for d in (0, 1, 2):
        out[f"cols{d}"] = np.where((col_dist > d)[:, :, None], 0, cls)
    # object-level abstention: a connected object of the network's hard map (26-connected voxels of one
    # class) is kept only if the rays gave evidence of that class somewhere in it (``comp``) or of any
    # object class in it (``company``); ``seen+comp``: the same on the ``seen`` classes
    ray_cls = np.argmax(ba.eta[1:], axis=0) + 1
    for name, base in (("comp", cls), ("seen+comp", out["seen"])):
        for any_class in (False, True):
            kept = np.zeros_like(base)
            for c in np.unique(base[base > 0]):
                lab, _n = ndimage.label(base == c, structure=np.ones((3, 3, 3), dtype=bool))
                hits = known & (True if any_class else ray_cls == c)
                good = np.unique(lab[hits & (lab > 0)])
                kept[np.isin(lab, good[good > 0])] = c
            out[name + ("any" if any_class else "")] = kept
    for c in out.values():
        c[walls] = 0
    return out


if __name__ == "__main__":
    main()

"""What each candidate action at one decision really gains by the end of the episode, against what the
objective predicts.

    L=docs/lab/2026-12-05-decision-oracle      # from the repository root
    .venv/bin/python $L/decision_oracle.py tune10 0,2,4,6,8 10 4 40 > $L/runs/decision-tune10-a.jsonl

Arguments: suite, scenes, K, M, H[, config file over the ``ours`` preset]. Per scene, the ``ours``
preset's skills (library defaults) take K views as MSAS would with manipulation not allowed (the grasp
skill tracks its FE-UMGF buffer every step, as in an episode). At step K manipulation is allowed:
every skill proposes and the objective scores every candidate; the M best of each skill are scored
exactly (``Term.refine``). Each of them is then executed from the same physical state
(``Simulator.snapshot``/``restore``) and followed, as in MSAS, by views only: the belief after a
manipulation is the effect model's prediction (capped as MSAS caps it), then the next-best view,
then the next-best views up to H steps in all. One JSON line per scene: the map at step K
(``base``) and per candidate its skill, objective rank, value and terms, outcome, and the change of
both paper metrics after the candidate and one view (``d2_``) and at step H (``d_``), with the final
2-D semantic counts per class. Ground truth only scores.

The observation model keeps state between updates (``cnabu-map``: the episode's ray record and the
network's own map). It is saved at step K and put back before each candidate, as the simulator's
state is; without that, every candidate after the first inherited the ray record of the previous
candidate's rollout (the runs made before this was fixed are ``runs/*-inherited-record.jsonl``).

``--skills view,push`` limits the candidates to those skills; ``--record MODE`` says what happens to
the model's ray record after a manipulation (the belief is always the effect model's prediction,
capped as MSAS caps it):

- ``as-is`` (MSAS today): the record is cleared only where the prediction rewrote the belief;
- ``cap``: the record's evidence is capped like the belief's (the predicted change, dilated);
- ``cap-all``: the record's evidence is capped everywhere (every ray before the manipulation counts as
  at most ``disturbed_evidence_cap`` in all);
- ``truth``: an oracle, the record is cleared wherever the ground-truth occupancy changed (dilated by
  ``disturbed_margin_voxels``).
"""
from __future__ import annotations

import copy
import json
import sys

import numpy as np

from msmem_core.config import load_config, read_config_file
from msmem_core.interfaces import DecisionContext
from msmem_core.map.belief import EvidentialMap
from msmem_core.msas import cap_evidence, decide, execute_measured
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.runner import MetricTracker, build_episode

KEYS = ("occupancy_miou", "semantic_miou_2d")
RECORD_MODES = ("as-is", "cap", "cap-all", "truth")


def model_state(model: object) -> dict:
    """A deep copy of an observation model's private state (its ray record, its own map, ...)."""
    return copy.deepcopy({k: v for k, v in vars(model).items() if k.startswith("_")})


def treat_record(model: object, mode: str, changed: np.ndarray, cap: float, margin: int,
                 truth_changed: np.ndarray | None) -> None:
    """After a manipulation: what ``mode`` does to ``cnabu-map``'s ray record (module docstring)."""
    from scipy import ndimage

    rays = getattr(model, "_rays", None)
    if rays is None or mode == "as-is":
        return
    if mode == "cap":
        model._rays = cap_evidence(rays, changed, cap, margin)
    elif mode == "cap-all":
        model._rays = cap_evidence(rays, np.ones_like(changed), cap, 0)
    elif mode == "truth":
        region = ndimage.binary_dilation(truth_changed, np.ones((3, 3, 3), bool), iterations=margin)
        r = rays.copy()
        r.alpha[region] = r.beta[region] = 1.0
        r.eta[:, region] = 1.0
        model._rays = r


def option(args: list[str], name: str, default: str) -> str:
    if name in args:
        i = args.index(name)
        value = args[i + 1]
        del args[i:i + 2]
        return value
    return default


def main() -> None:
    args = sys.argv[1:]
    record = option(args, "--record", "as-is")
    only = option(args, "--skills", "")
    assert record in RECORD_MODES, record
    suite, scenes, K, M = args[0], [int(s) for s in args[1].split(",")], int(args[2]), int(args[3])
    H = int(args[4])  # steps in all: views only after the candidate's associated view
    over = read_config_file(args[5]) if len(args) > 5 else {}
    pm = get_plugin_manager()
    for si in scenes:
        ep = build_episode(load_config("ours", None, {**over, "steps": 40, "threads": 1}), pm,
                           scene=suite_scenes(suite)[si])
        cfg = ep.cfg.msas
        ep.sim.reset(ep.scene)
        truth = MetricTracker(ep)
        ws = ep.workspace
        rng = np.random.default_rng(0)
        start = ep.start_view
        belief = ep.observe_model.update(EvidentialMap.empty(ws.grid, ws.num_classes),
                                         ep.sim.observe(ep.viewpoints[start]))
        visited: set[int] = set()
        for step in range(K):
            seen = visited | {start} if step == 0 else set(visited)
            ctx = DecisionContext(step, belief, ep.ig, ep.viewpoints, seen, ws, rng, False, cfg.tau_chi, -1)
            d = decide(ctx, ep.skills, ep.objective)
            out = execute_measured(d.skill.skill, ep.sim, d.action, ctx)
            belief = ep.observe_model.update(belief, out.observation)
            visited.add(d.action.view)
        base = truth(belief)
        gt_before = truth.gt_occ.copy()
        token = ep.sim.snapshot()
        state = model_state(ep.observe_model)
        ctx = DecisionContext(K, belief, ep.ig, ep.viewpoints, set(visited), ws, rng, True, cfg.tau_chi, -1)
        views_only = [b for b in ep.skills if b.skill.category == "perception"]
        rows = []
        for bound in ep.skills:
            if only and bound.name not in only.split(","):
                continue
            bound.skill.track(ctx)
            ctx.funnel.skill = bound.name
            acts = bound.skill.propose(ctx)
            if not acts:
                continue
            batch = bound.batch(ctx, acts)
            total, parts = ep.objective.score(ctx, batch)
            order = np.argsort(-total)[:M]
            for i in order:  # exact values
                for name, w, term in ep.objective.terms:
                    if name in parts:
                        ex = term.refine(ctx, batch, np.array([i]))
                        if ex is not None:
                            total[i] += w * (float(ex[0]) - parts[name][i])
                            parts[name][i] = float(ex[0])
            for i in order:
                ep.sim.restore(token)
                vars(ep.observe_model).update(copy.deepcopy(state))
                a = acts[i]
                out = execute_measured(bound.skill, ep.sim, a, ctx)
                b, vis, last = belief, set(visited), -1
                if out.observation is not None:
                    b = ep.observe_model.update(belief, out.observation)
                    vis.add(a.view)
                else:
                    pred = batch.prediction
                    if out.success:
                        b, cap = pred.belief(int(i)), cfg.disturbed_evidence_cap
                    else:
                        b, cap = belief, cfg.failed_manipulation_cap
                    ch = np.zeros(ws.grid.size, bool)
                    ch[pred.changes[int(i)].idx] = True
                    ch = ch.reshape(ws.grid.shape)
                    if cap is not None:
                        b = cap_evidence(b, ch, cap, cfg.disturbed_margin_voxels)
                    truth(b)  # the ground truth after the manipulation
                    treat_record(ep.observe_model, record, ch, cfg.disturbed_evidence_cap or 4.0,
                                 cfg.disturbed_margin_voxels, truth.gt_occ != gt_before)
                    vis, last = set(), K
                c2 = DecisionContext(K + 1, b, ep.ig, ep.viewpoints, vis, ws, rng, False, cfg.tau_chi, last)
                d2 = decide(c2, views_only, ep.objective)
                o2 = ep.sim.observe(ep.viewpoints[d2.action.view])
                b2 = ep.observe_model.update(b, o2)
                vis.add(d2.action.view)
                m2 = truth(b2)
                for step in range(K + 2, H):
                    c3 = DecisionContext(step, b2, ep.ig, ep.viewpoints, vis, ws, rng, False, cfg.tau_chi, last)
                    d3 = decide(c3, views_only, ep.objective)
                    b2 = ep.observe_model.update(b2, ep.sim.observe(ep.viewpoints[d3.action.view]))
                    vis.add(d3.action.view)
                m = truth(b2)
                pc = truth.paper_counts
                rows.append({"skill": bound.name, "rank": int(np.where(order == i)[0][0]), "value": float(total[i]),
                             **{f"t_{k}": float(v[i]) for k, v in parts.items()},
                             "success": bool(out.success), "removed": list(out.removed),
                             "moved": out.info.get("moved") if out.info else None,
                             "fell": list(out.fell_or_left or []),
                             **{f"d2_{k}": m2[k] - base[k] for k in KEYS},
                             "removed_classes": [truth.objects[o].class_id for o in out.removed],
                             "sem_inter": pc["semantic_2d_intersection"], "sem_union": pc["semantic_2d_union"],
                             **{f"d_{k}": m[k] - base[k] for k in KEYS}})
        ep.sim.restore(token)
        ep.sim.close()
        print(json.dumps({"scene": si, "record": record, "base": {k: base[k] for k in KEYS}, "rows": rows}),
              flush=True)


main()

"""``msmem perf step``: time one full MSAS decision of an episode, stage by stage.

The decision is built exactly as ``msmem run`` builds it (``runner.build_episode`` with the method
preset, ``ours`` by default: the real skills, effect models, objective terms and simulator), on a
mid-episode belief: the episode's start view and ``views - 1`` seeded random candidate views
rendered by the simulator and integrated with the episode's observation model, every skill's
``track`` run after each (the grasp skill's FE-UMGF buffer grows as in an episode). The decision
is the one at the next step, with manipulation allowed.

Each repeat runs ``msas.decide`` on a fresh copy of the skills as they were after the prefix (so
the grasp skill's tracking runs every time, as once per episode step) and a fresh context; thin
wrappers installed for the duration time every stage where ``decide`` calls it: per skill
``track``, ``propose``, the effect model's ``predict`` and ``Objective.best`` (the scoring path of
MSAS, refinement included), and inside them the objective terms, the IG kernels and the grasp
skill's FPP / FE-vMF / FE-UMGF steps (found by name where the plugins define them). Medians over
the repeats are reported.

References (``reference=True``): the brute-force float64 IG of ``msmem_core.map.ig_reference``
(extrapolated from a few views) for an IG sweep; a full, non-incremental re-score of every
predicted belief for the manipulation skills' ``ig`` term; and the whole decision with that
reference ``ig`` term. Approximations: the ``ig`` term screens candidates at every 2nd ray and
the IG kernels stop a ray at transmission 1e-3; over ``beliefs`` beliefs (other seeded view sets)
the chosen action is compared with exact scoring (no screening) and with fully exact scoring (no
screening, no early exit).
"""

from __future__ import annotations

import copy
import os
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from msmem_core.config import RunConfig, load_config
from msmem_core.interfaces import Action, CandidateBatch
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGService
from msmem_core.map.ig_reference import ig_views_reference
from msmem_core.msas import BoundSkill, Decision, DecisionContext, Objective, decide
from msmem_core.plugins.manager import ComponentRef, get_plugin_manager
from msmem_core.run.runner import Episode, build_episode, set_threads
from msmem_core.world.viewpoints import default_start_view

Path_ = tuple[str, ...]
# Plugin functions timed where they are looked up at call time (module globals); skipped when the
# module is not loaded. Core code never imports plugin packages: they are found in sys.modules.
PLUGIN_PROBES = (
    ("msmem_grasp.skill", "frontier_points", "FPP (frontier points)"),
    ("msmem_grasp.weights", "predict_cloud", "FE-vMF inference"),
    ("msmem_grasp.skill", "predict_geometric", "geometric grasp predictor"),
)


@dataclass
class Probe:
    """Inclusive wall-clock and CPU seconds (the process's, all threads) and call counts per call path
    while its wrappers are installed."""

    seconds: dict[Path_, float] = field(default_factory=lambda: defaultdict(float))
    cpu: dict[Path_, float] = field(default_factory=lambda: defaultdict(float))
    calls: dict[Path_, int] = field(default_factory=lambda: defaultdict(int))
    batches: dict[str, tuple[DecisionContext, CandidateBatch]] = field(default_factory=dict)
    """The last batch each skill scored (with its context), for the references."""
    stack: list[str] = field(default_factory=list)
    _undo: list[tuple[Any, str, Any, bool]] = field(default_factory=list)

    def wrap(self, owner: Any, attr: str, label: str | Callable[..., str]) -> None:
        """Time ``owner.attr`` (a method of an instance, or a module function) under ``label``."""
        fn = getattr(owner, attr)
        own = attr in vars(owner)

        def timed(*args: Any, **kwargs: Any) -> Any:
            self.stack.append(label(*args, **kwargs) if callable(label) else label)
            key = tuple(self.stack)
            self.seconds.setdefault(key, 0.0)  # rows in call order, parents before children
            t, c = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[key] += time.perf_counter() - t
                self.cpu[key] += time.process_time() - c
                self.calls[key] += 1
                self.stack.pop()

        setattr(owner, attr, timed)
        self._undo.append((owner, attr, fn, own))

    def restore(self) -> None:
        for owner, attr, fn, own in reversed(self._undo):
            if own:
                setattr(owner, attr, fn)
            else:
                delattr(owner, attr)
        self._undo.clear()


def clone_skills(skills: list[BoundSkill]) -> list[BoundSkill]:
    """Deep copies of the skills (their state, e.g. a grasp buffer) sharing effect models and any
    torch module (weights are read-only)."""
    out = []
    for b in skills:
        memo = {id(v): v for v in vars(b.skill).values() if hasattr(v, "state_dict")}
        out.append(BoundSkill(b.name, copy.deepcopy(b.skill, memo), b.effect_model))
    return out


@contextmanager
def probed(probe: Probe, skills: list[BoundSkill], objective: Objective, ig: IGService) -> Iterator[Probe]:
    """Install the stage wrappers of one decision (removed on exit)."""
    try:
        for b in skills:
            probe.wrap(b.skill, "track", f"{b.name}: track")
            probe.wrap(b.skill, "propose", f"{b.name}: propose")
            if b.effect_model is not None:
                probe.wrap(b.effect_model, "predict", f"{b.name}: effect prediction")
            buffer = getattr(b.skill, "buffer", None)
            if buffer is not None and hasattr(buffer, "update"):
                probe.wrap(buffer, "update", "FE-UMGF fusion")
        for module, name, label in PLUGIN_PROBES:
            mod = sys.modules.get(module)
            if mod is not None and callable(getattr(mod, name, None)):
                probe.wrap(mod, name, label)

        def best_label(ctx: DecisionContext, batch: CandidateBatch) -> str:
            probe.batches[batch.skill] = (ctx, batch)
            return f"{batch.skill}: score"

        probe.wrap(objective, "best", best_label)
        for name, _w, term in objective.terms:
            probe.wrap(term, "score", f"term {name}")
            probe.wrap(term, "refine", f"refine {name}")
        probe.wrap(ig, "prepare", "ig.prepare (belief -> IG field)")
        probe.wrap(ig, "view_ig", "IG sweep (all views)")
        if hasattr(ig, "sweep"):  # the base sweep shared by the view branch and the incremental IG
            probe.wrap(ig, "sweep", "IG sweep (all views)")
        probe.wrap(ig, "after_view", "two-step: after_view")
        probe.wrap(ig, "view_ig_delta", lambda base, deltas, exact=False, ray_step=1: (
            f"IG incremental, screening (1 ray in {ray_step}x{ray_step})" if ray_step > 1
            else "IG incremental, full density"))
        yield probe
    finally:
        probe.restore()


# ----------------------------------------------------------------------------------------- set-up
@dataclass
class StepState:
    """A mid-episode state: the belief, the skills after tracking every earlier step, visited views."""

    belief: EvidentialMap
    skills: list[BoundSkill]
    visited: set[int]
    step: int
    views: list[int]


def mid_episode_state(ep: Episode, views: int, seed: int) -> StepState:
    """The start view and ``views - 1`` seeded random views, observed in the episode's simulator and
    integrated by its observation model; every skill tracks every step as in ``run_msas``. The
    returned state is that of step ``views - 1`` (the belief holds ``views`` views)."""
    if views < 1:
        raise ValueError("views must be >= 1")
    cfg = ep.cfg
    rng = np.random.default_rng(seed)
    start = cfg.msas.start_view if cfg.msas.start_view is not None else default_start_view(cfg.viewpoints)
    others = np.setdiff1d(np.arange(len(ep.viewpoints)), [start])
    order = [start, *(int(v) for v in rng.choice(others, size=views - 1, replace=False))]
    skills = clone_skills(ep.skills)
    belief = ep.observe_model.update(EvidentialMap.empty(ep.ig.grid), ep.sim.observe(ep.viewpoints[start]))
    for step in range(views - 1):
        ctx = _context(ep, belief, _visited(order, step, start), step, False, 0)
        for b in skills:
            b.skill.track(ctx)
        nxt = order[step + 1]
        belief = ep.observe_model.update(belief, ep.sim.observe(ep.viewpoints[nxt]))
    step = views - 1
    return StepState(belief, skills, _visited(order, step, start), step, order)


def _visited(order: list[int], step: int, start: int) -> set[int]:
    """What ``run_episode`` passes at ``step``: the views taken so far (the start view at step 0 only)."""
    return set(order[1 : step + 1]) | ({start} if step == 0 else set())


def _context(ep: Episode, belief: EvidentialMap, visited: set[int], step: int, allowed: bool, seed: int,
             ig: IGService | None = None) -> DecisionContext:
    cfg = ep.cfg
    return DecisionContext(step, belief, ig or ep.ig, ep.viewpoints, set(visited), ep.ig.grid, ep.scene.shelf,
                           cfg.gripper, np.random.default_rng([cfg.seed, seed, step]), allowed, cfg.msas.tau_chi)


def _decide(ep: Episode, state: StepState, objective: Objective | None = None, ig: IGService | None = None,
            seed: int = 0) -> Decision:
    """One decision at the state's step (manipulation allowed) on fresh copies of the skills."""
    ctx = _context(ep, state.belief, state.visited, state.step, True, seed, ig)
    return decide(ctx, clone_skills(state.skills), objective or ep.objective)


def objective_with(ep: Episode, **ig_params: Any) -> Objective:
    """The episode's objective with the ``ig`` term rebuilt with these parameters."""
    pm = get_plugin_manager()
    terms = []
    for (name, weight, term), ref in zip(ep.objective.terms, ep.cfg.objective, strict=True):
        if ref.name == "ig":
            term = pm.build("objective-term", ComponentRef(name="ig", params={**ref.params, **ig_params}))
        terms.append((name, weight, term))
    return Objective(terms)


def _same(a: Decision, b: Decision) -> bool:
    return a.skill == b.skill and a.action == b.action


def _describe(d: Decision) -> str:
    best = ", ".join(f"{k} {v:.1f}" for k, v in d.best.items())
    return f"{d.skill} #{d.index} (objective {d.value:.1f}; best per skill: {best})"


# -------------------------------------------------------------------------------------------- run
def perf_step(
    repeats: int = 5,
    scene_seed: int = 1,
    views: int = 10,
    view_seed: int = 0,
    reference: bool = True,
    beliefs: int = 3,
    method: str = "ours",
    config: str | Path | None = None,
    scene: str | Path | None = None,
    reference_views: int = 2,
    report: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Time one MSAS decision of ``method`` on a mid-episode belief (see the module docstring).

    The scene is generated from ``scene_seed`` unless ``scene`` names a SceneSpec JSON file;
    ``config`` (a YAML/JSON file) overrides the method preset as in ``msmem run``.

    Reference figures are CPU seconds (the wall clock of a one-off run is too noisy on a shared
    machine). Returns ``decide_s`` (median wall-clock seconds of the whole ``decide`` call; ``decide_cpu_s``:
    CPU seconds of the process, all threads), ``stages`` (call path ``"a / b / c"`` -> median
    seconds; ``stages_cpu``: CPU seconds), ``calls`` (path -> calls per decision), ``decision`` (the
    last timed :class:`Decision`), ``candidates`` (per skill), the reference figures under
    ``reference/...`` and, with ``beliefs > 0``, ``agreement`` counts of equal decisions.
    """
    load_start = os.getloadavg()
    t_setup = time.perf_counter()
    over: dict[str, Any] = {"scene": {"seed": scene_seed, "file": None if scene is None else str(scene)}}
    cfg: RunConfig = load_config(method, config, over)
    set_threads(cfg.threads)
    ep = build_episode(cfg, get_plugin_manager())
    ep.sim.reset(ep.scene)
    state = mid_episode_state(ep, views, view_seed)
    setup_s = time.perf_counter() - t_setup

    per_repeat: list[Probe] = []
    totals: list[float] = []
    cpu_totals: list[float] = []
    decision: Decision | None = None
    for r in range(max(1, repeats) + 1):  # the first run warms up (numba loads its cached kernels)
        ctx = _context(ep, state.belief, state.visited, state.step, True, 0)
        skills = clone_skills(state.skills)
        probe = Probe()
        with probed(probe, skills, ep.objective, ep.ig):
            t, c = time.perf_counter(), time.process_time()
            decision = decide(ctx, skills, ep.objective)
            total, cpu_total = time.perf_counter() - t, time.process_time() - c
        if r > 0:
            per_repeat.append(probe)
            totals.append(total)
            cpu_totals.append(cpu_total)
    assert decision is not None
    paths: list[Path_] = []
    for p in per_repeat:
        paths += [k for k in p.seconds if k not in paths]
    stages = {" / ".join(k): statistics.median(p.seconds.get(k, 0.0) for p in per_repeat) for k in paths}
    cpu = {" / ".join(k): statistics.median(p.cpu.get(k, 0.0) for p in per_repeat) for k in paths}
    calls = {" / ".join(k): max(p.calls.get(k, 0) for p in per_repeat) for k in paths}
    res: dict[str, Any] = {
        "decide_s": statistics.median(totals), "decide_min_s": min(totals),
        "decide_cpu_s": statistics.median(cpu_totals), "stages": stages, "stages_cpu": cpu, "calls": calls,
        "decision": decision, "candidates": dict(decision.candidates), "setup_s": setup_s,
    }
    last = per_repeat[-1]

    refs: dict[str, tuple[float, str]] = {}  # stage path -> (reference seconds, what it is)
    if reference:
        res |= _references(ep, state, decision, last, stages, calls, refs, reference_views)
    if beliefs > 0:
        res["agreement"] = _agreement(ep, state, beliefs, views, view_seed, (decision, last))

    load_end = os.getloadavg()
    ig = ep.ig
    try:
        import torch

        torch_threads = torch.get_num_threads()
    except ImportError:  # pragma: no cover - torch is a dependency
        torch_threads = 0
    report(
        f"msmem perf step: method {cfg.method}, scene {ep.scene.name} ({len(ep.scene.objects)} objects), simulator "
        f"{cfg.simulator.name}; belief from {views} views (start + {views - 1} random, seed {view_seed}), decision at "
        f"step {state.step}; grid {ig.grid.voxel_m * 100:g} cm {tuple(ig.grid.shape)}, {ig.num_views} views x "
        f"{ig.rays_per_view} rays"
    )
    report(
        f"median of {len(totals)} decisions (+1 warm-up); {numba.get_num_threads()} numba / {torch_threads} torch "
        f"threads, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '-')}; load average "
        f"{' '.join(f'{x:.1f}' for x in load_start)} at start, {' '.join(f'{x:.1f}' for x in load_end)} at end; "
        f"set-up {setup_s:.1f} s"
    )
    report(f"candidates: {', '.join(f'{k} {v}' for k, v in decision.candidates.items())}; "
           f"chosen: {_describe(decision)}")
    width = max(44, *(2 * len(k) + len(k[-1]) for k in paths)) if paths else 44
    report(f"  {'stage':{width}} {'calls':>5} {'wall s':>7} {'cpu s':>7} {'cpu %':>6} {'ref cpu s':>10} {'ref/cpu':>8}")
    total_cpu = max(res["decide_cpu_s"], 1e-12)
    report(f"  {'decide() total':{width}} {1:5d} {res['decide_s']:7.3f} {res['decide_cpu_s']:7.3f} {1.0:6.0%}")
    for k in paths:
        name = "  " * (len(k) - 1) + k[-1]
        key = " / ".join(k)
        line = f"  {name:{width}} {calls[key]:5d} {stages[key]:7.3f} {cpu[key]:7.3f} {cpu[key] / total_cpu:6.0%}"
        if key in refs:  # reference CPU seconds per call against this stage's CPU seconds per call
            ref_s, _ = refs[key]
            line += f" {ref_s:10.2f} {ref_s / max(cpu[key] / max(calls[key], 1), 1e-12):7.0f}x"
        report(line)
    for key, (_, what) in refs.items():
        report(f"  reference for {key.split(' / ')[-1]!r} ({key.split(' / ')[0]}): {what}")
    if "reference/decide_s" in res:
        report(
            f"  decide() with the reference ig term (no screening, full re-score of every predicted belief): "
            f"{res['reference/decide_cpu_s']:.2f} s CPU = {res['reference/decide_cpu_s'] / total_cpu:.1f}x the median; "
            f"same decision: {res['reference/same_decision']}"
        )
    for skill in ("push", "grasp"):
        if f"reference/{skill}_ig_max_abs_diff" in res:
            diff, rel = res[f"reference/{skill}_ig_max_abs_diff"], res[f"reference/{skill}_ig_max_rel_diff"]
            report(f"  {skill}: incremental IG (full density) vs the full re-score: max abs diff {diff:.2e} "
                   f"(rel {rel:.1e})")
    if "agreement" in res:
        a = res["agreement"]
        n = a["beliefs"]
        report(
            f"  approximations, over {n} belief{'s' if n != 1 else ''} (view seeds {view_seed}..{view_seed + n - 1}): "
            f"the chosen action "
            f"differs from exact scoring (no screening) in {n - a['same_as_unscreened']}/{n}, from fully exact scoring "
            f"(no screening, no early exit) in {n - a['same_as_exact']}/{n}; within a skill, the screened best push "
            f"differs from the exact best push in {a['push_best_differs']}/{a['push_batches']}"
        )
    return res


def _references(ep: Episode, state: StepState, timed: Decision, probe: Probe, stages: dict[str, float],
                calls: dict[str, int], refs: dict[str, tuple[float, str]], reference_views: int) -> dict[str, Any]:
    """Time the brute-force references of the stages that have one (see the module docstring)."""
    out: dict[str, Any] = {}
    ig = ep.ig
    # one IG sweep: pure-Python float64 reference, extrapolated from a few views
    field_ = ig.prepare(state.belief)
    sel = np.linspace(0, ig.num_views - 1, max(1, reference_views)).astype(int)
    c = time.process_time()
    ig_views_reference(field_.p, field_.H, ig.origins[sel], ig.dirs[sel], ig.grid, ig.t_min, ig.t_max)
    sweep_ref = (time.process_time() - c) * ig.num_views / len(sel)
    out["reference/sweep_cpu_s"] = sweep_ref
    for key in stages:
        if key.endswith("IG sweep (all views)"):
            refs[key] = (sweep_ref, f"brute-force float64 IG sweep (ig_reference, per call), extrapolated from "
                                    f"{len(sel)} views")
    # manipulation IG: full (non-incremental) re-score of every predicted belief
    for skill, (ctx, batch) in probe.batches.items():
        if batch.prediction is None or not batch.actions:
            continue
        c = time.process_time()
        full = ig.view_ig([ig.prepare(b) for b in batch.prediction.beliefs]).max(axis=1)
        ref_s = time.process_time() - c
        exact = ig.view_ig_delta(ctx.field, _deltas(ctx, batch)).max(axis=1)
        diff = np.abs(full - exact)
        out[f"reference/{skill}_ig_cpu_s"] = ref_s
        out[f"reference/{skill}_ig_max_abs_diff"] = float(diff.max())
        out[f"reference/{skill}_ig_max_rel_diff"] = float((diff / np.maximum(np.abs(full), 1e-12)).max())
        key = f"{skill}: score / term ig"
        if key in stages:
            refs[key] = (ref_s, f"full re-score of all {len(batch.actions)} predicted beliefs "
                                             "(ig_views_batch, incremental: false)")
    # the whole decision with the reference ig term
    ref_obj = objective_with(ep, incremental=False, screen_ray_step=1)
    t, c = time.perf_counter(), time.process_time()
    d_ref = _decide(ep, state, ref_obj)
    out["reference/decide_s"], out["reference/decide_cpu_s"] = time.perf_counter() - t, time.process_time() - c
    out["reference/same_decision"] = _same(timed, d_ref)
    return out


def _deltas(ctx: DecisionContext, batch: CandidateBatch) -> list[Any]:
    """The IG deltas of a manipulation batch (as the ``ig`` term computes them)."""
    from msmem_core.map.belief import DeltaBeliefs

    assert batch.prediction is not None
    beliefs = batch.prediction.beliefs
    if isinstance(beliefs, DeltaBeliefs) and beliefs.base is ctx.belief:
        return [ctx.ig.belief_delta(ctx.field, d) for d in beliefs.deltas]
    return [ctx.ig.field_delta(ctx.field, ctx.ig.prepare(b)) for b in beliefs]


def _agreement(ep: Episode, state: StepState, beliefs: int, views: int, seed: int,
               first: tuple[Decision, Probe]) -> dict[str, int]:
    """How often the approximations change the chosen action (default vs unscreened vs fully exact)."""
    unscreened = objective_with(ep, screen_ray_step=1)
    exact_ig = IGService(ep.ig.grid, ep.cfg.camera, ep.viewpoints, ep.scene.shelf,
                         ep.cfg.ig.model_copy(update={"early_exit": 0.0}))
    counts = {"beliefs": 0, "same_as_unscreened": 0, "same_as_exact": 0, "push_batches": 0, "push_best_differs": 0}
    for b in range(beliefs):
        if b == 0:
            st, (d, probe) = state, first
        else:
            st, probe = mid_episode_state(ep, views, seed + b), Probe()
            ctx = _context(ep, st.belief, st.visited, st.step, True, 0)
            skills = clone_skills(st.skills)
            with probed(probe, skills, ep.objective, ep.ig):
                d = decide(ctx, skills, ep.objective)
        d_uns = _decide(ep, st, unscreened)
        d_exact = _decide(ep, st, unscreened, exact_ig)
        counts["beliefs"] += 1
        counts["same_as_unscreened"] += _same(d, d_uns)
        counts["same_as_exact"] += _same(d, d_exact)
        if "push" in probe.batches:
            _, batch = probe.batches["push"]
            i_exact = unscreened.best(_context(ep, st.belief, st.visited, st.step, True, 0), batch)[0]
            i_screened = ep.objective.best(_context(ep, st.belief, st.visited, st.step, True, 0), batch)[0]
            counts["push_batches"] += 1
            counts["push_best_differs"] += int(i_exact != i_screened)
    return counts


def is_valid_action(action: Action, num_views: int) -> bool:
    """A decision's action survives a JSON round trip through its own model and names a real view."""
    again = type(action).model_validate_json(action.model_dump_json())
    view = getattr(action, "view", None)
    return again == action and (view is None or 0 <= int(view) < num_views)

"""``msmem perf step``: time one full MSAS decision of an episode, stage by stage.

The decision is built exactly as ``msmem run`` builds it (``runner.build_episode`` with the method
preset, ``ours`` by default: the real skills, effect models, objective terms and simulator), on a
mid-episode belief: the episode's start view and ``views - 1`` seeded random candidate views
rendered by the simulator and integrated with the episode's observation model, every skill's
``track`` run after each (the grasp skill's FE-UMGF buffer grows as in an episode). The decision
is the one at the next step, with manipulation allowed.

Each repeat runs ``msas.decide`` on a fresh copy of the skills as they were after the prefix (so
the grasp skill's tracking runs every time, as once per episode step) and a fresh context, with a
``StageTimer``: a tracer (``msmem_core.util.trace``) that times every span the decision opens. Per
skill ``track``, ``propose``, the effect model's ``predict`` and ``score`` (``Objective.best``, the
scoring path of MSAS, refinement included), and inside them the objective terms, the IG service's
kernels and the stages plugins mark themselves (the grasp skill's FPP / FE-vMF / FE-UMGF steps).
Nothing is wrapped or patched. Medians over the repeats are reported.

References (``reference=True``): the brute-force float64 IG of ``msmem_core.map.ig_reference``
(extrapolated from a few views) for an IG sweep; a full, non-incremental re-score of every
predicted belief for the manipulation skills' ``ig`` term; and the whole decision with that
reference ``ig`` term. Approximations: the ``ig`` term screens candidates at every 2nd ray and
the IG kernels stop a ray at transmission 1e-3; over ``beliefs`` beliefs (other seeded view sets)
the chosen action is compared with exact scoring (no screening) and with fully exact scoring (no
screening, no early exit).
"""

from __future__ import annotations

import os
import statistics
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from msmem_core.config import RunConfig, load_config
from msmem_core.interfaces import Action, CandidateBatch, DecisionContext, PerceptionAction
from msmem_core.map.ig import IGDelta, IGService
from msmem_core.map.ig_reference import ig_views_reference
from msmem_core.msas import Decision, Objective, decide
from msmem_core.plugins.manager import ComponentRef, get_plugin_manager
from msmem_core.run.runner import Episode, build_episode, set_threads
from msmem_core.run.states import EpisodeState, clone_skills, decision_context, mid_episode_state
from msmem_core.util.trace import Span, Tracer

Path_ = tuple[str, ...]
_IG_STAGES = {"ig.prepare": "ig.prepare (belief -> IG field)", "ig.sweep": "IG sweep (all views)",
              "ig.after_view": "two-step: after_view", "ig.views": "IG of the finalist views (full density)"}


def stage_label(span: Span) -> str | None:
    """The table row of a span (None: the whole decision, reported as its total)."""
    s = span.stage
    if s == "decide":
        return None
    if s == "predict":
        return f"{span.skill}: effect prediction"
    if s in ("track", "propose", "score", "execute"):
        return f"{span.skill}: {s}"
    if s in ("term", "refine"):
        return f"{s} {span.info['term']}"
    if s == "ig.sweep" and int(span.info.get("ray_step", 1)) > 1:
        step = int(span.info["ray_step"])
        return f"IG sweep, screening (1 ray in {step}x{step})"
    if s == "ig.incremental":
        step = int(span.info.get("ray_step", 1))
        return f"IG incremental, screening (1 ray in {step}x{step})" if step > 1 else "IG incremental, full density"
    return _IG_STAGES.get(s, s)  # a component's own stage is shown by its name


@dataclass
class StageTimer(Tracer):
    """A tracer: inclusive wall-clock and CPU seconds (the process's, all threads) and call counts per
    call path of the spans it sees (one path element per ``stage_label``)."""

    seconds: dict[Path_, float] = field(default_factory=lambda: defaultdict(float))
    cpu: dict[Path_, float] = field(default_factory=lambda: defaultdict(float))
    calls: dict[Path_, int] = field(default_factory=lambda: defaultdict(int))
    batches: dict[str, tuple[DecisionContext, CandidateBatch]] = field(default_factory=dict)
    """The last batch each skill scored (with its context), for the references."""
    stack: list[str] = field(default_factory=list)
    _open: list[tuple[Path_, float, float] | None] = field(default_factory=list)

    def begin(self, span: Span) -> None:
        label = stage_label(span)
        if label is None:
            self._open.append(None)
            return
        if span.stage == "score" and span.skill is not None:
            self.batches[span.skill] = (span.info["ctx"], span.info["batch"])
        self.stack.append(label)
        key = tuple(self.stack)
        self.seconds.setdefault(key, 0.0)  # rows in call order, parents before children
        self._open.append((key, time.perf_counter(), time.process_time()))

    def end(self, span: Span) -> None:
        opened = self._open.pop()
        if opened is None:
            return
        key, t, c = opened
        self.seconds[key] += time.perf_counter() - t
        self.cpu[key] += time.process_time() - c
        self.calls[key] += 1
        self.stack.pop()


# ----------------------------------------------------------------------------------------- set-up
def _decide(ep: Episode, state: EpisodeState, objective: Objective | None = None, ig: IGService | None = None,
            seed: int = 0, tracer: Tracer | None = None) -> Decision:
    """One decision at the state's step (manipulation allowed) on fresh copies of the skills."""
    ctx = decision_context(ep, state.belief, state.visited, state.step, True, seed, ig)
    return decide(ctx, clone_skills(state.skills), objective or ep.objective, tracer)


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
    return a.skill.name == b.skill.name and a.action == b.action


def _describe(d: Decision) -> str:
    best = ", ".join(f"{k} {v:.1f}" for k, v in d.best.items())
    return f"{d.skill.name} #{d.index} (objective {d.value:.1f}; best per skill: {best})"


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

    per_repeat: list[StageTimer] = []
    totals: list[float] = []
    cpu_totals: list[float] = []
    decision: Decision | None = None
    for r in range(max(1, repeats) + 1):  # the first run warms up (numba loads its cached kernels)
        ctx = decision_context(ep, state.belief, state.visited, state.step, True, 0)
        skills = clone_skills(state.skills)
        timer = StageTimer()
        t, c = time.perf_counter(), time.process_time()
        decision = decide(ctx, skills, ep.objective, tracer=timer)
        total, cpu_total = time.perf_counter() - t, time.process_time() - c
        if r > 0:
            per_repeat.append(timer)
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
    res |= _time_observation_update(ep, state, decision, max(1, repeats))

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
    report(f"  {'observation update (' + cfg.observation_model.name + ')':{width}} {1:5d} {res['observe_s']:7.3f} "
           f"{res['observe_cpu_s']:7.3f}   (after the decision, outside decide(): the view {res['observe_view']}, "
           f"already rendered)")
    for key, (_, what) in refs.items():
        report(f"  reference for {key.split(' / ')[-1]!r} ({key.split(' / ')[0]}): {what}")
    if "reference/decide_s" in res:
        report(
            f"  decide() with the reference ig term (no screening, full re-score of every predicted belief): "
            f"{res['reference/decide_cpu_s']:.2f} s CPU = {res['reference/decide_cpu_s'] / total_cpu:.1f}x the median; "
            f"same decision: {res['reference/same_decision']}"
        )
    for skill in (b.name for b in ep.skills):
        if f"reference/{skill}_ig_max_abs_diff" in res:
            diff, rel = res[f"reference/{skill}_ig_max_abs_diff"], res[f"reference/{skill}_ig_max_rel_diff"]
            report(f"  {skill}: incremental IG (full density) vs the full re-score: max abs diff {diff:.2e} "
                   f"(rel {rel:.1e})")
    if "agreement" in res:
        a = res["agreement"]
        n = a["beliefs"]
        within = ", ".join(f"{skill} in {a[f'{skill}_best_differs']}/{a[f'{skill}_batches']}"
                           for skill in manipulation_skills(ep))
        report(
            f"  approximations, over {n} belief{'s' if n != 1 else ''} (view seeds {view_seed}..{view_seed + n - 1}): "
            f"the chosen action "
            f"differs from exact scoring (no screening) in {n - a['same_as_unscreened']}/{n}, from fully exact scoring "
            f"(no screening, no early exit) in {n - a['same_as_exact']}/{n}"
            + (f"; within a skill, the screened best candidate differs from the exact best: {within}" if within else "")
        )
    return res


def _time_observation_update(ep: Episode, state: EpisodeState, decision: Decision, repeats: int) -> dict[str, Any]:
    """Median wall and CPU seconds of the episode's observation update of one rendered view: the view
    the decision chose, or the first unvisited one when it chose a manipulation."""
    if isinstance(decision.action, PerceptionAction):
        view = decision.action.view
    else:
        view = next(v for v in range(len(ep.viewpoints)) if v not in state.visited)
    obs = ep.sim.observe(ep.viewpoints[view])
    walls, cpus = [], []
    for r in range(repeats + 1):  # the first run warms up
        t, c = time.perf_counter(), time.process_time()
        ep.observe_model.update(state.belief, obs)
        if r > 0:
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
    return {"observe_s": statistics.median(walls), "observe_cpu_s": statistics.median(cpus), "observe_view": view}


def _references(ep: Episode, state: EpisodeState, timed: Decision, probe: StageTimer, stages: dict[str, float],
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
        full = ig.view_ig([ig.prepare(b, before=field_) for b in batch.prediction.beliefs]).max(axis=1)
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


def _deltas(ctx: DecisionContext, batch: CandidateBatch) -> list[IGDelta]:
    """The IG deltas of a manipulation batch (as the ``ig`` term computes them)."""
    assert batch.prediction is not None
    return [ctx.ig.belief_delta(ctx.field, d) for d in batch.prediction.changes]


def _agreement(ep: Episode, state: EpisodeState, beliefs: int, views: int, seed: int,
               first: tuple[Decision, StageTimer]) -> dict[str, int]:
    """How often the approximations change the chosen action (default vs unscreened vs fully exact)."""
    unscreened = objective_with(ep, screen_ray_step=1)
    exact_ig = IGService(ep.ig.grid, ep.cfg.camera, ep.viewpoints, ep.scene.shelf,
                         ep.cfg.ig.model_copy(update={"early_exit": 0.0}))
    skills = manipulation_skills(ep)
    counts = {"beliefs": 0, "same_as_unscreened": 0, "same_as_exact": 0,
              **{f"{skill}_{k}": 0 for skill in skills for k in ("batches", "best_differs")}}
    for b in range(beliefs):
        if b == 0:
            st, (d, probe) = state, first
        else:
            st, probe = mid_episode_state(ep, views, seed + b), StageTimer()
            d = _decide(ep, st, tracer=probe)
        d_uns = _decide(ep, st, unscreened)
        d_exact = _decide(ep, st, unscreened, exact_ig)
        counts["beliefs"] += 1
        counts["same_as_unscreened"] += _same(d, d_uns)
        counts["same_as_exact"] += _same(d, d_exact)
        for skill in skills:
            if skill not in probe.batches:
                continue
            _, batch = probe.batches[skill]
            i_exact = unscreened.best(decision_context(ep, st.belief, st.visited, st.step), batch)[0]
            i_screened = ep.objective.best(decision_context(ep, st.belief, st.visited, st.step), batch)[0]
            counts[f"{skill}_batches"] += 1
            counts[f"{skill}_best_differs"] += int(i_exact != i_screened)
    return counts


def manipulation_skills(ep: Episode) -> list[str]:
    """The config names of the episode's manipulation skills, in config order."""
    return [b.name for b in ep.skills if b.skill.category == "manipulation"]


def is_valid_action(action: Action, num_views: int) -> bool:
    """A decision's action survives a JSON round trip through its own model and names a real view."""
    again = type(action).model_validate_json(action.model_dump_json())
    return again == action and (not isinstance(action, PerceptionAction) or 0 <= action.view < num_views)

"""Conformance suites for skills and effect models, in the manner of ``simulator_conformance``.

Usage, inside a pytest test of the plugin::

    from msmem_core.testing.conformance import effect_model_conformance, skill_conformance

    def test_my_skill_conforms():
        skill_conformance(MySkill, "mine", belief=belief_with_boxes(...))   # executes on PyBullet

    def test_my_effect_model_conforms():
        effect_model_conformance(MyEffect, actions_for=lambda ctx: MySkill().propose(ctx), belief=...)

A factory is anything that returns a fresh component when called: the class, ``lambda:
MySkill(MyConfig(...))``, or the registered name (``"push"``: built through the plugin manager).
Each suite checks its argument first and raises ``ConformanceUsageError`` (a ``TypeError``) in one
line when it is not what the suite tests. A failed check raises ``ConformanceError`` (an
``AssertionError``) naming the component and the rule; every ``check_*`` function is public, so a
plugin can also run the checks one by one.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from msmem_core.interfaces import (
    Action,
    DecisionContext,
    EffectModel,
    ObservationModel,
    Outcome,
    PerceptionAction,
    Prediction,
    Simulator,
    Skill,
    Term,
    Workspace,
)
from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_core.map.ig import IGService
from msmem_core.testing.builders import (
    belief_of_scene,
    conformance_scene,
    decision_context,
    default_workspace,
    small_ig,
)
from msmem_core.util.jsonable import jsonable
from msmem_core.world.camera import CameraConfig, Observation
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import SceneSpec

SimulatorChoice = Callable[[], Simulator] | Literal["pybullet", "fake"] | None
EXECUTE_CAMERA = CameraConfig(width_px=160, height_px=120)
"""Camera of the simulator ``skill_conformance`` builds (small: fast to render)."""


@dataclass
class SkillReport:
    """What ``skill_conformance`` saw: the actions proposed on the belief and the outcomes of those
    it executed (as ``execute`` returned them), for further assertions of the plugin's own."""

    actions: list[Action]
    outcomes: list[Outcome] = field(default_factory=list)


class ConformanceError(AssertionError):
    """A component broke a rule of its interface (the message names the component and the rule)."""


class ConformanceUsageError(TypeError):
    """A suite was handed something other than what it tests."""


# ---------------------------------------------------------------------------------------- arguments
_KINDS: tuple[tuple[type, str], ...] = (
    (Simulator, "Simulator"),
    (Skill, "Skill"),
    (EffectModel, "EffectModel"),
    (ObservationModel, "ObservationModel"),
    (Term, "objective Term"),
    (Action, "Action"),
)


def describe(obj: object) -> str:
    """What ``obj`` is, for a usage message: ``a Skill (msmem_view.skill.ViewSkill)``, ``the class
    ViewSkill (a Skill)``, ``a str``."""
    if isinstance(obj, type):
        kind = next((n for k, n in _KINDS if issubclass(obj, k)), None)
        return f"the class {obj.__qualname__}" + (f" (a {kind})" if kind else "")
    cls = type(obj)
    kind = next((n for k, n in _KINDS if isinstance(obj, k)), None)
    where = f"{cls.__module__}.{cls.__qualname__}"
    return f"a {kind} ({where})" if kind else f"a {cls.__qualname__}" + ("" if cls.__module__ == "builtins" else
                                                                           f" ({where})")


def built(factory: Any, expected: type, suite: str, what: str, build: Callable[[str], Any] | None = None) -> Any:
    """Call ``factory`` (``build(name)`` for a string) and check it returned an ``expected``;
    anything else raises ``ConformanceUsageError`` naming the suite, what it expected and what it got."""
    want = f"{suite} expects {what}"
    if isinstance(factory, str):
        if build is None:
            raise ConformanceUsageError(f"{want}, got the string {factory!r}")
        obj = build(factory)
    elif isinstance(factory, expected):
        raise ConformanceUsageError(f"{want}, got {describe(factory)} itself: pass a factory, e.g. "
                                    f"`lambda: {type(factory).__name__}(...)` or the class")
    elif not callable(factory) or (not isinstance(factory, type) and any(isinstance(factory, k) for k, _ in _KINDS)):
        raise ConformanceUsageError(f"{want}, got {describe(factory)}")
    elif isinstance(factory, type) and not issubclass(factory, expected):
        raise ConformanceUsageError(f"{want}, got {describe(factory)}")
    else:
        obj = factory()
    if not isinstance(obj, expected):
        if isinstance(obj, Simulator):
            obj.close()
        raise ConformanceUsageError(f"{want}, but the factory returned {describe(obj)}")
    return obj


def _fail(msg: str) -> None:
    raise ConformanceError(msg)


def _plugin_manager_build(kind: str) -> Callable[[str], Any]:
    def build(name: str) -> Any:
        from msmem_core.plugins import get_plugin_manager

        return get_plugin_manager().build(kind, name)

    return build


# ------------------------------------------------------------------------------------------- skills
def check_actions(actions: object, name: str, skill: Skill, ctx: DecisionContext) -> list[Action]:
    """``propose`` returned a list of ``Action``\\ s whose ``kind`` is the skill's registered name and
    whose ``category`` is the skill's; each survives a JSON round trip (``model_dump_json`` then
    ``model_validate_json`` of its class gives an equal action); a perception skill's are
    ``PerceptionAction``\\ s with a view index into ``ctx.viewpoints``; a manipulation's
    ``swept_volume(workspace)`` is a boolean mask of the grid."""
    who = f"skill {name!r} ({type(skill).__name__})"
    if not isinstance(actions, list):
        _fail(f"{who}: propose must return a list of actions, got {describe(actions)}")
    assert isinstance(actions, list)
    for i, a in enumerate(actions):
        if not isinstance(a, Action):
            _fail(f"{who}: action {i} is {describe(a)}, not a msmem_core.interfaces.Action")
        if a.kind != name:
            _fail(f"{who}: action {i} has kind {a.kind!r}; an action's kind must be the skill's registered name "
                  f"{name!r}")
        if a.category != skill.category:
            _fail(f"{who}: action {i} has category {a.category!r}, the skill's is {skill.category!r}")
        try:
            again = type(a).model_validate_json(a.model_dump_json())
        except Exception as e:  # any failure of the round trip is the finding
            _fail(f"{who}: action {i} ({type(a).__name__}) does not survive a JSON round trip: "
                  f"{type(e).__name__}: {str(e).splitlines()[0]}")
        if again != a:
            _fail(f"{who}: action {i} ({type(a).__name__}) changes in a JSON round trip: {a!r} -> {again!r}")
        if skill.category == "perception":
            if not isinstance(a, PerceptionAction):
                _fail(f"{who}: a perception skill's actions must be msmem_core.interfaces.PerceptionAction "
                      f"(naming their view); action {i} is a {type(a).__name__}")
            assert isinstance(a, PerceptionAction)
            if not 0 <= a.view < len(ctx.viewpoints):
                _fail(f"{who}: action {i} names view {a.view}, outside the {len(ctx.viewpoints)} viewpoints")
        else:
            vol = a.swept_volume(ctx.workspace)
            if not (isinstance(vol, np.ndarray) and vol.dtype == bool and vol.shape == tuple(ctx.grid.shape)):
                got = f"{vol.dtype} {vol.shape}" if isinstance(vol, np.ndarray) else describe(vol)
                _fail(f"{who}: action {i}'s swept_volume(workspace) must be a bool mask of shape "
                      f"{tuple(ctx.grid.shape)}, got {got}")
    return actions


def check_reproducible(factory: Callable[[], Skill], name: str, make_ctx: Callable[[], DecisionContext],
                       first: list[Action]) -> None:
    """A fresh skill on a context with the same seed proposes the same actions: every random
    choice draws from ``ctx.rng``."""
    skill = factory()
    ctx = make_ctx()
    skill.track(ctx)
    again = skill.propose(ctx)
    if again != first:
        _fail(f"skill {name!r} ({type(skill).__name__}): two fresh skills on the same belief and seed proposed "
              f"different actions ({len(first)} vs {len(again)}): draw every random number from ctx.rng")


def check_manipulation_gate(skill: Skill, name: str, ctx: DecisionContext) -> None:
    """A manipulation skill proposes nothing when ``ctx.manipulation_allowed`` is false."""
    if ctx.manipulation_allowed:
        raise ValueError("check_manipulation_gate needs a context with manipulation_allowed=False")
    skill.track(ctx)
    actions = skill.propose(ctx)
    if actions:
        _fail(f"skill {name!r} ({type(skill).__name__}): proposed {len(actions)} action(s) although "
              "ctx.manipulation_allowed is false: return [] then")


def check_outcome(outcome: object, name: str, skill: Skill, action: Action, object_ids: set[int]) -> Outcome:
    """What ``execute`` returned directly (before MSAS measures it): an ``Outcome`` with a bool
    ``success``; a perception action's ``observation`` set, a manipulation's None; ``removed`` ids
    of objects that were in the scene; ``info`` a dict that ``steps.jsonl`` can hold; and
    ``displacement_m`` / ``fell_or_left`` left empty (MSAS measures them, ``execute_measured``)."""
    who = f"skill {name!r} ({type(skill).__name__})"
    if not isinstance(outcome, Outcome):
        _fail(f"{who}: execute must return a msmem_core.interfaces.Outcome, got {describe(outcome)}")
    assert isinstance(outcome, Outcome)
    if not isinstance(outcome.success, bool | np.bool_):
        _fail(f"{who}: Outcome.success must be a bool, got {describe(outcome.success)}")
    if action.category == "perception":
        if not isinstance(outcome.observation, Observation):
            _fail(f"{who}: a perception action's outcome must carry its Observation, got "
                  f"{describe(outcome.observation)}")
    elif outcome.observation is not None:
        _fail(f"{who}: a manipulation's outcome must not carry an observation (MSAS would integrate it instead "
              "of the effect model's prediction)")
    if outcome.displacement_m or outcome.fell_or_left:
        _fail(f"{who}: execute set displacement_m / fell_or_left; leave them empty, MSAS measures them for "
              "every skill (msmem_core.msas.execute_measured)")
    if not isinstance(outcome.removed, list) or not all(isinstance(i, int) for i in outcome.removed):
        _fail(f"{who}: Outcome.removed must be a list of object ids (int), got {outcome.removed!r}")
    unknown = set(outcome.removed) - object_ids
    if unknown:
        _fail(f"{who}: Outcome.removed names objects that were not in the scene: {sorted(unknown)}")
    if not isinstance(outcome.info, dict):
        _fail(f"{who}: Outcome.info must be a dict, got {describe(outcome.info)}")
    try:
        json.dumps(jsonable(outcome.info))
    except (TypeError, ValueError) as e:
        _fail(f"{who}: Outcome.info must be JSON-serialisable (it is written to steps.jsonl): {e}")
    return outcome


def _simulator(choice: SimulatorChoice, camera: CameraConfig) -> Simulator:
    if choice == "fake":
        from msmem_core.testing.fake import FakeSimulator

        return FakeSimulator(camera)
    if choice == "pybullet":
        from msmem_core.sim.build import build_simulator

        return build_simulator("pybullet", camera=camera, seed=0, label_noise=0.0)
    sim: Simulator = built(choice, Simulator, "skill_conformance", "simulator= a factory returning a Simulator, "
                           "'pybullet', 'fake' or None")
    return sim


def skill_conformance(
    factory: Callable[[], Skill] | str,
    name: str | None = None,
    *,
    belief: EvidentialMap | None = None,
    scene: SceneSpec | None = None,
    workspace: Workspace | None = None,
    ig: IGService | None = None,
    step: int = 1,
    simulator: SimulatorChoice = "pybullet",
    execute: int = 1,
    camera: CameraConfig | None = None,
) -> SkillReport:
    """Run every skill check on skills from ``factory``, registered as ``name``; return the actions
    proposed on ``belief`` and the outcomes of those executed (``SkillReport``).

    ``factory`` is a class or function returning a fresh ``Skill``, or a registered name (built
    through the plugin manager; ``name`` defaults to it). The context is ``decision_context(belief,
    step)`` (``workspace`` default ``default_workspace()``, ``ig`` default four viewpoints); ``belief``
    defaults to the exactly known ``scene`` (``belief_of_scene``; ``scene`` default
    ``conformance_scene()``). The skill must propose at least one action there.

    Checks: ``check_actions``; ``check_reproducible``; for a manipulation skill
    ``check_manipulation_gate``; then, unless ``simulator`` is None, the first ``execute`` actions
    are executed, each on a freshly reset ``scene``, and ``check_outcome`` looks at what ``execute``
    returned. ``simulator``: ``"pybullet"`` (built through the plugin manager with ``camera``,
    default 160 x 120), ``"fake"`` (``FakeSimulator``: control flow only), or a factory.
    """
    suite = "skill_conformance"
    skill: Skill = built(factory, Skill, suite, "a factory returning a msmem_core.interfaces.Skill (or a registered "
                         "skill name)", _plugin_manager_build("skill"))

    def make() -> Skill:
        fresh: Skill = built(factory, Skill, suite, "a Skill", _plugin_manager_build("skill"))
        return fresh

    if name is None:
        if not isinstance(factory, str):
            raise ConformanceUsageError(f"{suite} needs the skill's registered name: {suite}(factory, 'name')")
        name = factory
    if skill.category not in ("perception", "manipulation"):
        _fail(f"skill {name!r} ({type(skill).__name__}): category must be 'perception' or 'manipulation', "
              f"got {skill.category!r}")
    ws = workspace or (Workspace(belief.grid, default_workspace().shelf) if belief is not None else
                       default_workspace())
    scene = scene or conformance_scene()
    if belief is None:
        belief = belief_of_scene(scene, ws.grid)
    ig = ig or small_ig(ws)

    def ctx_of(allowed: bool) -> DecisionContext:
        return decision_context(belief, step, manipulation_allowed=allowed, workspace=ws, ig=ig, seed=step)

    ctx = ctx_of(True)
    skill.track(ctx)
    actions = check_actions(skill.propose(ctx), name, skill, ctx)
    if not actions:
        _fail(f"skill {name!r} ({type(skill).__name__}) proposed nothing on the given belief: the checks need a "
              "belief in which it acts (pass belief=...)")
    check_reproducible(make, name, lambda: ctx_of(True), actions)
    if skill.category == "manipulation":
        check_manipulation_gate(make(), name, ctx_of(False))
    report = SkillReport(actions)
    if simulator is None or execute <= 0:
        return report
    sim = _simulator(simulator, camera or EXECUTE_CAMERA)
    try:
        ids = {o.id for o in scene.objects}
        for action in actions[:execute]:
            sim.reset(scene)
            report.outcomes.append(check_outcome(skill.execute(sim, action, ctx), name, skill, action, ids))
    finally:
        sim.close()
    return report


# ------------------------------------------------------------------------------------ effect models
def check_prediction(prediction: object, belief: EvidentialMap, actions: Sequence[Action], label: str) -> Prediction:
    """A ``Prediction`` relative to ``belief`` (its ``base`` is that very object) with one change per
    action; each change has int64 flat indices that are in range, sorted and unique, new alpha and
    beta ``[n]`` and eta ``[C, n]``, finite and >= 1 (the prior), and lists only voxels whose
    evidence differs from the base; the dense ``changed`` masks equal the changes' indices;
    ``excluded`` is None or one in-range index array per action."""
    if not isinstance(prediction, Prediction):
        _fail(f"{label}: predict must return a msmem_core.interfaces.Prediction, got {describe(prediction)}")
    assert isinstance(prediction, Prediction)
    if prediction.base is not belief:
        _fail(f"{label}: Prediction.base must be the belief predict was given (the same object), not a copy")
    k = len(actions)
    if len(prediction.changes) != k:
        _fail(f"{label}: {len(prediction.changes)} changes for {k} actions: one change per action, in order")
    size, c = belief.grid.size, belief.num_classes
    a0, b0, e0 = belief.alpha.reshape(-1), belief.beta.reshape(-1), belief.eta.reshape(c, -1)
    for i, d in enumerate(prediction.changes):
        at = f"{label}: change {i} (action {actions[i].kind!r})"
        if not isinstance(d, BeliefDelta):
            _fail(f"{at} is {describe(d)}, not a msmem_core.map.belief.BeliefDelta")
        idx = np.asarray(d.idx)
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
            _fail(f"{at}: idx must be a 1-D integer array of flat voxel indices, got {idx.dtype} {idx.shape}")
        n = len(idx)
        if n and (idx.min() < 0 or idx.max() >= size):
            _fail(f"{at}: voxel indices outside the grid [0, {size}): {idx.min()}..{idx.max()}")
        if n > 1 and not np.all(np.diff(idx) > 0):
            _fail(f"{at}: voxel indices must be sorted and unique")
        for what, arr, shape in (("alpha", d.alpha, (n,)), ("beta", d.beta, (n,)), ("eta", d.eta, (c, n))):
            arr = np.asarray(arr)
            if arr.shape != shape:
                _fail(f"{at}: {what} has shape {arr.shape}, expected {shape}")
            if not np.all(np.isfinite(arr)):
                _fail(f"{at}: {what} is not finite everywhere")
            if n and arr.min() < 1.0:
                _fail(f"{at}: {what} falls below the prior 1 (min {float(arr.min()):.3g}): evidence is >= 1")
        same = (d.alpha == a0[idx]) & (d.beta == b0[idx]) & np.all(d.eta == e0[:, idx], axis=0)
        if same.any():
            _fail(f"{at}: lists {int(same.sum())} voxel(s) whose evidence equals the base's; list only what "
                  "changes (BeliefDelta.against(base) drops the rest)")
    changed = np.asarray(prediction.changed)
    if changed.shape != (k, *belief.grid.shape):
        _fail(f"{label}: Prediction.changed has shape {changed.shape}, expected {(k, *belief.grid.shape)}")
    for i, d in enumerate(prediction.changes):
        if not np.array_equal(np.flatnonzero(changed[i]), np.asarray(d.idx)):
            _fail(f"{label}: Prediction.changed[{i}] does not match the voxels of change {i}")
    if prediction.excluded is not None:
        if len(prediction.excluded) != k:
            _fail(f"{label}: excluded has {len(prediction.excluded)} entries for {k} actions (None: nothing excluded)")
        for i, ex in enumerate(prediction.excluded):
            ex = np.asarray(ex)
            if ex.ndim != 1 or (len(ex) and (not np.issubdtype(ex.dtype, np.integer) or ex.min() < 0
                                             or ex.max() >= size)):
                _fail(f"{label}: excluded[{i}] must be flat voxel indices in [0, {size})")
    return prediction


def check_base_unchanged(belief: EvidentialMap, before: tuple[np.ndarray, np.ndarray, np.ndarray], label: str) -> None:
    """``predict`` left the belief it was given as it was."""
    for what, arr, old in zip(("alpha", "beta", "eta"), (belief.alpha, belief.beta, belief.eta), before, strict=True):
        if not np.array_equal(arr, old):
            _fail(f"{label}: predict modified the belief it was given ({what} of "
                  f"{int(np.sum(arr != old))} voxel(s)); predictions are changes relative to it")


def _same_prediction(p: Prediction, q: Prediction) -> bool:
    return len(p.changes) == len(q.changes) and all(
        np.array_equal(a.idx, b.idx) and np.array_equal(a.alpha, b.alpha) and np.array_equal(a.beta, b.beta)
        and np.array_equal(a.eta, b.eta) for a, b in zip(p.changes, q.changes, strict=True))


def effect_model_conformance(
    factory: Callable[[], EffectModel] | str,
    actions_for: Callable[[DecisionContext], Sequence[Action]],
    *,
    belief: EvidentialMap | None = None,
    workspace: Workspace | None = None,
    step: int = 1,
    expect_change: bool = True,
) -> Prediction:
    """Run every effect-model check on a model from ``factory`` (a class, a function, or a
    registered belief-model name with the *effect* role); return its prediction.

    The actions are ``actions_for(ctx)`` on ``ctx = decision_context(belief, step)`` (e.g.
    ``lambda ctx: MySkill().propose(ctx)``); ``belief`` defaults to the exactly known default
    scene (``belief_of_scene``), ``workspace`` to the belief's grid in the default shelf. Checks
    ``check_prediction``, ``check_base_unchanged``, that a second ``predict`` gives the same
    changes, and (``expect_change``) that some action changes something: effect models must predict
    what moves.
    """
    suite = "effect_model_conformance"
    model: EffectModel = built(factory, EffectModel, suite, "a factory returning a msmem_core.interfaces.EffectModel "
                               "(or a registered belief-model name with the effect role)",
                               _plugin_manager_build("belief-model"))
    label = f"effect model {type(model).__name__}" + (f" ({factory!r})" if isinstance(factory, str) else "")
    if not callable(actions_for):
        raise ConformanceUsageError(f"{suite} expects actions_for= a function of the DecisionContext returning "
                                    f"actions, got {describe(actions_for)}")
    ws = workspace or (Workspace(belief.grid, default_workspace().shelf) if belief is not None else
                       default_workspace())
    if belief is None:
        belief = belief_of_scene(conformance_scene(), ws.grid)
    ctx = decision_context(belief, step, workspace=ws, ig=small_ig(ws), seed=step)
    actions = list(actions_for(ctx))
    if not actions:
        raise ConformanceUsageError(f"{suite}: actions_for returned no actions on the given belief; the checks "
                                    "need some (pass a belief in which the skill acts)")
    bad = next((a for a in actions if not isinstance(a, Action)), None)
    if bad is not None:
        raise ConformanceUsageError(f"{suite}: actions_for must return Actions, got {describe(bad)}")
    before = (belief.alpha.copy(), belief.beta.copy(), belief.eta.copy())
    prediction = check_prediction(model.predict(belief, actions, ws), belief, actions, label)
    check_base_unchanged(belief, before, label)
    again = model.predict(belief, actions, ws)
    if not isinstance(again, Prediction) or not _same_prediction(prediction, again):
        _fail(f"{label}: two predictions of the same actions on the same belief differ: predict must be "
              "deterministic")
    if expect_change and not any(len(d.idx) for d in prediction.changes):
        _fail(f"{label}: none of the {len(actions)} actions changes the belief; an effect model predicts what "
              "moves (expect_change=False if that is right for these actions)")
    return prediction


def _check_evidence(out: EvidentialMap, label: str) -> None:
    for what, arr in (("alpha", out.alpha), ("beta", out.beta), ("eta", out.eta)):
        if not np.all(np.isfinite(arr)):
            _fail(f"{label}: {what} has non-finite values")
        if float(arr.min()) < 1.0 - 1e-6:
            _fail(f"{label}: {what} goes below the prior's 1 (min {float(arr.min()):.4g}); evidence is at least 1")


def check_updated_belief(out: object, belief: EvidentialMap, label: str) -> EvidentialMap:
    """``update``'s result is a new ``EvidentialMap`` on the same grid and classes, evidence finite and
    at least 1, sharing no array with its input, with a ray record (``observed``) that is None or a
    boolean grid that keeps every voxel the input's record had."""
    if not isinstance(out, EvidentialMap):
        _fail(f"{label}: update must return an EvidentialMap, got {describe(out)}")
    assert isinstance(out, EvidentialMap)
    if out.grid != belief.grid:
        _fail(f"{label}: update returned a belief on another grid ({out.grid} for {belief.grid})")
    if out.num_classes != belief.num_classes:
        _fail(f"{label}: update returned {out.num_classes} classes for {belief.num_classes}")
    if any(np.shares_memory(a, b) for a in (out.alpha, out.beta, out.eta) for b in (belief.alpha, belief.beta,
                                                                                     belief.eta)):
        _fail(f"{label}: update returned arrays shared with its input; return a new map (MSAS and the terms keep "
              "references to earlier beliefs)")
    _check_evidence(out, label)
    if out.observed is not None:
        obs = np.asarray(out.observed)
        if obs.dtype != np.bool_ or obs.shape != tuple(belief.grid.shape):
            _fail(f"{label}: observed must be a boolean array of the grid's shape {tuple(belief.grid.shape)}, got "
                  f"{obs.dtype} {obs.shape}")
        if belief.observed is not None and np.any(belief.observed & ~obs):
            _fail(f"{label}: observed lost {int(np.sum(belief.observed & ~obs))} voxel(s) the input's ray record "
                  "had; a view only adds to the record")
    return out


def observation_model_conformance(
    factory: Callable[[], ObservationModel] | str,
    *,
    grid: GridSpec | None = None,
    camera: CameraConfig | None = None,
    views: int = 2,
) -> EvidentialMap:
    """Run every observation-model check on a model from ``factory`` (a class, a function, or a
    registered belief-model name with the *observe* role); return the belief after ``views`` views.

    The conformance scene (``conformance_scene``) is observed in PyBullet from ``views`` of the default
    viewpoints, the start view first, and integrated from the prior on ``grid`` (default: the library's
    grid). Per view: ``check_updated_belief`` and that the input belief is left as it was; after the
    first view the belief differs from the prior (a view is evidence); and a second model from
    ``factory`` fed the same views returns the same beliefs (``update`` is deterministic).
    """
    from msmem_core.sim.build import build_simulator
    from msmem_core.world.viewpoints import ViewpointConfig, default_start_view, generate_viewpoints

    suite = "observation_model_conformance"
    what = ("a factory returning a msmem_core.interfaces.ObservationModel (or a registered belief-model name "
            "with the observe role)")
    model: ObservationModel = built(factory, ObservationModel, suite, what, _plugin_manager_build("belief-model"))
    label = f"observation model {type(model).__name__}" + (f" ({factory!r})" if isinstance(factory, str) else "")
    if views < 1:
        raise ConformanceUsageError(f"{suite}: views must be at least 1, got {views}")
    scene = conformance_scene()
    grid = grid or GridSpec()
    camera = camera or CameraConfig(width_px=160, height_px=120)
    cfg = ViewpointConfig()
    poses = generate_viewpoints(cfg, scene.shelf)
    start = default_start_view(cfg)
    order = [start, *[int(i) for i in np.linspace(0, len(poses) - 1, views + 1).astype(int) if i != start]][:views]
    sim = build_simulator("pybullet", camera=camera, seed=0, label_noise=0.0)
    try:
        sim.reset(scene)
        observations = [sim.observe(poses[v]) for v in order]
    finally:
        sim.close()
    beliefs = []
    belief = EvidentialMap.empty(grid, scene.num_classes)
    for i, obs in enumerate(observations):
        before = (belief.alpha.copy(), belief.beta.copy(), belief.eta.copy())
        out = check_updated_belief(model.update(belief, obs), belief, f"{label}, view {i + 1}")
        for name, arr, old in zip(("alpha", "beta", "eta"), (belief.alpha, belief.beta, belief.eta), before,
                                  strict=True):
            if not np.array_equal(arr, old):
                _fail(f"{label}: update modified the belief it was given ({name} of {int(np.sum(arr != old))} "
                      "voxel(s)); return a new map")
        if i == 0 and all(np.array_equal(a, b) for a, b in zip((out.alpha, out.beta, out.eta), before, strict=True)):
            _fail(f"{label}: the first view left the prior unchanged; a view is evidence")
        beliefs.append(out)
        belief = out
    again: ObservationModel = built(factory, ObservationModel, suite, what, _plugin_manager_build("belief-model"))
    b2 = EvidentialMap.empty(grid, scene.num_classes)
    for i, obs in enumerate(observations):
        b2 = again.update(b2, obs)
        if not all(np.array_equal(a, b) for a, b in zip((b2.alpha, b2.beta, b2.eta),
                                                         (beliefs[i].alpha, beliefs[i].beta, beliefs[i].eta),
                                                         strict=True)):
            _fail(f"{label}: a second model fed the same views returned another belief at view {i + 1}: update "
                  "must be deterministic")
    return belief


__all__ = [
    "EXECUTE_CAMERA",
    "ConformanceError",
    "ConformanceUsageError",
    "SkillReport",
    "built",
    "check_actions",
    "check_base_unchanged",
    "check_manipulation_gate",
    "check_outcome",
    "check_prediction",
    "check_reproducible",
    "check_updated_belief",
    "describe",
    "effect_model_conformance",
    "observation_model_conformance",
    "skill_conformance",
]

"""The testing kit: msmem's own skills and effect models pass the conformance suites; every check
catches a deliberately broken skill or effect model with a message naming the rule; every suite
refuses the wrong kind of argument in one line; the builders and ``one_decision``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import numpy as np
import pytest
from msmem_grasp.effect import AnalyticGraspEffect
from msmem_grasp.skill import GraspSkill
from msmem_push.effect import AnalyticPushEffect
from msmem_push.skill import PushSkill
from msmem_view.skill import ViewAction, ViewSkill
from pydantic import field_serializer

from msmem_core.interfaces import (
    Action,
    CandidateBatch,
    Category,
    DecisionContext,
    EffectModel,
    Outcome,
    PerceptionAction,
    Prediction,
    Simulator,
    Skill,
    Term,
    Workspace,
)
from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_core.msas import BoundSkill
from msmem_core.testing import (
    ConformanceError,
    ConformanceUsageError,
    FakeSimulator,
    belief_of_scene,
    belief_with_boxes,
    decision_context,
    default_workspace,
    effect_model_conformance,
    one_decision,
    simulator_conformance,
    skill_conformance,
    small_ig,
)
from msmem_core.testing.conformance import conformance_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")
WS = default_workspace()
SCENE = conformance_scene()
FRONT_SEEN = ((-0.5, -0.2, -0.1), (0.5, 0.16, 0.4))
"""The front of the shelf seen (the foam brick at y = 0.12 and the free space around it), the back not."""
CAN = 9


@pytest.fixture(scope="module")
def known() -> EvidentialMap:
    """The conformance scene, known exactly."""
    return belief_of_scene(SCENE, WS.grid)


@pytest.fixture(scope="module")
def front() -> EvidentialMap:
    """The conformance scene with only its front seen: the push skill has occluders to push."""
    return belief_of_scene(SCENE, WS.grid, known=FRONT_SEEN)


# ------------------------------------------------------------------------------- msmem's own plugins
def test_the_view_skill_conforms_and_observes_in_pybullet():
    report = skill_conformance("view")
    assert len(report.actions) == 3  # four viewpoints, the first visited
    (outcome,) = report.outcomes
    assert outcome.observation is not None
    assert outcome.observation.depth.shape == (120, 160)


def test_the_push_skill_conforms_and_pushes_in_pybullet(front):
    report = skill_conformance(PushSkill, "push", belief=front, scene=SCENE)
    assert all(a.kind == "push" for a in report.actions)
    assert report.outcomes[0].success


def test_the_grasp_skill_conforms_and_grasps_in_pybullet(known):
    report = skill_conformance("grasp", belief=known, scene=SCENE)
    (outcome,) = report.outcomes
    assert outcome.success, outcome.info
    assert len(outcome.removed) == 1


@pytest.mark.parametrize("model", [AnalyticPushEffect, "push-analytic"])
def test_the_analytic_push_effect_conforms(model, front):
    prediction = effect_model_conformance(model, lambda ctx: PushSkill().propose(ctx)[:8], belief=front)
    assert len(prediction) == 8


def test_the_analytic_grasp_effect_conforms(known):
    prediction = effect_model_conformance(AnalyticGraspEffect, lambda ctx: GraspSkill().propose(ctx)[:4], belief=known)
    assert prediction.excluded is not None


@pytest.mark.parametrize(("model", "skill"), [("cnabu-push", PushSkill), ("cnabu-grasp", GraspSkill)])
def test_the_learned_cnabu_effects_conform_on_their_1_cm_grid(model, skill):
    ws = default_workspace(0.01)  # the shipped weights' grid
    belief = belief_of_scene(SCENE, ws.grid, known=FRONT_SEEN if skill is PushSkill else None)
    effect_model_conformance(model, lambda ctx: skill().propose(ctx)[:3], belief=belief, workspace=ws)


# ------------------------------------------------------------------------------- toy plugins to break
class PokeAction(Action):
    kind: str = "poke"
    category: Literal["manipulation"] = "manipulation"
    x_m: float


class Poke(Skill):
    """Pokes at random x along the front; the gripper moves to the point and parks."""

    category: ClassVar[Category] = "manipulation"

    def propose(self, ctx: Any) -> list[Action]:
        if not ctx.manipulation_allowed:
            return []
        return [PokeAction(x_m=float(x)) for x in ctx.rng.uniform(-0.2, 0.2, 3)]

    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        assert isinstance(action, PokeAction)
        pose = np.eye(4)
        pose[:3, 3] = (action.x_m, 0.05, 0.05)
        sim.move_gripper([pose], opening_m=0.0)
        sim.park_gripper()
        return Outcome(success=True, info={"x_m": action.x_m})


class PokeEffect(EffectModel):
    """The poked column at the front becomes confidently free."""

    def changes(self, belief: EvidentialMap, a: Action) -> BeliefDelta:
        assert isinstance(a, PokeAction)
        c = belief.grid.centers()
        m = (np.abs(c[..., 0] - a.x_m) < 0.03) & (c[..., 1] < 0.06) & (c[..., 2] < 0.1)
        idx = np.flatnonzero(m)
        eta = belief.eta.reshape(belief.num_classes, -1)[:, idx].copy()
        eta[0] += 10.0
        d = BeliefDelta(idx, belief.alpha.reshape(-1)[idx].copy(), belief.beta.reshape(-1)[idx] + 10.0, eta)
        return d.against(belief)

    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        return Prediction(belief, [self.changes(belief, a) for a in actions])


def poke_conformance(skill: type[Skill] = Poke, **kw: Any) -> Any:
    return skill_conformance(skill, "poke", belief=EvidentialMap.empty(WS.grid), simulator="fake", **kw)


def poke_effect_conformance(model: type[EffectModel]) -> Prediction:
    return effect_model_conformance(model, lambda ctx: Poke().propose(ctx), belief=EvidentialMap.empty(WS.grid))


def test_the_toy_plugins_conform():
    report = poke_conformance()
    assert len(report.actions) == 3
    assert report.outcomes[0].info["x_m"] == report.actions[0].x_m  # type: ignore[attr-defined]
    assert len(poke_effect_conformance(PokeEffect)) == 3


class Glance(Poke):
    category: ClassVar[Category] = "perception"

    def propose(self, ctx: Any) -> list[Action]:
        return [Action(kind="poke", category="perception")]


class FarView(Poke):
    category: ClassVar[Category] = "perception"

    def propose(self, ctx: Any) -> list[Action]:
        return [ViewAction(kind="poke", view=99)]


class Named(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return [PokeAction(kind="jab", x_m=0.0)] if ctx.manipulation_allowed else []


class WrongCategory(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return [ViewAction(kind="poke", view=0)] if ctx.manipulation_allowed else []


class ArrayAction(PokeAction):
    data: Any = None


class Unserialisable(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return [ArrayAction(x_m=0.0, data=object())] if ctx.manipulation_allowed else []


class RoundedAction(PokeAction):
    @field_serializer("x_m")
    def _rounded(self, v: float) -> float:
        return round(v, 2)


class Lossy(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return [RoundedAction(x_m=0.1234)] if ctx.manipulation_allowed else []


class Tuple(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return tuple(super().propose(ctx))  # type: ignore[return-value]


class Ungated(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return [PokeAction(x_m=float(x)) for x in ctx.rng.uniform(-0.2, 0.2, 3)]


class Unseeded(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return [PokeAction(x_m=float(np.random.default_rng().uniform(-0.2, 0.2)))] if ctx.manipulation_allowed else []


class Idle(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return []


class SweptFloats(PokeAction):
    def swept_volume(self, workspace: Workspace) -> Any:
        return np.zeros(workspace.grid.shape)


class FloatSweep(Poke):
    def propose(self, ctx: Any) -> list[Action]:
        return [SweptFloats(x_m=0.0)] if ctx.manipulation_allowed else []


class ReturnsDict(Poke):
    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Any:
        return {"success": True}


class MeasuresItself(Poke):
    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        out = super().execute(sim, action, ctx)
        out.fell_or_left = [0]
        return out


class RemovesGhost(Poke):
    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        out = super().execute(sim, action, ctx)
        out.removed = [42]
        return out


class OpaqueInfo(Poke):
    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        out = super().execute(sim, action, ctx)
        out.info["sim"] = sim
        return out


class Looks(Poke):
    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        return Outcome(observation=sim.observe(ctx.viewpoints[0]))


class BlindView(ViewSkill):
    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        return Outcome(success=True)


@pytest.mark.parametrize(("skill", "match"), [
    (Glance, r"perception skill's actions must be msmem_core.interfaces.PerceptionAction"),
    (FarView, r"names view 99, outside the 4 viewpoints"),
    (Named, r"kind 'jab'; an action's kind must be the skill's registered name 'poke'"),
    (WrongCategory, r"category 'perception', the skill's is 'manipulation'"),
    (Unserialisable, r"does not survive a JSON round trip"),
    (Lossy, r"changes in a JSON round trip"),
    (Tuple, r"propose must return a list of actions, got a tuple"),
    (Ungated, r"although ctx.manipulation_allowed is false"),
    (Unseeded, r"proposed different actions .* draw every random number from ctx.rng"),
    (Idle, r"proposed nothing on the given belief"),
    (FloatSweep, r"swept_volume\(workspace\) must be a bool mask"),
    (ReturnsDict, r"execute must return a msmem_core.interfaces.Outcome, got a dict"),
    (MeasuresItself, r"leave them empty, MSAS measures them"),
    (RemovesGhost, r"removed names objects that were not in the scene: \[42\]"),
    (OpaqueInfo, r"info must be JSON-serialisable"),
    (Looks, r"a manipulation's outcome must not carry an observation"),
], ids=lambda v: v.__name__ if isinstance(v, type) else "")
def test_a_broken_skill_is_caught_naming_the_rule(skill, match):
    with pytest.raises(ConformanceError, match=match) as e:
        poke_conformance(skill)
    assert str(e.value).startswith("skill 'poke' (")


def test_a_view_skill_whose_outcome_has_no_observation_is_caught():
    with pytest.raises(ConformanceError, match=r"perception action's outcome must carry its Observation"):
        skill_conformance(BlindView, "view", simulator="fake")


class OnACopy(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        return super().predict(belief.copy(), actions, workspace)


class OneShort(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        return super().predict(belief, actions[1:], workspace)


def _edit(fn: Any) -> type[PokeEffect]:
    """A PokeEffect whose first change is passed through ``fn(delta, belief)``."""

    class Edited(PokeEffect):
        def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
            p = super().predict(belief, actions, workspace)
            p.changes[0] = fn(p.changes[0], belief)
            return p

    Edited.__name__ = fn.__name__
    return Edited


def reversed_idx(d: BeliefDelta, b: EvidentialMap) -> BeliefDelta:
    return BeliefDelta(d.idx[::-1], d.alpha[::-1], d.beta[::-1], d.eta[:, ::-1])


def out_of_grid(d: BeliefDelta, b: EvidentialMap) -> BeliefDelta:
    idx = d.idx.copy()
    idx[-1] = b.grid.size
    return BeliefDelta(idx, d.alpha, d.beta, d.eta)


def below_prior(d: BeliefDelta, b: EvidentialMap) -> BeliefDelta:
    return BeliefDelta(d.idx, d.alpha, d.beta * 0.0 + 0.5, d.eta)


def nan_eta(d: BeliefDelta, b: EvidentialMap) -> BeliefDelta:
    eta = d.eta.copy()
    eta[3, 0] = np.nan
    return BeliefDelta(d.idx, d.alpha, d.beta, eta)


def eta_per_voxel(d: BeliefDelta, b: EvidentialMap) -> BeliefDelta:
    return BeliefDelta(d.idx, d.alpha, d.beta, d.eta.T.copy())


def unchanged_listed(d: BeliefDelta, b: EvidentialMap) -> BeliefDelta:
    extra = np.setdiff1d(np.arange(5), d.idx)
    idx = np.concatenate([extra, d.idx])
    c = b.num_classes
    return BeliefDelta(idx, np.concatenate([b.alpha.reshape(-1)[extra], d.alpha]),
                       np.concatenate([b.beta.reshape(-1)[extra], d.beta]),
                       np.concatenate([b.eta.reshape(c, -1)[:, extra], d.eta], axis=1))


def float_idx(d: BeliefDelta, b: EvidentialMap) -> BeliefDelta:
    return BeliefDelta(d.idx.astype(np.float64), d.alpha, d.beta, d.eta)  # type: ignore[arg-type]


class InPlace(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        p = super().predict(belief, actions, workspace)
        belief.beta.reshape(-1)[p.changes[0].idx] = p.changes[0].beta  # writes the prediction into the base
        return p


class StaleMask(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        p = super().predict(belief, actions, workspace)
        p.__dict__["changed"] = np.zeros((len(actions), *belief.grid.shape), dtype=bool)
        return p


class Jittery(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        p = super().predict(belief, actions, workspace)
        d = p.changes[0]
        d.beta += np.float32(np.random.default_rng().uniform(0.1, 1.0))
        return p


class Inert(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        return Prediction.from_beliefs(belief, [belief for _ in actions])


class BadExcluded(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        p = super().predict(belief, actions, workspace)
        p.excluded = [np.zeros(0, np.int64)]
        return p


class FullMaps(PokeEffect):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Any:
        return [self.changes(belief, a).apply(belief) for a in actions]


@pytest.mark.parametrize(("model", "match"), [
    (OnACopy, r"Prediction.base must be the belief predict was given"),
    (OneShort, r"2 changes for 3 actions"),
    (_edit(reversed_idx), r"change 0 \(action 'poke'\): voxel indices must be sorted and unique"),
    (_edit(out_of_grid), r"voxel indices outside the grid"),
    (_edit(below_prior), r"beta falls below the prior 1"),
    (_edit(nan_eta), r"eta is not finite everywhere"),
    (_edit(eta_per_voxel), r"eta has shape \(\d+, 15\), expected \(15, \d+\)"),
    (_edit(unchanged_listed), r"lists 5 voxel\(s\) whose evidence equals the base's"),
    (_edit(float_idx), r"idx must be a 1-D integer array"),
    (InPlace, r"predict modified the belief it was given \(beta"),
    (StaleMask, r"Prediction.changed\[0\] does not match the voxels of change 0"),
    (Jittery, r"predict must be deterministic"),
    (Inert, r"none of the 3 actions changes the belief"),
    (BadExcluded, r"excluded has 1 entries for 3 actions"),
    (FullMaps, r"predict must return a msmem_core.interfaces.Prediction, got a list"),
], ids=lambda v: v.__name__ if isinstance(v, type) else "")
def test_a_broken_effect_model_is_caught_naming_the_rule(model, match):
    with pytest.raises(ConformanceError, match=match) as e:
        poke_effect_conformance(model)
    assert str(e.value).startswith(f"effect model {model.__name__}: ")


# ------------------------------------------------------------------------------------ wrong arguments
@pytest.mark.parametrize(("run", "match"), [
    (lambda: simulator_conformance(ViewSkill()),  # type: ignore[arg-type]
     r"^simulator_conformance expects a factory returning a msmem_core.interfaces.Simulator .*, got a Skill "
     r"\(msmem_view.skill.ViewSkill\)$"),
    (lambda: simulator_conformance(ViewSkill),  # type: ignore[arg-type]
     r"^simulator_conformance expects .*, got the class ViewSkill \(a Skill\)$"),
    (lambda: simulator_conformance(lambda: ViewSkill()),  # type: ignore[arg-type,return-value]
     r"^simulator_conformance expects .*, but the factory returned a Skill \(msmem_view.skill.ViewSkill\)$"),
    (lambda: simulator_conformance(FakeSimulator()),  # type: ignore[arg-type]
     r"^simulator_conformance expects .*, got a Simulator \(msmem_core.testing.fake.FakeSimulator\) itself: pass a "
     r"factory"),
    (lambda: simulator_conformance(3),  # type: ignore[arg-type]
     r"^simulator_conformance expects .*, got a int$"),
    (lambda: skill_conformance(FakeSimulator, "fake"),  # type: ignore[arg-type]
     r"^skill_conformance expects a factory returning a msmem_core.interfaces.Skill .*, got the class FakeSimulator "
     r"\(a Simulator\)$"),
    (lambda: skill_conformance(lambda: PokeEffect(), "poke"),  # type: ignore[arg-type,return-value]
     r"^skill_conformance expects .*, but the factory returned a EffectModel \(test_conformance.PokeEffect\)$"),
    (lambda: skill_conformance(Poke),
     r"^skill_conformance needs the skill's registered name"),
    (lambda: effect_model_conformance(Poke, lambda ctx: []),  # type: ignore[arg-type]
     r"^effect_model_conformance expects a factory returning a msmem_core.interfaces.EffectModel .*, got the class "
     r"Poke \(a Skill\)$"),
    (lambda: effect_model_conformance("analytic-observation", lambda ctx: []),
     r"^effect_model_conformance expects .*, but the factory returned a ObservationModel "),
    (lambda: effect_model_conformance(PokeEffect, Poke()),  # type: ignore[arg-type]
     r"^effect_model_conformance expects actions_for= a function of the DecisionContext returning actions, got a "
     r"Skill"),
    (lambda: effect_model_conformance(PokeEffect, lambda ctx: [], belief=EvidentialMap.empty(WS.grid)),
     r"^effect_model_conformance: actions_for returned no actions"),
], ids=["sim<-skill", "sim<-skill-class", "sim<-skill-factory", "sim<-instance", "sim<-int", "skill<-sim-class",
        "skill<-effect-factory", "skill-without-name", "effect<-skill-class", "effect<-observation-model",
        "effect<-actions-not-callable", "effect<-no-actions"])
def test_every_suite_refuses_the_wrong_kind_of_argument_in_one_line(run, match):
    with pytest.raises(ConformanceUsageError, match=match) as e:
        run()
    assert "\n" not in str(e.value)
    assert isinstance(e.value, TypeError)


# ------------------------------------------------------------------------------------------ builders
def test_belief_with_boxes_is_confident_inside_and_free_or_prior_elsewhere():
    box = ((-0.06, 0.02, 0.0), (0.06, 0.08, 0.08), CAN)  # faces between voxel centres (odd centimetres)
    b = belief_with_boxes(WS.grid, [box])
    c = WS.grid.centers()
    inside = np.all((c > box[0]) & (c < box[1]), axis=-1)
    assert inside.sum() == 6 * 3 * 4  # the 2 cm voxels whose centres are inside
    p = b.expected_occupancy()
    assert np.all(p[inside] > 0.95)
    assert np.all(p[~inside] < 0.05)
    assert np.all(np.argmax(b.eta, axis=0)[inside] == CAN)
    assert np.all(b.vacuity()[~inside] < 0.5)
    prior = belief_with_boxes(WS.grid, [box], free="none")
    assert np.all(prior.expected_occupancy()[~inside] == 0.5)
    above = belief_with_boxes(WS.grid, [box], free=[((-0.06, 0.02, 0.0), (0.06, 0.08, 0.28))])
    free = above.expected_occupancy() < 0.05
    assert free.sum() == 6 * 3 * 10
    assert not (free & inside).any()  # the object's voxels stay the object's
    with pytest.raises(ValueError, match="class id 0"):
        belief_with_boxes(WS.grid, [((0, 0, 0), (0.1, 0.1, 0.1), 0)])


def test_belief_of_scene_knows_the_objects_and_only_the_known_region(known, front):
    p = known.expected_occupancy()
    assert 0 < (p > 0.5).sum() < 0.1 * WS.grid.size
    assert not np.any(p == 0.5)
    hidden = front.expected_occupancy() == 0.5
    assert hidden.any()
    assert np.all(WS.grid.centers()[hidden][:, 1] > 0.15)


def test_decision_context_is_valid_and_checks_its_grids():
    ctx = decision_context(step=4, manipulation_allowed=False, seed=3)
    assert isinstance(ctx, DecisionContext)
    assert (ctx.step, ctx.manipulation_allowed, ctx.visited) == (4, False, {0})
    assert ctx.viewpoints.shape == (4, 4, 4)
    assert ctx.field is not None  # the IG service accepts the belief
    assert ctx.rng.integers(1000) == np.random.default_rng(3).integers(1000)
    with pytest.raises(ValueError, match="belief's grid differs"):
        decision_context(EvidentialMap.empty(default_workspace(0.01).grid), workspace=WS)
    with pytest.raises(ValueError, match="IG service's grid differs"):
        decision_context(EvidentialMap.empty(WS.grid), ig=small_ig(default_workspace(0.01)))


class Prefer(Term):
    """Manipulations score ``manipulation``, views 1."""

    def __init__(self, manipulation: float) -> None:
        self.manipulation = manipulation

    def score(self, ctx: Any, batch: CandidateBatch) -> np.ndarray:
        return np.full(len(batch.actions), self.manipulation if batch.category == "manipulation" else 1.0)


def test_one_decision_runs_msas_with_your_skill():
    skills = [("view", ViewSkill()), ("poke", Poke(), PokeEffect())]
    d = one_decision(skills, objective=Prefer(10.0))
    assert (d.skill.name, d.candidates) == ("poke", {"view": 3, "poke": 3})
    assert isinstance(d.action, PokeAction)
    assert len(d.batch.prediction) == 3  # type: ignore[arg-type]
    assert one_decision(skills, objective=Prefer(0.5)).skill.name == "view"
    held_back = one_decision(skills, objective=Prefer(10.0), manipulation_allowed=False)
    assert held_back.skill.name == "view"
    assert "poke" not in held_back.candidates
    ig = one_decision([BoundSkill("view", ViewSkill())], belief_with_boxes(WS.grid, [], free="none"))
    assert ig.terms.keys() == {"ig"}  # the default objective: the built-in ig term
    assert ig.value > 0
    assert isinstance(ig.action, PerceptionAction)


def test_one_decision_names_what_is_missing():
    with pytest.raises(TypeError, match="manipulation skill 'poke' needs an EffectModel"):
        one_decision([("poke", Poke())])
    with pytest.raises(TypeError, match="each skill must be a BoundSkill, or a"):
        one_decision([Poke()])  # type: ignore[list-item]

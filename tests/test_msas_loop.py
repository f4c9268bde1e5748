"""The loop's contracts with its plugins, on the fake simulator and toy skills: MSAS measures what a
manipulation moved and what fell or left (once, for every skill), a tracer sees every stage of a
decision in order, and a perception action must name its view."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import numpy as np
import pytest
from msmem_view.skill import ViewSkill
from numpy.typing import NDArray

from msmem_core.config import MSASConfig
from msmem_core.errors import PluginError
from msmem_core.interfaces import (
    Action,
    CandidateBatch,
    Category,
    DecisionContext,
    EffectModel,
    ObservationModel,
    Outcome,
    Prediction,
    Simulator,
    Skill,
    Term,
    Workspace,
)
from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_core.map.ig import IGService
from msmem_core.msas import BoundSkill, Decision, Objective, decide, run_msas
from msmem_core.testing import FakeSimulator
from msmem_core.util.trace import Span, Tracer, active_tracer, span
from msmem_core.world.camera import CameraConfig, Observation
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ObjectSpec, SceneSpec, ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

SHELF = ShelfSpec()
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.02)
WORKSPACE = Workspace(GRID, SHELF)
CAMERA = CameraConfig(width_px=32, height_px=24)
SCENE = SceneSpec(name="two", objects=(
    ObjectSpec(id=0, class_name="sugar_box", position_m=(-0.1, 0.15, 0.0)),
    ObjectSpec(id=1, class_name="tomato_soup_can", position_m=(0.1, 0.15, 0.0)),
))


# ------------------------------------------------------------------------------------------ toy plugins
class ToppleAction(Action):
    kind: str = "topple"
    category: Literal["manipulation"] = "manipulation"


class ToppleSkill(Skill):
    """Tips object 0 over and slides object 1 by 3 cm in the fake simulator; reports only success."""

    category: ClassVar[Category] = "manipulation"

    def propose(self, ctx: Any) -> list[Action]:
        return [ToppleAction(target_object=0)] if ctx.manipulation_allowed else []

    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        assert isinstance(sim, FakeSimulator)
        tip = np.eye(4)
        tip[1:3, 1:3] = [[0.0, -1.0], [1.0, 0.0]]  # 90 degrees about x
        sim.poses[0] = sim.poses[0] @ tip
        sim.poses[1][0, 3] += 0.03
        return Outcome(success=True, info={"toppled": 0})


class NoChange(EffectModel):
    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        empty = BeliefDelta(np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32),
                            np.zeros((belief.num_classes, 0), np.float32))
        return Prediction(belief, [empty for _ in actions])


class Glance(Skill):
    """A perception skill whose actions do not say where they look from."""

    def propose(self, ctx: Any) -> list[Action]:
        return [Action(kind="glance", category="perception")]

    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        raise AssertionError("never executed")


class KeepBelief(ObservationModel):
    def update(self, belief: EvidentialMap, observation: Observation) -> EvidentialMap:
        return belief


class Constant(Term):
    """Manipulations score 100, views 1 (after touching the IG field, so its span nests here)."""

    def score(self, ctx: Any, batch: CandidateBatch) -> np.ndarray:
        assert ctx.field is not None
        return np.full(len(batch.actions), 100.0 if batch.category == "manipulation" else 1.0)


@pytest.fixture(scope="module")
def ig() -> IGService:
    views = generate_viewpoints(ViewpointConfig(targets_x_m=(0.0,), grid=2), SHELF)
    return IGService(GRID, CAMERA, views, SHELF)


def skills() -> list[BoundSkill]:
    return [BoundSkill("view", ViewSkill()), BoundSkill("topple", ToppleSkill(), NoChange())]


def run(ig: IGService, steps: int, tracer: Tracer | None = None) -> list[tuple[int, Decision, Outcome]]:
    sim = FakeSimulator(CAMERA)
    sim.reset(SCENE)
    out: list[tuple[int, Decision, Outcome]] = []
    cfg = MSASConfig(manipulation_window=(0, 10), mapped_fraction=1.0)
    run_msas(sim, KeepBelief(), skills(), Objective([("constant", 1.0, Constant())]), ig, WORKSPACE, cfg, steps,
             start_view=0, seed=0, on_step=lambda step, d, o, b: out.append((step, d, o)), tracer=tracer)
    return out


# -------------------------------------------------------------------------------------------- tests
def test_the_loop_measures_what_a_manipulation_moved_and_what_fell_for_a_skill_that_does_not(ig):
    steps = run(ig, 4)
    assert [d.skill.name for _, d, _ in steps] == ["topple", "view", "view", "view"]
    _, first, outcome = steps[0]
    assert first.skill.skill.__class__ is ToppleSkill  # the decision carries its bound skill
    assert outcome.fell_or_left == [0], "the tipped object fell over"
    assert outcome.displacement_m[1] == pytest.approx(0.03)
    assert outcome.displacement_m[0] == pytest.approx(0.0)
    assert outcome.info == {"toppled": 0, "moved": [1]}
    # after it, only views: the manipulation's associated view, then none since an object fell
    assert all("topple" not in d.candidates for _, d, _ in steps[1:])
    for _, _, o in steps[1:]:
        assert o.fell_or_left == []
        assert o.displacement_m == {}  # perception actions are not measured


def test_a_tracer_sees_every_stage_of_a_step_in_order(ig):
    events: list[tuple[str, str, str | None]] = []
    spans: dict[str, Span] = {}

    class Recorder(Tracer):
        def begin(self, s: Span) -> None:
            events.append(("begin", s.stage, s.skill))

        def end(self, s: Span) -> None:
            events.append(("end", s.stage, s.skill))
            spans.setdefault(s.stage, s)

    ((_, decision, outcome),) = run(ig, 1, Recorder())
    core = [e for e in events if e[1] in ("decide", "track", "propose", "predict", "score", "term", "execute")]
    assert core == [
        ("begin", "decide", None),
        ("begin", "track", "view"), ("end", "track", "view"),
        ("begin", "propose", "view"), ("end", "propose", "view"),
        ("begin", "score", "view"), ("begin", "term", "view"), ("end", "term", "view"), ("end", "score", "view"),
        ("begin", "track", "topple"), ("end", "track", "topple"),
        ("begin", "propose", "topple"), ("end", "propose", "topple"),
        ("begin", "predict", "topple"), ("end", "predict", "topple"),
        ("begin", "score", "topple"), ("begin", "term", "topple"), ("end", "term", "topple"),
        ("end", "score", "topple"),
        ("end", "decide", None),
        ("begin", "execute", "topple"), ("end", "execute", "topple"),
    ]
    # the IG service's own stage nests inside the term that first needed the field
    i = events.index(("begin", "ig.prepare", None))
    assert events[i - 1] == ("begin", "term", "view")
    assert spans["decide"].result is decision
    assert spans["execute"].result is outcome
    assert isinstance(spans["predict"].result, Prediction)
    assert len(spans["propose"].result) == decision.candidates["view"] == len(ig.viewpoints) - 1  # not the start
    assert spans["score"].info["batch"].skill == "view"
    assert active_tracer() is None  # reported only while the loop runs


def test_without_a_tracer_spans_cost_nothing_but_a_lookup():
    assert active_tracer() is None
    with span("anything", skill="x", payload=object()) as s:
        assert s is None


def test_a_perception_action_without_a_view_index_is_refused_naming_the_skill(ig):
    ctx = DecisionContext(0, EvidentialMap.empty(GRID), ig, ig.viewpoints, set(), WORKSPACE,
                          np.random.default_rng(0), False, 0.5)
    objective = Objective([("constant", 1.0, Constant())])
    with pytest.raises(PluginError, match=r"perception skill 'glance' proposed a Action \('glance'\) without a view"
                                          r"(.|\n)*category = \"manipulation\""):  # says how to make it one
        decide(ctx, [BoundSkill("glance", Glance())], objective)


def test_an_effect_model_must_predict_from_the_belief_it_was_given(ig):
    class Elsewhere(NoChange):
        def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
            return super().predict(belief.copy(), actions, workspace)

    ctx = DecisionContext(3, EvidentialMap.empty(GRID), ig, ig.viewpoints, set(), WORKSPACE,
                          np.random.default_rng(0), True, 0.5)
    objective = Objective([("constant", 1.0, Constant())])
    with pytest.raises(PluginError, match="effect model of skill 'topple'"):
        decide(ctx, [BoundSkill("topple", ToppleSkill(), Elsewhere())], objective)


class Flaky(ToppleSkill):
    """Does nothing in the world and reports ``success`` as told."""

    def __init__(self, success: bool) -> None:
        self.success = success

    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        return Outcome(success=self.success)


class Stamp(EffectModel):
    """Predicts the first 10 voxels certainly free (what a successful grasp of an object there would do)."""

    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        idx = np.arange(10, dtype=np.int64)
        n = belief.num_classes
        delta = BeliefDelta(idx, np.ones(10, np.float32), np.full(10, 60.0, np.float32), np.ones((n, 10), np.float32))
        return Prediction(belief, [delta for _ in actions])


class Sure(ObservationModel):
    """Every view makes every voxel confidently occupied (alpha 30, beta 2)."""

    def update(self, belief: EvidentialMap, observation: Observation) -> EvidentialMap:
        return EvidentialMap(belief.grid, np.full_like(belief.alpha, 30.0), np.full_like(belief.beta, 2.0),
                             belief.eta.copy())


@pytest.mark.parametrize("success", [True, False])
def test_a_failed_manipulation_does_not_write_the_prediction_of_success(ig, success):
    sim = FakeSimulator(CAMERA)
    sim.reset(SCENE)
    beliefs: list[EvidentialMap] = []
    cfg = MSASConfig(manipulation_window=(0, 10), mapped_fraction=1.0, disturbed_margin_voxels=0,
                     disturbed_evidence_cap=None)
    run_msas(sim, Sure(), [BoundSkill("view", ViewSkill()), BoundSkill("flaky", Flaky(success), Stamp())],
             Objective([("constant", 1.0, Constant())]), ig, WORKSPACE, cfg, 1, start_view=0, seed=0,
             on_step=lambda step, d, o, b: beliefs.append(b))
    after = beliefs[0]
    a, b = after.alpha.ravel(), after.beta.ravel()
    if success:  # the prediction, as is (no disturbed cap configured)
        assert np.all(b[:10] == 60.0)
        assert np.all(a[:10] == 1.0)
    else:  # the belief before, its evidence shrunk to alpha + beta <= 4 where the prediction would have changed it
        assert np.allclose(a[:10] + b[:10], cfg.failed_manipulation_cap)
        assert np.all(a[:10] > b[:10]), "still believed occupied: only the confidence is gone"
        assert np.all(a[10:] == 30.0)
        assert np.all(b[10:] == 2.0)


class Told(Sure):
    """``Sure``, recording what MSAS tells it about disturbed regions."""

    def __init__(self) -> None:
        self.told: list[tuple[np.ndarray, float]] = []

    def disturbed(self, region: np.ndarray, cap: float) -> None:
        self.told.append((region.copy(), cap))


@pytest.mark.parametrize("success", [True, False])
def test_the_observation_model_is_told_the_region_msas_capped(ig, success):
    """After a manipulation MSAS caps the belief where the prediction changed it (dilated) and tells the
    observation model the same region and cap, so that evidence the model keeps of its own (a ray
    record) is capped there too."""
    sim = FakeSimulator(CAMERA)
    sim.reset(SCENE)
    beliefs: list[EvidentialMap] = []
    model = Told()
    cfg = MSASConfig(manipulation_window=(0, 10), mapped_fraction=1.0, disturbed_margin_voxels=1,
                     disturbed_evidence_cap=5.0, failed_manipulation_cap=3.0)
    run_msas(sim, model, [BoundSkill("view", ViewSkill()), BoundSkill("flaky", Flaky(success), Stamp())],
             Objective([("constant", 1.0, Constant())]), ig, WORKSPACE, cfg, 1, start_view=0, seed=0,
             on_step=lambda step, d, o, b: beliefs.append(b))
    assert len(model.told) == 1
    region, cap = model.told[0]
    assert cap == (5.0 if success else 3.0)
    assert region.reshape(-1)[:10].all()  # Stamp's voxels
    assert region.sum() > 10  # dilated by the margin
    after = beliefs[0]
    capped = (after.alpha + after.beta) <= cap + 1e-5
    assert np.array_equal(capped, region)  # Sure's evidence (32) everywhere else


class ToldApart(Told):
    """``Told``, with ``failed_manipulation`` recorded apart."""

    def __init__(self) -> None:
        super().__init__()
        self.failed: list[tuple[np.ndarray, float]] = []

    def failed_manipulation(self, region: np.ndarray, cap: float) -> None:
        self.failed.append((region.copy(), cap))


@pytest.mark.parametrize("success", [True, False])
def test_a_failed_manipulation_is_told_as_such_and_old_models_hear_it_as_disturbed(ig, success):
    """After a manipulation that reported failure MSAS calls ``failed_manipulation`` (after a success,
    ``disturbed``); a model that implements only ``disturbed`` is told through it either way."""
    cfg = MSASConfig(manipulation_window=(0, 10), mapped_fraction=1.0, disturbed_evidence_cap=5.0,
                     failed_manipulation_cap=3.0)
    skills = [BoundSkill("view", ViewSkill()), BoundSkill("flaky", Flaky(success), Stamp())]
    apart, old = ToldApart(), Told()
    for model in (apart, old):
        sim = FakeSimulator(CAMERA)
        sim.reset(SCENE)
        run_msas(sim, model, skills, Objective([("constant", 1.0, Constant())]), ig, WORKSPACE, cfg, 1,
                 start_view=0, seed=0, on_step=lambda step, d, o, b: None)
    assert (len(apart.told), len(apart.failed)) == ((1, 0) if success else (0, 1))
    assert len(old.told) == 1
    assert old.told[0][1] == (5.0 if success else 3.0)
    told = (apart.told if success else apart.failed)[0]
    assert np.array_equal(told[0], old.told[0][0])
    assert told[1] == old.told[0][1]


def test_an_episode_counts_its_falls_and_the_bench_table_reads_them(tmp_path):
    """run_episode counts the manipulations after which an object fell or left; the bench turns them
    into ``falls`` and ``fell`` (NaN for an episode that never manipulated)."""
    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.bench import episode_metrics
    from msmem_core.run.runner import build_episode, run_episode

    over = {"steps": 3, "camera": {"width_px": 32, "height_px": 24}, "ig": {"ray_stride_px": 4},
            "msas": {"manipulation_window": [0, 10], "mapped_fraction": 1.0}}
    ep = build_episode(load_config("view-only", None, over), get_plugin_manager(), scene=SCENE)
    ep.sim = FakeSimulator(ep.cfg.camera)
    ep.skills = [*ep.skills, BoundSkill("topple", ToppleSkill(), NoChange())]
    ep.objective = Objective([("constant", 1.0, Constant())])
    final = run_episode(ep, tmp_path)
    assert [r["skill"] for r in ep.records] == ["topple", "view", "view"]
    assert final["falls"] == 1
    skills = {b.name: b.skill.category for b in ep.skills}
    m = episode_metrics(final, ep.records, skills)
    assert (m["falls"], m["fell"], m["topples"], m["views"], m["topple_success"]) == (1, 1.0, 1, 2, 1.0)
    assert "pushes" not in m  # a column per skill of the method, whatever its name
    assert "view_success" not in m  # success shares of manipulation skills only
    viewing = [{**r, "skill": "view", "fell_or_left": []} for r in ep.records]
    assert np.isnan(episode_metrics({**final, "falls": 0}, viewing, skills)["fell"])  # never manipulated
    assert episode_metrics({**final, "falls": 0}, ep.records, skills)["fell"] == 0.0


class _Fixed(Term):
    """Scores a batch's candidates with fixed values."""

    applies_to: ClassVar[frozenset[Category]] = frozenset({"manipulation"})

    def __init__(self, values: list[float]) -> None:
        self.values = np.asarray(values, dtype=np.float64)

    def score(self, ctx: DecisionContext, batch: CandidateBatch) -> NDArray[np.float64]:
        return self.values.copy()


def test_best_skips_refused_argmaxes_and_does_not_ask_about_one_that_cannot_win() -> None:
    """``Objective.best`` with ``admissible``: a refused argmax is left out and the next one taken; with
    ``stop_at``, an argmax at most that value is returned without asking; all refused gives None."""
    objective = Objective([("fixed", 1.0, _Fixed([3.0, 5.0, 1.0, 4.0]))])
    batch = CandidateBatch("push", "manipulation", [None] * 4)  # type: ignore[list-item]
    asked: list[int] = []

    def not_1(i: int) -> bool:
        asked.append(i)
        return i != 1

    def best(**kw: Any) -> Any:
        asked.clear()
        return objective.best(None, batch, **kw)  # type: ignore[arg-type]

    assert best(admissible=not_1)[:2] == (3, 4.0)
    assert asked == [1, 3]
    assert best(admissible=not_1, stop_at=4.5)[:2] == (3, 4.0)
    assert asked == [1], "an argmax at most stop_at cannot win: it is not asked about"
    assert best(admissible=not_1, stop_at=6.0)[:2] == (1, 5.0)
    assert asked == []
    assert best(admissible=lambda i: asked.append(i) or False) is None
    assert sorted(asked) == [0, 1, 2, 3]
    assert best()[:2] == (1, 5.0)


def test_a_run_without_a_manipulation_skill_never_allows_manipulation(ig):
    seen: list[bool] = []

    class Spy(Term):
        def score(self, ctx: Any, batch: CandidateBatch) -> np.ndarray:
            seen.append(ctx.manipulation_allowed)
            return np.ones(len(batch.actions))

    cfg = MSASConfig(manipulation_window=(0, 10), mapped_fraction=1.0)
    for bound, allowed in (([BoundSkill("view", ViewSkill())], False), (skills(), True)):
        seen.clear()
        sim = FakeSimulator(CAMERA)
        sim.reset(SCENE)
        run_msas(sim, KeepBelief(), bound, Objective([("spy", 1.0, Spy())]), ig, WORKSPACE, cfg, 3,
                 start_view=0, seed=0, on_step=lambda *a: None)
        # inside the window every step allows manipulation, if the run has a skill to manipulate with
        assert len(seen) >= 3
        assert set(seen) == {allowed}

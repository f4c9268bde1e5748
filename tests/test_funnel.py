"""The candidate funnel: every skill asked at a step reports how many candidates each stage of its
proposal left (``interfaces.Funnel``), MSAS adds its own stages, the step records keep them and the
bench sums them; a skill of its own reports its own stages."""

from __future__ import annotations

import itertools
from typing import Any, ClassVar, Literal

import pytest
from msmem_view.skill import ViewSkill

from msmem_core.interfaces import Action, Category, Outcome, Simulator, Skill
from msmem_core.run.bench import summarise, table_markdown
from msmem_core.run.funnel import funnel_counts, sum_funnels
from msmem_core.testing.builders import belief_with_boxes, decision_context, default_workspace, one_decision
from tests.test_msas_loop import NoChange

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class SieveAction(Action):
    kind: str = "sieve"
    category: Literal["manipulation"] = "manipulation"
    size: int


class Sieve(Skill):
    """A skill of its own: draws 10 candidates, keeps the even ones, then those under 6."""

    category: ClassVar[Category] = "manipulation"

    def propose(self, ctx: Any) -> list[Action]:
        drawn = list(range(10))
        even = [n for n in drawn if n % 2 == 0]
        small = [n for n in even if n < 6]
        for stage, kept in (("drawn", drawn), ("even", even), ("small", small)):
            ctx.funnel.count(stage, len(kept))
        return [SieveAction(size=n) for n in small]

    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        raise AssertionError("never executed")


def test_a_skill_of_its_own_reports_its_stages_and_msas_adds_proposed_and_chosen() -> None:
    belief = belief_with_boxes(default_workspace().grid, [((-0.1, 0.1, 0.0), (0.0, 0.2, 0.1), 2)])
    d = one_decision([("view", ViewSkill()), ("sieve", Sieve(), NoChange())], belief)
    assert list(d.funnel["sieve"]) == ["drawn", "even", "small", "proposed", "chosen"]
    assert d.funnel["sieve"] == {"drawn": 10, "even": 5, "small": 3, "proposed": 3,
                                 "chosen": int(d.skill.name == "sieve")}
    assert d.funnel["view"]["proposed"] == d.candidates["view"]
    assert sum(f["chosen"] for f in d.funnel.values()) == 1
    # not asked while manipulation is not allowed: no entry, as in the step records
    d = one_decision([("view", ViewSkill()), ("sieve", Sieve(), NoChange())], belief, manipulation_allowed=False)
    assert set(d.funnel) == {"view"}


def test_a_negative_count_is_refused_naming_the_stage_and_the_skill() -> None:
    ctx = decision_context(None, 1)
    ctx.funnel.skill = "mine"
    with pytest.raises(ValueError, match="stage 'kept' of skill 'mine'"):
        ctx.funnel.count("kept", -1)


def _non_increasing(stages: dict[str, int]) -> bool:
    """Each count at most the one before, but at a stage that adds candidates (the grasp skill's
    ``turned``: its twins), which at least keeps them."""
    pairs = itertools.pairwise(stages.items())
    return all(a >= b if k != "turned" else a <= b for (_, a), (k, b) in pairs)


@pytest.mark.slow  # about 20 s
def test_a_pybullet_episode_records_a_consistent_funnel_for_every_skill(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``ours`` (view, push, grasp; the analytic models) for 5 steps on a generated scene, manipulation
    allowed from step 1: every step's funnel holds the skills asked, in stage order, each count at
    most the one before, ``proposed`` as in ``candidates`` and one skill chosen, the one that acted."""
    import json

    from msmem_core.config import deep_merge, load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import build_episode, run_episode
    from tests.support.defaults import ANALYTIC

    over = {"steps": 5, "scene": {"seed": 3}, "msas": {"manipulation_window": [1, 38]}, "report_steps": []}
    ep = build_episode(load_config("ours", None, deep_merge(over, ANALYTIC)), get_plugin_manager())
    run_episode(ep, tmp_path)
    records = [json.loads(line) for line in (tmp_path / "steps.jsonl").read_text().splitlines()]
    assert len(records) == 5
    manipulation_asked = 0
    for r in records:
        funnel = r["funnel"]
        assert "view" in funnel
        assert set(funnel) == set(r["candidates"])
        for skill, stages in funnel.items():
            assert _non_increasing(stages), (r["step"], skill, stages)
            assert stages["proposed"] == r["candidates"][skill]
            assert stages["chosen"] == int(skill == r["skill"])
        manipulation_asked += "grasp" in funnel
        if "grasp" in funnel:
            assert "push" in funnel
            assert list(funnel["grasp"])[:2] == ["fused", "confident"]
            assert list(funnel["grasp"])[-3:] == ["clear_exit", "proposed", "chosen"]
            assert list(funnel["push"]) == ["drawn", "in_shelf", "collision_free", "proposed", "chosen"]
    assert manipulation_asked >= 2  # steps 1-4, less the one right after a manipulation
    assert records[0]["funnel"].keys() == {"view"}  # step 0: before the manipulation window
    # the bench's sums over the episode
    counts = funnel_counts(records)
    assert counts["view"]["asked"] == 5
    assert counts["grasp"]["asked"] == manipulation_asked
    assert counts["grasp"]["with_candidates"] == sum(r["funnel"].get("grasp", {}).get("proposed", 0) > 0
                                                     for r in records)
    assert sum(c["chosen"] for c in counts.values()) == 5


def test_the_bench_sums_the_funnel_per_method_and_reports_it() -> None:
    def step(proposed: int, chosen: int) -> dict[str, Any]:
        return {"funnel": {"view": {"proposed": 3, "chosen": 1 - chosen},
                           "grasp": {"fused": 9, "clear_exit": proposed, "proposed": proposed, "chosen": chosen}}}

    def episode(scene: int, steps: list[dict[str, Any]]) -> dict[str, Any]:
        from msmem_core.run.bench import COUNT_METRICS, TABLE_METRICS

        metrics = {k: 0.5 for k, _, _ in TABLE_METRICS} | {k: 1 for k, _ in COUNT_METRICS}
        return {"method": "grasp-only", "scene_index": scene, "status": "ok", "metrics": metrics,
                "funnel": funnel_counts(steps)}

    eps = [episode(0, [step(0, 0), step(2, 1), {"funnel": {"view": {"proposed": 3, "chosen": 1}}}]),
           episode(1, [step(0, 0), step(0, 0)])]
    f = summarise(eps, ["grasp-only"])["table"]["grasp-only"]["funnel"]
    assert f["grasp"] == {"episodes": 2, "asked": 4, "with_candidates": 1, "chosen": 1,
                          "stages": {"fused": 36, "clear_exit": 2, "proposed": 2, "chosen": 1}}
    assert f["view"]["asked"] == 5
    assert f["view"]["chosen"] == 4
    assert sum_funnels([]) == {}
    md = table_markdown(summarise(eps, ["grasp-only"]))
    assert "## Candidate funnel" in md
    assert "| grasp-only | grasp | 2 | 1 / 4 (25%) | 1 | fused 36 → clear_exit 2 → proposed 2 |" in md
    older = [{k: v for k, v in e.items() if k != "funnel"} for e in eps]  # results written before the funnel
    assert "Candidate funnel" not in table_markdown(summarise(older, ["grasp-only"]))


@pytest.mark.parametrize(("top_k", "max_per_object"), [(2, 4), (40, 1), (3, 2)])
def test_the_grasp_funnel_counts_every_candidate_past_top_k_when_asked(top_k: int, max_per_object: int) -> None:
    """With ``funnel: every-candidate`` the stages are counted over every candidate, so ``clear_exit`` can
    exceed what ``top_k`` and ``max_per_object`` let through to ``proposed``; by default the tests stop
    once nothing more would be proposed, and the proposals are the same."""
    from msmem_grasp.skill import FUNNEL_STAGES, GraspConfig, GraspSkill

    from tests.test_grasp import BYSTANDER, TARGET, box_belief, ctx

    got = {}
    for funnel in ("every-candidate", "until-full"):
        c = ctx(box_belief([TARGET, BYSTANDER]))
        c.funnel.skill = "grasp"
        skill = GraspSkill(GraspConfig(predictor="geometric", top_k=top_k, max_per_object=max_per_object,
                                       funnel=funnel))  # type: ignore[arg-type]
        got[funnel] = (skill.propose(c), c.funnel.stages("grasp"))
    (out, every), (same, until) = got["every-candidate"], got["until-full"]
    assert same == out
    assert 0 < len(out) <= top_k
    for stages in (every, until):
        assert list(stages) == list(FUNNEL_STAGES)
        assert _non_increasing(stages)
    assert len(out) < every["clear_exit"]
    assert until["clear_exit"] == len(out)  # every candidate tested was proposed: nothing was left over
    assert until["collision_free"] < every["collision_free"]
    assert {k: until[k] for k in FUNNEL_STAGES[:7]} == {k: every[k] for k in FUNNEL_STAGES[:7]}
    assert every["turned"] > every["preselected"]  # the default turns grasps to the front and the sides

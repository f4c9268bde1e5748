"""Predicted IG against realised map gains (``msmem_core.run.tracking``)."""

from __future__ import annotations

import math

from msmem_core.run.tracking import skill_categories, spearman, step_rows, tracking_summary


def _episode() -> dict:
    occ = [0.50, 0.60, 0.55, 0.70, 0.72]
    sem = [0.30, 0.40, 0.35, 0.52, 0.50]
    return {"method": "ours", "scene_index": 3, "skills": ["view", "view", "grasp", "view", "view"],
            "terms": [{"ig": 9.0}, {"ig": 5.0}, {"ig": 7.0, "cdc": -1.0}, {"ig": 4.0}, {"ig": 1.0}],
            "curves": {"occupancy_miou": occ, "semantic_miou_2d": sem}}


def test_a_manipulation_is_credited_with_its_associated_view() -> None:
    rows = step_rows(_episode())
    assert [(r["step"], r["kind"]) for r in rows] == [(1, "view"), (2, "manipulation"), (4, "view")]
    grasp = rows[1]
    assert math.isclose(grasp["d_occupancy_miou"], 0.70 - 0.60)  # over the grasp and its view
    assert math.isclose(grasp["d_semantic_miou_2d"], 0.52 - 0.40)
    assert math.isclose(rows[2]["d_semantic_miou_2d"], 0.50 - 0.52)
    assert step_rows({**_episode(), "terms": None}) == []  # files without terms give nothing


def test_rank_correlation_and_summary() -> None:
    assert math.isclose(spearman([1, 2, 3, 4], [10, 20, 30, 40]), 1.0)
    assert math.isclose(spearman([1, 2, 3, 4], [4, 3, 2, 1]), -1.0)
    assert math.isnan(spearman([1, 2], [1, 2]))
    s = {(r["kind"]): r for r in tracking_summary(step_rows(_episode()))}
    assert s["all"]["decisions"] == 3
    assert s["view"]["decisions"] == 2
    assert math.isclose(s["all"]["rho_semantic_miou_2d"], 1.0)  # ig 5, 7, 4 and gains .10, .12, -.02 rank alike


def test_the_kind_of_a_step_is_its_skills_category_whatever_its_name() -> None:
    """An episode file names each skill's category (``skill_categories``): an outside perception skill's
    steps are views, an outside manipulation skill's are manipulations; a file without them takes the
    categories the registered skills declare."""
    ep = {**_episode(), "skills": ["look", "look", "nudge", "look", "look"],
          "skill_categories": {"look": "perception", "nudge": "manipulation"}}
    assert [(r["step"], r["kind"], r["skill"]) for r in step_rows(ep)] == [
        (1, "view", "look"), (2, "manipulation", "nudge"), (4, "view", "look")]
    assert skill_categories(_episode()) == {"view": "perception", "grasp": "manipulation"}

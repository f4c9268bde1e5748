"""The generated results page's comparisons (``msmem_core.run.results``)."""

from __future__ import annotations

import json
from pathlib import Path

from msmem_core.run.results import same_episodes
from msmem_core.run.tracking import load_episodes

TABLE1 = Path(__file__).resolve().parents[1] / "docs" / "results" / "table1"


def _write(folder: Path, method: str, scene: int, skills: list[str], sem: list[float]) -> None:
    (folder / "episodes").mkdir(parents=True, exist_ok=True)
    episode = {"method": method, "scene_index": scene, "status": "ok", "skills": skills,
               "curves": {"occupancy_miou": [0.8] * len(sem), "semantic_miou_2d": sem}}
    (folder / "episodes" / f"{method}__scene{scene:02d}.json").write_text(json.dumps(episode))


def test_same_episodes_need_the_same_skills_and_the_same_metrics_at_every_step(tmp_path: Path) -> None:
    grasp = ["view", "grasp", "view"]
    _write(tmp_path, "grasp-only", 0, grasp, [0.5, 0.6, 0.7])
    _write(tmp_path, "ours", 0, grasp, [0.5, 0.6, 0.7])  # the same episode
    _write(tmp_path, "grasp-only", 1, grasp, [0.5, 0.6, 0.7])
    _write(tmp_path, "ours", 1, grasp, [0.5, 0.6, 0.71])  # another grasp: the same skills, other metrics
    _write(tmp_path, "grasp-only", 2, grasp, [0.5, 0.6, 0.7])
    _write(tmp_path, "ours", 2, ["view", "push", "view"], [0.5, 0.6, 0.7])  # another skill
    _write(tmp_path, "grasp-only", 3, grasp, [0.5, 0.6, 0.7])  # ours did not run scene 3
    same = same_episodes(load_episodes(tmp_path), [0, 1, 2, 3])
    assert same[("ours", "grasp-only")] == [0]
    assert same[("grasp-only", "ours")] == [0]
    assert same[("grasp-only", "grasp-only")] == [0, 1, 2, 3]


def test_on_the_committed_table_the_same_episodes_end_alike_and_the_others_differ() -> None:
    episodes = load_episodes(TABLE1)
    eps = {(e["method"], e["scene_index"]): e for e in episodes}
    same = same_episodes(episodes, list(range(25)))
    for a, b in (("ours", "grasp-only"), ("no-cdc", "grasp-only")):
        assert same[(a, b)], f"{a} and {b} share no episode"
        for s in range(25):
            x, y = eps[(a, s)], eps[(b, s)]
            if s in same[(a, b)]:
                assert x["metrics"]["semantic_miou_2d"] == y["metrics"]["semantic_miou_2d"]
            else:
                assert x["skills"] != y["skills"] or x["curves"] != y["curves"]
    assert not same[("ours", "view-only")]  # grasps make the episodes differ


def test_position_change_where_the_episodes_differ_counts_only_those_scenes() -> None:
    from msmem_core.run.results import _where_differ

    def row(pc: float, grasps: int, held: int) -> dict:
        return {"position_change_m": pc, "grasps": grasps, "grasp_success": held / grasps if grasps else 0.0}

    per = {"ours": {0: row(0.01, 2, 2), 1: row(0.30, 4, 1), 2: row(0.02, 3, 3)},
           "no-cdc": {0: row(0.01, 2, 2), 1: row(0.10, 4, 3), 2: row(0.02, 3, 3)}}
    text = _where_differ(per, {("ours", "no-cdc"): [0, 2]}, "ours", "no-cdc")
    assert text == ("; on the scene where their episodes differ, 0.300 m against 0.100 m, "
                    "grasps held 1 of 4 against 3 of 4")
    assert _where_differ(per, {("ours", "no-cdc"): [0, 1, 2]}, "ours", "no-cdc") == ""  # the same everywhere
    assert _where_differ(per, {("ours", "no-cdc"): []}, "ours", "no-cdc") == ""  # different everywhere
    assert _where_differ(per, None, "ours", "no-cdc") == ""


def test_absent_classes_are_the_predicted_classes_no_scene_holds(tmp_path: Path) -> None:
    from msmem_core.run.bench import suite_scenes
    from msmem_core.run.results import absent_classes
    from msmem_core.world.scene import CLASS_NAMES

    scenes = suite_scenes("hard25")[:2]
    held = {CLASS_NAMES.index(o.class_name) for s in scenes for o in s.objects}
    missing = [c for c in range(1, len(CLASS_NAMES)) if c not in held]
    assert missing  # two scenes never hold every class
    episodes = []
    for i in range(2):
        union = [0] * len(CLASS_NAMES)
        for c in held:
            union[c] = 50 + c  # held classes: predicted or not, never reported
        union[missing[0]] = 2 + i  # a stray label of a class neither scene holds
        episodes.append({"method": "ours", "scene_index": i, "fingerprint": {"suite": "hard25"},
                         "paper_counts": {"semantic_2d_union": union}})
    assert absent_classes(episodes, "ours", [0, 1]) == {CLASS_NAMES[missing[0]]: 5}
    assert absent_classes(episodes, "ours", [0]) == {CLASS_NAMES[missing[0]]: 2}
    assert absent_classes(episodes, "view-only", [0, 1]) == {}
    user = [{**e, "fingerprint": {"suite": str(tmp_path)}} for e in episodes]  # a user's suite: not checked
    assert absent_classes(user, "ours", [0, 1]) == {}


def test_the_committed_ur5e_row_labels_a_bowl_no_scene_holds() -> None:
    from msmem_core.run.results import absent_classes

    episodes = load_episodes(TABLE1.parent / "table1-ur5e")
    assert absent_classes(episodes, "view-only", list(range(10))) == {"bowl": 2}
    assert absent_classes(load_episodes(TABLE1), "ours", list(range(25))) == {}

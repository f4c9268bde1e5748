"""Classes a scene declares beside the built-ins: numbered after them, known to every object,
the backends and ground truth, counted in the belief, shown in the report; learned models trained on
other classes are refused in one line naming the classes they lack."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msmem_core.config import load_config
from msmem_core.errors import PluginError, UserError
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.report import class_palette
from msmem_core.run.runner import build_episode, run_episode
from msmem_core.world.scene import CLASS_NAMES, NUM_CLASSES, ObjectSpec, SceneSpec, class_mismatch, model_classes
from tests.support.defaults import ANALYTIC

SMALL = {**ANALYTIC, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}
CHIPS = {"name": "chips_can", "parts": [{"kind": "cylinder", "size_m": [0.038, 0.25], "position_m": [0, 0, 0.125]}],
         "mass_kg": 0.2, "confusable_with": "master_chef_can", "color_rgb": [0.9, 0.1, 0.1]}


def chips_scene() -> SceneSpec:
    return SceneSpec.model_validate({"name": "chips", "classes": [CHIPS], "objects": [
        {"id": 0, "class_name": "chips_can", "position_m": [-0.1, 0.12, 0.0]},
        {"id": 1, "class_name": "sugar_box", "position_m": [0.15, 0.2, 0.0]},
    ]})


def test_a_declared_class_is_numbered_after_the_built_ins_and_its_objects_know_it() -> None:
    scene = chips_scene()
    assert scene.num_classes == NUM_CLASSES + 1
    assert scene.class_names == (*CLASS_NAMES, "chips_can")
    chips = scene.objects[0].object_class
    assert (chips.name, chips.class_id, chips.mass_kg) == ("chips_can", NUM_CLASSES, 0.2)
    assert chips.confusable_id == scene.object_class("master_chef_can").class_id
    assert scene.objects[1].class_id == scene.object_class("sugar_box").class_id
    back = SceneSpec.model_validate_json(scene.model_dump_json())  # a scene.json reads back with its class
    assert back.objects[0].class_id == NUM_CLASSES
    assert back == scene
    assert SceneSpec().num_classes == NUM_CLASSES  # scenes without classes: the built-ins


@pytest.mark.parametrize(("data", "message"), [
    ({"objects": [{"id": 0, "class_name": "chips_can", "position_m": [0, 0.1, 0]}]},
     "objects.0.class_name: unknown object class 'chips_can'"),
    ({"classes": [CHIPS, CHIPS]}, "classes.1.name: 'chips_can' is declared twice"),
    ({"classes": [{**CHIPS, "name": "mug"}]}, "classes.0.name: 'mug' is a built-in class"),
    ({"classes": [{**CHIPS, "confusable_with": "crisps"}]}, "classes.0.confusable_with: unknown class 'crisps'"),
    ({"classes": [{**CHIPS, "name": "Chips Can"}]}, "String should match pattern"),
    ({"classes": [{**CHIPS, "parts": []}]}, "class 'chips_can' needs either parts or a mesh"),
])
def test_bad_classes_are_refused_naming_the_field(tmp_path: Path, data: dict, message: str) -> None:
    f = tmp_path / "scene.json"
    f.write_text(json.dumps(data))
    with pytest.raises(UserError, match="invalid scene file") as e:
        SceneSpec.from_json(f)
    assert message in str(e.value)


def test_an_object_outside_a_scene_knows_only_the_built_ins() -> None:
    assert ObjectSpec(id=0, class_name="mug", position_m=(0, 0, 0)).object_class.name == "mug"
    with pytest.raises(UserError, match="unknown object class 'chips_can'"):
        _ = ObjectSpec(id=0, class_name="chips_can", position_m=(0, 0, 0)).object_class


def test_model_classes_and_mismatch() -> None:
    assert model_classes(None, NUM_CLASSES) == CLASS_NAMES
    assert model_classes(None, 7) is None
    assert model_classes(["background", "a"], 2) == ("background", "a")
    assert class_mismatch(CLASS_NAMES, CLASS_NAMES) == ""
    assert class_mismatch(CLASS_NAMES, (*CLASS_NAMES, "chips_can")).startswith(
        "it does not know chips_can; it knows 14 object classes: cracker_box, sugar_box")
    assert "in this order; the scene has cracker_box, sugar_box" in class_mismatch(CLASS_NAMES[::-1], CLASS_NAMES)


def test_a_pybullet_episode_maps_a_declared_class(tmp_path: Path) -> None:
    cfg = load_config("view-only", None, {**SMALL, "steps": 3})
    ep = build_episode(cfg, get_plugin_manager(), scene=chips_scene())
    assert ep.workspace.num_classes == NUM_CLASSES + 1
    ep.sim.reset(ep.scene)
    obs = ep.sim.observe(ep.viewpoints[ep.start_view])
    assert NUM_CLASSES in set(np.unique(obs.labels).tolist()), "the camera labels the can with its own class"
    final = run_episode(ep, tmp_path / "run")
    with np.load(tmp_path / "run" / "belief_final.npz") as f:
        assert f["eta"].shape[0] == NUM_CLASSES + 1
    with np.load(tmp_path / "run" / "gt_final.npz") as f:
        assert NUM_CLASSES in set(np.unique(f["classes"]).tolist())
    assert final["correctly_found"] + final["misclassified"] + final["not_found"] == 2
    names, colors = class_palette(ep.scene)
    assert names[-1] == "chips_can"
    assert colors[-1] == "#e61a1a"


def test_msmem_run_writes_the_report_of_a_scene_with_its_own_class(tmp_path: Path) -> None:
    from msmem_core.run.report import write_report

    cfg = load_config("view-only", None, {**SMALL, "steps": 2})
    ep = build_episode(cfg, get_plugin_manager(), scene=chips_scene())
    run_episode(ep, tmp_path / "run")
    files = write_report(tmp_path / "run")
    html = next(f for f in files if f.suffix == ".html").read_text()
    assert "chips_can" in html


def test_a_learned_model_trained_on_other_classes_is_refused_naming_what_it_lacks() -> None:
    cfg = load_config("push-only", None, SMALL)  # the learned cnabu-push is push-only's effect model
    with pytest.raises(PluginError, match=r"effect_models\.push: cnabu-push does not fit the classes of scene "
                                          r"'chips': it does not know chips_can; it knows 14 object classes: "
                                          r"cracker_box, .*, wood_block; set class_map"):
        build_episode(cfg, get_plugin_manager(), scene=chips_scene())
    small = {k: v for k, v in SMALL.items() if k not in ANALYTIC}  # the library defaults: cnabu-map first
    with pytest.raises(PluginError, match=r"observation_model: cnabu-map does not fit the classes of scene "
                                          r"'chips': it does not know chips_can; .*, use the analytic models "
                                          r"there \(-c examples/scenes/analytic-effects.yaml"):
        build_episode(load_config("view-only", None, small), get_plugin_manager(), scene=chips_scene())
    analytic = load_config("push-only", None, {**SMALL, "skills": [
        {"name": "view"}, {"name": "push", "effect_model": {"name": "push-analytic"}}]})
    assert build_episode(analytic, get_plugin_manager(), scene=chips_scene()).scene.num_classes == 16

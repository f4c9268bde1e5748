"""Object classes that plugins declare: any scene may name them, the scene written to a run
folder declares them, and clashes are left out with a warning naming the plugin."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from msmem_core.config import load_config
from msmem_core.errors import UserError
from msmem_core.plugins import get_plugin_manager
from msmem_core.plugins.manager import PluginLoadWarning
from msmem_core.run.runner import build_episode, run_episode
from msmem_core.world.scene import NUM_CLASSES, SceneSpec
from tests.support import class_plugin
from tests.support.defaults import ANALYTIC

SMALL = {**ANALYTIC, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}
SCENE = {"name": "plugin-classes", "objects": [
    {"id": 0, "class_name": "toy_brick", "position_m": [-0.1, 0.15, 0.0]},
    {"id": 1, "class_name": "cracker_box", "position_m": [0.1, 0.15, 0.0]},
    {"id": 2, "class_name": "chips_can", "position_m": [0.25, 0.2, 0.0]},
]}


@pytest.fixture
def pm():
    manager = get_plugin_manager(extra_plugins=[("snacks", class_plugin)])
    with pytest.warns(PluginLoadWarning, match=r"object class 'mug' of plugin 'snacks' \(from <code>\) is left out: "
                                               r"the name is a built-in class"):
        classes = manager.object_classes()
    assert list(classes) == ["chips_can", "toy_brick"]
    return manager


def test_a_scene_names_a_plugin_class_and_the_run_folder_declares_it(pm, tmp_path: Path) -> None:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(SCENE))
    cfg = load_config("view-only", None, {**SMALL, "steps": 2, "scene": {"file": str(path)}})
    ep = build_episode(cfg, pm)
    # declared in the order the objects first name them, after the built-ins
    assert [c.name for c in ep.scene.classes] == ["toy_brick", "chips_can"]
    assert [o.class_id for o in ep.scene.objects] == [NUM_CLASSES, 1, NUM_CLASSES + 1]
    assert ep.workspace.num_classes == NUM_CLASSES + 2
    run_episode(ep, tmp_path / "run")
    written = SceneSpec.from_json(tmp_path / "run" / "scene.json")  # stands alone, without the plugin
    assert written.classes == ep.scene.classes


def test_without_the_plugin_the_class_is_unknown_and_the_error_says_where_classes_come_from(tmp_path: Path) -> None:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(SCENE))
    cfg = load_config("view-only", None, {**SMALL, "steps": 2, "scene": {"file": str(path)}})
    with pytest.raises(UserError, match=r"objects\.0\.class_name: unknown object class 'toy_brick'.*install a plugin"):
        build_episode(cfg, get_plugin_manager())


def test_a_scene_own_declaration_wins_over_the_plugin(pm, tmp_path: Path) -> None:
    own = {**class_plugin.BRICK.model_dump(), "mass_kg": 0.3}
    scene = SceneSpec.model_validate({**SCENE, "classes": [own]}, context={"offered_classes": pm.object_classes()})
    assert [c.name for c in scene.classes] == ["toy_brick", "chips_can"]
    assert scene.object_class("toy_brick").mass_kg == 0.3


def test_msmem_plugins_lists_the_classes(pm) -> None:
    rows = [r for r in pm.listing() if r["kind"] == "object-class"]
    assert [(r["name"], r["plugin"]) for r in rows] == [("chips_can", "snacks"), ("toy_brick", "snacks")]
    assert rows[0]["description"] == "object class: 1 parts, 0.2 kg"


def test_two_plugins_declaring_one_class_keep_the_first() -> None:
    again = SimpleNamespace(msmem_object_classes=class_plugin.msmem_object_classes)  # a second plugin
    manager = get_plugin_manager(extra_plugins=[("snacks", class_plugin), ("again", again)])
    with pytest.warns(PluginLoadWarning) as record:
        classes = manager.object_classes()
    assert classes["chips_can"] is class_plugin.CHIPS
    assert ("object class 'chips_can' of plugin 'again' (from <code>) is left out: the name is declared by plugin "
            "'snacks' (kept)") in [str(w.message) for w in record]
    assert manager.class_sources["chips_can"] == ("snacks", "<code>")

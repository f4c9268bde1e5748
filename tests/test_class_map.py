"""Class maps: every learned belief model (``cnabu-map``, ``cnabu-observe``, ``cnabu-push``,
``cnabu-grasp``) takes a scene's classes mapped onto the ones its weights know. A permuted map gives the
unmapped model's prediction, permuted. One top-level ``class_map`` in a run config reaches them all.
A map or a scene that does not fit is refused in one line. The line names the component, the keys at
fault and the classes the weights know."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from msmem_cnabu.classmap import mapped_classes, onto_slots
from msmem_cnabu.configs import CNABUEffectConfig, CNABUObserveConfig
from msmem_cnabu.learn.training import write_weights
from msmem_cnabu.models import CNABUGraspEffect, CNABUObservationModel, CNABUPushEffect

from msmem_core.config import load_config
from msmem_core.errors import PluginError, UserError
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.plugins.manager import ComponentRef
from msmem_core.run.bench import suite_scenes
from msmem_core.run.runner import build_episode
from msmem_core.world.scene import CLASS_NAMES
from tests.test_cnabu import GRID, WORKSPACE, grasp_actions, push_actions, random_belief, tiny_net

pytestmark = pytest.mark.usefixtures("one_torch_thread")
ROOT = Path(__file__).resolve().parents[1]
DEFAULTS = ROOT / "examples" / "scenes" / "mesh25-defaults.yaml"
SMALL = {"camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}
TRAINED = "14 object classes: cracker_box, sugar_box, master_chef_can"  # how a message names the weights' classes


def permuted_map(trained: tuple[str, ...]) -> tuple[dict[str, str], np.ndarray]:
    """11 scene classes onto 11 of the 14 trained ones, shuffled, and the class index it makes."""
    keep = np.random.default_rng(0).permutation(np.arange(1, 15))[:11]  # scene class i is trained class keep[i-1]
    return {f"thing{i}": trained[k] for i, k in enumerate(keep, 1)}, np.r_[0, keep]


def scene_and_trained_beliefs(seed: int, idx: np.ndarray) -> tuple[EvidentialMap, EvidentialMap]:
    """A belief over the scene's 12 classes and the same belief in the trained classes' slots (no
    evidence, 1, on the classes no scene class maps to)."""
    b = random_belief(seed=seed)
    scene = EvidentialMap(GRID, b.alpha, b.beta, b.eta[:len(idx)].copy())
    return scene, EvidentialMap(GRID, b.alpha, b.beta, onto_slots(scene.eta, idx, 15, fill=1))


# ------------------------------------------------------------------------------ permuted = unmapped, permuted
@pytest.mark.parametrize("kind", ["push", "grasp"])
def test_a_permuted_class_map_gives_the_unmapped_effect_prediction_permuted(tmp_path, kind):
    w = tmp_path / f"{kind}.pt"
    write_weights(tiny_net(kind, change_bias=0.3), w)
    cls = CNABUPushEffect if kind == "push" else CNABUGraspEffect
    plain = cls(CNABUEffectConfig(weights=w, change_threshold=0.5, batch=2))
    cmap, idx = permuted_map(plain.classes)
    mapped = cls(CNABUEffectConfig(weights=w, change_threshold=0.5, batch=2, class_map=cmap))
    assert mapped.classes == ("background", *cmap)
    assert mapped.trained_classes == plain.classes == CLASS_NAMES
    scene, trained = scene_and_trained_beliefs(1, idx)
    actions = push_actions() if kind == "push" else grasp_actions()  # grasps of scene class 3
    moved = actions if kind == "push" else [a.model_copy(update={"target_class": int(idx[3])}) for a in actions]
    got = mapped.predict(scene, actions, WORKSPACE)
    want = plain.predict(trained, moved, WORKSPACE)
    assert got.changed.any()
    for g, t in zip(got.beliefs, want.beliefs, strict=True):
        assert g.num_classes == 12
        np.testing.assert_array_equal(g.alpha, t.alpha)
        np.testing.assert_array_equal(g.beta, t.beta)
        np.testing.assert_array_equal(g.eta, t.eta[idx])
    if kind == "grasp":  # the grasped object's region, found on the scene's classes
        assert got.excluded is not None
        assert want.excluded is not None
        assert all(np.array_equal(a, b) for a, b in zip(got.excluded, want.excluded, strict=True))
        assert all(len(a) for a in got.excluded)


def test_a_permuted_class_map_gives_the_unmapped_observe_update_permuted(tmp_path):
    w = tmp_path / "observe.pt"
    write_weights(tiny_net("observe"), w)
    plain = CNABUObservationModel(CNABUObserveConfig(weights=w))
    cmap, idx = permuted_map(plain.classes)
    mapped = CNABUObservationModel(CNABUObserveConfig(weights=w, class_map=cmap))
    scene, trained = scene_and_trained_beliefs(2, idx)
    rng = np.random.default_rng(0)
    free = rng.random(GRID.shape) < 0.2
    occ = (rng.random(GRID.shape) < 0.05) & ~free
    seen = np.zeros((12, *GRID.shape), bool)
    seen[3] = occ  # the rays labelled scene class 3
    got = mapped.update_masks(scene, free, occ, seen)
    want = plain.update_masks(trained, free, occ, onto_slots(seen, idx, 15, fill=False))
    assert (got.alpha != scene.alpha).any()
    np.testing.assert_array_equal(got.alpha, want.alpha)
    np.testing.assert_array_equal(got.beta, want.beta)
    np.testing.assert_array_equal(got.eta, want.eta[idx])


# ------------------------------------------------------------------------------ one map for every model
def test_one_top_level_class_map_serves_every_learned_model_of_every_method():
    """The library defaults on a mesh25 scene with ``examples/scenes/mesh25-defaults.yaml``: the run gives
    its ``class_map`` to the observation and both effect models; a component's own map wins."""
    pm = get_plugin_manager()
    scene = suite_scenes("mesh25")[0]
    ep = build_episode(load_config("ours", DEFAULTS, SMALL), pm, scene=scene)
    models = [ep.observe_model, *(s.effect_model for s in ep.skills if s.effect_model is not None)]
    assert [type(m).__name__ for m in models] == ["CNABUMapObservationModel", "CNABUPushEffect", "CNABUGraspEffect"]
    assert all(m.classes == scene.class_names for m in models)
    assert all(m.trained_classes == CLASS_NAMES for m in models)
    view = build_episode(load_config("view-only", DEFAULTS, SMALL), pm, scene=scene)
    assert view.observe_model.classes == scene.class_names
    own = {"effect_models": {"push": {"name": "cnabu-push", "params": {"class_map": {"cereal": "mug"}}}}}
    with pytest.raises(PluginError, match=r"effect_models\.push: cnabu-push does not fit the classes of scene "
                                          r"'mesh25-00': it leaves book, teddy, .* unmapped"):
        build_episode(load_config("push-only", DEFAULTS, {**SMALL, **own}), pm, scene=scene)


# ------------------------------------------------------------------------------ one line, naming what is wrong
@pytest.mark.parametrize("component", ["cnabu-map", "cnabu-observe", "cnabu-push", "cnabu-grasp"])
@pytest.mark.parametrize(("class_map", "message"), [
    ({"cereal": "cracker_box", "ghost": "chips_can"},
     rf"class_map maps ghost to chips_can, which the weights do not know; they know {TRAINED}"),
    ({"cereal": "cracker_box", "book": "cracker_box", "cup": "mug"},
     rf"class_map maps cereal and book to cracker_box; map each scene class to a class of its own \(the weights "
     rf"know {TRAINED}"),
    ({"background": "mug"}, "class_map maps background, which is always itself"),
    ({"cereal": "background"}, rf"class_map maps cereal to background, which is no object class; .*{TRAINED}"),
])
def test_a_bad_class_map_is_refused_in_one_line_naming_the_component_and_the_keys(component, class_map, message):
    with pytest.raises(UserError, match=rf"^{component}: {message}") as err:
        mapped_classes(class_map, CLASS_NAMES, component)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("component", ["cnabu-map", "cnabu-push", "cnabu-grasp"])
def test_each_learned_model_names_itself_when_its_class_map_names_an_unknown_class(component):
    ref = ComponentRef(name=component, params={"class_map": {"ghost": "chips_can"}})
    with pytest.raises(UserError, match=rf"^{component}: class_map maps ghost to chips_can, which the weights do not "
                                        rf"know; they know {TRAINED}"):
        get_plugin_manager().build("belief-model", ref)


GHOST = {"cereal": "cracker_box", "book": "sugar_box", "ghost": "mug"}  # 3 entries: one no scene class


@pytest.mark.parametrize(("method", "where", "component"), [
    ("view-only", "observation_model", "cnabu-map"),
    ("push-only", r"effect_models\.push", "cnabu-push"),
    ("grasp-only", r"effect_models\.grasp", "cnabu-grasp"),
])
def test_a_class_map_that_does_not_fit_the_scene_names_its_keys_and_the_trained_classes(method, where, component):
    """A map of 3 entries on mesh25 (11 classes): the key no scene class has (``ghost``), the scene
    classes left unmapped, and the 14 classes the weights know, not the 3 + background the map takes."""
    pm = get_plugin_manager()
    over = {**SMALL, "class_map": GHOST}
    if component != "cnabu-map":  # the observation model that takes any classes, to reach the effect model
        over["observation_model"] = {"name": "analytic-observation"}
    with pytest.raises(PluginError) as err:
        build_episode(load_config(method, None, over), pm, scene=suite_scenes("mesh25")[0])
    line = str(err.value)
    assert "\n" not in line
    assert re.match(rf"{where}: {component} does not fit the classes of scene 'mesh25-00': its class_map maps "
                    r"ghost, which the scene does not have; it leaves teddy, bunny, cup, duck, lego, blob_flat, "
                    rf"blob_bar, blob_round, blob_big unmapped; the weights know {TRAINED}", line), line
    assert "4 classes" not in line
    assert line.endswith("to a distinct class the weights know")


def test_a_learned_model_without_a_map_names_the_classes_it_lacks_and_says_to_set_class_map():
    pm = get_plugin_manager()
    with pytest.raises(PluginError) as err:
        build_episode(load_config("view-only", None, SMALL), pm, scene=suite_scenes("mesh25")[0])
    line = str(err.value)
    assert line.startswith("observation_model: cnabu-map does not fit the classes of scene 'mesh25-00': it does "
                           "not know cereal, book, teddy, bunny, cup, duck, lego, blob_flat, blob_bar, blob_round, "
                           f"blob_big; it knows {TRAINED}")
    assert "set class_map to map each of the scene's object classes" in line
    assert "a top-level class_map gives it to every learned model" in line
    reordered = dict(reversed(list(load_config(None, DEFAULTS).class_map.items())))  # right classes, wrong order
    with pytest.raises(PluginError, match=r"its class_map lists the scene's classes in another order than the scene "
                                          r"\(cereal, book, teddy"):
        build_episode(load_config("view-only", None, {**SMALL, "class_map": reordered}), pm,
                      scene=suite_scenes("mesh25")[0])

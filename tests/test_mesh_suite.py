"""Generated scenes of declared classes: the generator draws from a class registry (the
built-ins and/or classes declared as parts or meshes), ``msmem scene generate --generator`` writes a
suite, and the shipped ``mesh25`` suite of ``pybullet_data`` meshes loads without decomposing anything
and stands still on the PyBullet shelf."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import ValidationError
from typer.testing import CliRunner

from msmem_core.cli import build_app
from msmem_core.config import load_config
from msmem_core.run.bench import SUITES, suite_scenes
from msmem_core.world.meshparts import mesh_pieces, shipped_cache_dir
from msmem_core.world.scene import NUM_CLASSES, ClassSpec, Part, SceneSpec
from msmem_core.world.scenegen import SceneGenConfig, _box_bodied, _class_pool, footprint_fraction, generate_scene
from tests.support.defaults import ANALYTIC

TALL = {"name": "crate", "parts": [{"kind": "box", "size_m": [0.14, 0.05, 0.2], "position_m": [0, 0, 0.1]}],
        "mass_kg": 0.4}
SMALL = {"name": "pebble", "parts": [{"kind": "cylinder", "size_m": [0.03, 0.04], "position_m": [0, 0, 0.02]}],
         "mass_kg": 0.05}
OWN = SceneGenConfig(builtin_classes=False, require_hard=False, classes=(ClassSpec(**TALL), ClassSpec(**SMALL)))


def test_the_generator_draws_only_the_declared_classes_when_asked() -> None:
    scene = generate_scene(3, OWN)
    names = {o.class_name for o in scene.objects}
    assert names <= {"crate", "pebble"}
    assert len(scene.objects) >= 5
    assert [c.name for c in scene.classes] == ["crate", "pebble"]
    assert not scene.builtin_classes
    assert scene.class_names == ("background", "crate", "pebble")  # only what can occur, numbered from 1
    assert {o.class_id for o in scene.objects} <= {1, 2}
    again = SceneSpec.model_validate_json(scene.model_dump_json())
    assert again == scene
    assert again.objects[0].object_class == scene.objects[0].object_class
    assert footprint_fraction(again) == pytest.approx(scene.occupancy_fraction, abs=1e-6)
    assert 0.30 <= scene.occupancy_fraction <= 0.45
    assert generate_scene(3, OWN) == scene


def test_the_built_ins_and_declared_classes_mix_and_the_built_in_scenes_stay_as_they_were() -> None:
    pool = _class_pool(SceneGenConfig(classes=(ClassSpec(**TALL),)))
    assert [c.name for c in pool][-1] == "crate"
    assert len(pool) == NUM_CLASSES
    shipped = suite_scenes("hard25")[0]
    assert generate_scene(25000).model_copy(update={"name": shipped.name}) == shipped


def test_a_mesh_box_makes_the_front_row_and_a_mesh_cylinder_does_not() -> None:
    import trimesh

    def convex(mesh: trimesh.Trimesh) -> ClassSpec:
        v = tuple(map(tuple, np.asarray(mesh.vertices)))
        return ClassSpec(name="x", parts=(Part(kind="convex", vertices_m=v),))

    box = _class_pool(SceneGenConfig(builtin_classes=False, classes=(
        convex(trimesh.creation.box((0.12, 0.05, 0.2)).apply_translation((0, 0, 0.1))),)))[0]
    cyl = _class_pool(SceneGenConfig(builtin_classes=False, classes=(
        convex(trimesh.creation.cylinder(0.05, 0.2, sections=32).apply_translation((0, 0, 0.1))),)))[0]
    assert _box_bodied(box)
    assert not _box_bodied(cyl)


def test_a_scene_without_the_built_ins_knows_only_its_own_classes() -> None:
    own = {"builtin_classes": False, "classes": [TALL], "objects": [{"id": 0, "class_name": "crate",
                                                                    "position_m": [0.0, 0.1, 0.0]}]}
    scene = SceneSpec.model_validate(own)
    assert (scene.num_classes, scene.objects[0].class_id) == (2, 1)
    with_builtins = SceneSpec.model_validate({**own, "builtin_classes": True})
    assert (with_builtins.num_classes, with_builtins.objects[0].class_id) == (NUM_CLASSES + 1, NUM_CLASSES)
    bad = {**own, "objects": [{"id": 0, "class_name": "mug", "position_m": [0.0, 0.1, 0.0]}]}
    with pytest.raises(ValidationError, match=r"objects\.0\.class_name: unknown object class 'mug'; known: crate"):
        SceneSpec.model_validate(bad)
    with pytest.raises(ValidationError, match=r"classes\.0\.name: 'mug' is a built-in class"):
        SceneSpec.model_validate({**own, "classes": [{**TALL, "name": "mug"}]})
    with pytest.raises(ValidationError, match="at least one class must be declared"):
        SceneSpec.model_validate({"builtin_classes": False})


@pytest.mark.parametrize(("settings", "message"), [
    ({"builtin_classes": False}, "at least one class must be declared"),
    ({"classes": [{**TALL, "name": "mug"}]}, "classes.0.name: 'mug' is a built-in class"),
    ({"classes": [TALL, TALL]}, "classes.1.name: 'crate' is declared twice"),
    ({"classes": [{"name": "ghost", "mesh": {"file": "/nowhere/ghost.obj"}}]}, "classes.0.mesh: mesh file"),
])
def test_bad_generator_classes_are_refused_naming_the_field(settings: dict, message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        SceneGenConfig(**settings)


def test_msmem_scene_generate_writes_a_suite_from_a_generator_file(tmp_path: Path) -> None:
    gen = tmp_path / "gen.yaml"
    gen.write_text(yaml.safe_dump({"builtin_classes": False, "require_hard": False, "classes": [TALL, SMALL]}))
    res = CliRunner().invoke(build_app(), ["scene", "generate", "--generator", str(gen), "--seed", "7",
                                           "--count", "2", "--name", "mine", "--out", str(tmp_path / "suite")])
    assert res.exit_code == 0, res.output
    files = sorted((tmp_path / "suite").glob("scene_*.json"))
    assert [f.name for f in files] == ["scene_00.json", "scene_01.json"]
    scenes = [SceneSpec.from_json(f) for f in files]
    assert [s.name for s in scenes] == ["mine-00", "mine-01"]
    assert [s.seed for s in scenes] == [7, 8]
    assert scenes[1] == generate_scene(8, OWN).model_copy(update={"name": "mine-01"})
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"classes": [{**TALL, "name": "mug"}]}))
    res = CliRunner().invoke(build_app(), ["scene", "generate", "--generator", str(bad)])
    assert res.exit_code != 0
    assert str(res.exception) == f"invalid generator settings in {bad}: classes.0.name: 'mug' is a built-in class"


def test_a_run_config_generator_mesh_path_is_relative_to_the_config_file(tmp_path: Path) -> None:
    import trimesh

    (tmp_path / "meshes").mkdir()
    trimesh.creation.box((0.05, 0.05, 0.05)).export(tmp_path / "meshes" / "cube.obj")
    cfg_file = tmp_path / "run.yaml"
    cfg_file.write_text(yaml.safe_dump({"scene": {"generator": {"classes": [
        {"name": "cube", "mesh": {"file": "meshes/cube.obj"}}]}}}))
    cfg = load_config("view-only", cfg_file, None)
    assert Path(cfg.scene.generator.classes[0].mesh.file) == (tmp_path / "meshes" / "cube.obj").resolve()


# ------------------------------------------------------------------------------------ mesh25
def test_mesh25_is_a_hard_suite_of_pybullet_data_meshes_decomposed_in_advance() -> None:
    assert "mesh25" in SUITES
    scenes = suite_scenes("mesh25")
    assert len(scenes) == 25
    assert len({s.seed for s in scenes}) == 25
    assert all(s.hidden_objects >= 4 for s in scenes)
    declared = {c.name: c for s in scenes for c in s.classes}
    assert all(c.mesh is not None and c.mesh.file.startswith("pybullet_data:") for c in declared.values())
    used = {o.class_name for s in scenes for o in s.objects}
    assert used <= set(declared)
    assert len(used) >= 8
    for c in declared.values():  # shipped decompositions: no CoACD at run time
        m = c.mesh
        _, report = mesh_pieces(m.file, m.scale, m.max_hulls, m.threshold, quat_xyzw=m.quat_xyzw)
        assert report.cache.parent == shipped_cache_dir(), c.name
        assert json.loads(report.cache.read_text())["pieces"]


@pytest.mark.parametrize("index", [0, 7])
def test_a_mesh25_scene_stands_still_on_the_pybullet_shelf(index: int) -> None:
    from msmem_pybullet.simulator import PyBulletSimulator

    scene = suite_scenes("mesh25")[index]
    sim = PyBulletSimulator()
    try:
        sim.reset(scene)
        sim.step(2.0)
        poses = sim.object_poses()
    finally:
        sim.close()
    for o in scene.objects:
        moved = np.linalg.norm(poses[o.id][:2, 3] - np.asarray(o.position_m[:2]))
        tilt = np.degrees(np.arccos(np.clip(poses[o.id][2, 2], -1.0, 1.0)))
        assert moved < 0.01, (o.id, o.class_name, moved)
        assert tilt < 5.0, (o.id, o.class_name, tilt)


@pytest.mark.parametrize("overlap", [-0.01, 0.0005, 0.002, 0.01])
def test_mesh_pieces_interpenetration_is_measured_by_the_inscribed_ball(overlap: float) -> None:
    """Mesh pieces have hundreds of edges, too many for the separating-axis test's edge pairs: their
    overlap depth is twice the largest ball inside both, which equals the separating-axis depth for
    two boxes overlapping at a corner and, for two spheres, their overlap along the centre line."""
    import trimesh

    from msmem_core.world.placement import SAT_MAX_EDGES, _Solid, inscribed_depth, penetration_depth
    from msmem_core.world.voxelize import _polytope

    def solid(part: Part, at: tuple[float, float, float]) -> _Solid:
        v, n, e = _polytope(part)
        v = v + np.asarray(at)
        return _Solid(v, n, e, v.min(axis=0), v.max(axis=0))

    box = Part(kind="box", size_m=(0.1, 0.1, 0.1))
    a, b = solid(box, (0, 0, 0)), solid(box, (0.1 - overlap, 0.05, 0.02))
    assert inscribed_depth(a, b) == pytest.approx(penetration_depth(a, b), abs=1e-9)
    assert penetration_depth(a, b) == pytest.approx(max(overlap, 0.0), abs=1e-9)
    ball = trimesh.creation.icosphere(3, 0.05)
    part = Part(kind="convex", vertices_m=tuple(map(tuple, ball.vertices)))
    a, b = solid(part, (0, 0, 0)), solid(part, (0.1 - overlap, 0, 0))
    assert len(a.edges) > SAT_MAX_EDGES
    assert penetration_depth(a, b) == pytest.approx(max(overlap, 0.0), abs=3e-4)


@pytest.mark.slow
def test_the_shipped_mesh25_suite_is_what_its_generator_file_makes() -> None:
    from msmem_core.config import load_generator_config

    path = Path(__file__).parents[1] / "examples" / "suites" / "mesh25.generator.yaml"
    shipped = suite_scenes("mesh25")[0]
    made = generate_scene(35000, load_generator_config(path))
    assert made.model_copy(update={"name": shipped.name}) == shipped


@pytest.mark.slow  # about 10 s: kept out of `make test`'s five minutes, run by CI's `make test-slow`
def test_an_episode_on_a_mesh25_scene_maps_its_mesh_classes_only() -> None:
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import build_episode, run_episode

    scene = suite_scenes("mesh25")[3]
    small = {**ANALYTIC, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}, "steps": 3}
    ep = build_episode(load_config("view-only", None, small), get_plugin_manager(), scene=scene)
    metrics = run_episode(ep)
    assert ep.workspace.num_classes == 1 + len(scene.classes) == 12
    assert [c.name for c in ep.workspace.classes] == [c.name for c in scene.classes]  # shapes skills may judge
    assert metrics["semantic_miou_2d"] > 0.1
    assert metrics["occupancy_miou"] > 0.4


def _both_methods(path: Path, suite: str):  # type: ignore[no-untyped-def]
    """view-only and ours built with the config file ``path`` on the suite's scene 0 (small camera),
    and a check that a config naming a skill ``psuh`` under ``field`` is refused."""
    from msmem_core.errors import PluginError
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import build_episode

    pm = get_plugin_manager()
    small = {"camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}
    scene = suite_scenes(suite)[0]
    built = [build_episode(load_config(m, path, small), pm, scene=scene) for m in ("view-only", "ours")]

    def refuse(field: str, value: object) -> None:
        with pytest.raises(PluginError, match=rf"{field}\.psuh: no skill named 'psuh'"):
            build_episode(load_config("ours", None, {**small, field: value}), pm)

    return built[0], built[1], refuse


def test_one_effect_models_file_serves_every_method_without_changing_its_skills() -> None:
    """``effect_models`` (examples/scenes/analytic-effects.yaml) sets the effect model of the skills a
    method has: view-only stays view-only (a ``skills`` list in the file would have given it pushes)."""
    view, ours, refuse = _both_methods(Path(__file__).parents[1] / "examples" / "scenes" / "analytic-effects.yaml",
                                       "mesh25")
    assert [s.name for s in view.skills] == ["view"]
    effects = {s.name: type(s.effect_model).__name__ for s in ours.skills if s.effect_model is not None}
    assert set(effects) == {"push", "grasp"}
    assert all("Analytic" in name for name in effects.values()), effects
    refuse("effect_models", {"psuh": {"name": "push-analytic"}})


def test_one_skill_params_file_sets_a_skills_parameters_for_every_method() -> None:
    """``skill_params`` (examples/push/without-fall-rules.yaml) merges parameters into the skills a method
    has, without adding skills to a method that lacks them; a misspelt skill is refused."""
    view, ours, refuse = _both_methods(Path(__file__).parents[1] / "examples" / "push" / "without-fall-rules.yaml",
                                       "hard25")
    assert [s.name for s in view.skills] == ["view"]
    push = next(s.skill for s in ours.skills if s.name == "push")
    assert (push.config.max_pushes_per_object, push.config.trip_height_ratio) == (None, None)
    assert [s.name for s in ours.skills] == ["view", "push", "grasp"]
    over = {"skills": [{"name": "view"}, {"name": "push", "params": {"max_samples": 7, "clearance_m": 0.05}}],
            "skill_params": {"push": {"clearance_m": 0.02}}}
    merged = load_config("push-only", None, over).skills[1].params
    assert merged == {"max_samples": 7, "clearance_m": 0.02}  # merged over the entry's own params
    refuse("skill_params", {"psuh": {"clearance_m": 0.01}})

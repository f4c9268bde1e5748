"""Build an episode from a ``RunConfig``, run MSAS on it and write the run folder.

Run folder: ``config.json`` (resolved), ``scene.json``, ``steps.jsonl`` (one record per step),
``metrics.json`` (final metrics and action counts), ``belief_final.npz``, and for the run report
(``msmem_core.run.runfolder``) ``belief_step{N}.npz`` (float16 belief and ground truth after the steps of
``RunConfig.snapshot_steps``) and ``gt_final.npz`` (final ground-truth occupancy and classes).
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import os
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msmem_core.config import RunConfig
from msmem_core.errors import Interrupted, PluginError, UserError
from msmem_core.interfaces import (
    BeliefModel,
    EffectModel,
    ObservationModel,
    Outcome,
    PerceptionAction,
    Robot,
    Simulator,
    Workspace,
)
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGService, shelf_interior_mask, shelf_wall_mask
from msmem_core.msas import BoundSkill, Decision, Objective, run_msas
from msmem_core.plugins.manager import ComponentRef, MsmemPluginManager
from msmem_core.run.estimate import Estimate, check_estimate, estimate
from msmem_core.run.failures import named_failures
from msmem_core.run.metrics import (
    belief_nll,
    object_counts,
    observable_iou,
    occupancy_iou,
    paper_counts,
    paper_metrics_from_counts,
    position_change_m,
    prediction_from_belief,
    semantic_miou,
    semantic_miou_bev,
)
from msmem_core.run.runfolder import save_ground_truth, save_snapshot, writing
from msmem_core.util.artifacts import sha256_file
from msmem_core.util.interrupt import caused_by_interrupt
from msmem_core.util.jsonable import dumps
from msmem_core.util.threads import configure_threads
from msmem_core.util.trace import Tracer
from msmem_core.world.placement import check_placement
from msmem_core.world.scene import ClassSpec, SceneSpec, class_mismatch
from msmem_core.world.scenegen import generate_scene
from msmem_core.world.viewpoints import default_start_view, generate_viewpoints
from msmem_core.world.visibility import observable_mask
from msmem_core.world.voxelize import voxelize_instances


def set_threads(n: int) -> None:
    """Per-episode thread counts, so results do not depend on where an episode runs."""
    configure_threads()  # before numba.set_num_threads starts numba's threading layer
    os.environ.setdefault("OMP_NUM_THREADS", str(n))
    import numba
    import torch

    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    torch.set_num_threads(n)


def resolve_scene(cfg: RunConfig, offered: Mapping[str, ClassSpec] | None = None) -> SceneSpec:
    """The run's scene: its file (objects may name classes plugins ``offered``), else generated."""
    if cfg.scene.file is not None:  # fields, then size, then placement: one-line errors
        scene = SceneSpec.from_json(str(cfg.scene.file), offered)
        scene_estimate(cfg, scene, manipulates=False)  # a lower bound, before the placement checks' pairs
        return check_placement(scene, f"scene file {cfg.scene.file}")
    return generate_scene(cfg.scene.seed, cfg.scene.generator)


def scene_estimate(cfg: RunConfig, scene: SceneSpec, manipulates: bool) -> Estimate:
    """The estimated memory and object work of an episode of ``cfg`` on ``scene`` (``msmem_core.run.estimate``),
    or a one-line ``UserError`` naming the scene when it is above the limits."""
    est = estimate(len(scene.objects), cfg.grid_spec(scene.shelf), scene.num_classes, cfg.steps, manipulates)
    return check_estimate(est, f"scene {scene.name!r}")


@dataclass
class Episode:
    """Everything built from a config, ready for ``run``."""

    cfg: RunConfig
    scene: SceneSpec
    sim: Simulator
    observe_model: ObservationModel
    skills: list[BoundSkill]
    objective: Objective
    ig: IGService
    viewpoints: np.ndarray
    records: list[dict[str, Any]] = field(default_factory=list)
    robot: Robot | None = None
    """The config's robot (None: no arm, everything reachable)."""

    @property
    def workspace(self) -> Workspace:
        """The grid, shelf, gripper, robot and classes every skill, effect model and term of the episode works in."""
        return Workspace(self.ig.grid, self.scene.shelf, self.cfg.gripper, self.scene.num_classes, self.robot,
                         self.scene.object_classes)

    @property
    def start_view(self) -> int:
        """The viewpoint of the episode's first observation."""
        start = self.cfg.msas.start_view
        return start if start is not None else default_start_view(self.cfg.viewpoints)


def effect_ref(cfg: RunConfig, pm: MsmemPluginManager, i: int) -> tuple[ComponentRef | None, str]:
    """The effect model of skill entry ``i`` and where the config names it: the entry's own, else
    ``effect_models`` by skill name, else the skill's default (None for perception skills). Refuses
    ``effect_models`` and ``skill_params`` keys that name no registered skill."""
    for name in ("effect_models", "skill_params"):
        unknown = sorted(set(getattr(cfg, name)) - set(pm.skills()))
        if unknown:
            raise PluginError(f"{name}.{unknown[0]}: no skill named {unknown[0]!r}; skills: "
                              f"{', '.join(sorted(pm.skills()))}")
    ref = cfg.skills[i]
    if ref.effect_model is not None:
        return ref.effect_model, f"skills.{i}.effect_model"
    if ref.name in cfg.effect_models:
        return cfg.effect_models[ref.name], f"effect_models.{ref.name}"
    default = getattr(pm.skills().get(ref.name), "effect_model", None)
    return (ComponentRef(name=default) if default else None), f"skills.{i}.effect_model"


def component_refs(cfg: RunConfig, pm: MsmemPluginManager) -> list[tuple[str, ComponentRef, str]]:
    """Every component the config names, as (kind, reference, where in the config), effect models included."""
    refs = [("belief-model", cfg.observation_model, "observation_model"), ("simulator", cfg.simulator, "simulator"),
            ("robot", cfg.robot, "robot")]
    for i, ref in enumerate(cfg.skills):
        refs.append(("skill", ref, f"skills.{i}"))
        eref, where = effect_ref(cfg, pm, i)
        if eref is not None:
            refs.append(("belief-model", eref, where))
    refs += [("objective-term", t, f"objective.{i}") for i, t in enumerate(cfg.objective)]
    return refs


@functools.cache
def _file_sha256(path: Path, size: int, mtime_ns: int) -> str:
    """``sha256_file``, once per file version (size and modification time)."""
    return sha256_file(path)


def artifact_files(spec: Any, params: dict[str, Any]) -> list[Path]:
    """The weights a component may load: ``*.pt`` files in a ``weights`` folder of the package that
    defines it, and any ``.pt`` file its params name."""
    files: set[Path] = set()
    module = inspect.getmodule(spec.factory)
    if module is not None and getattr(module, "__file__", None):
        pkg = Path(module.__file__).resolve().parent  # type: ignore[arg-type]
        files.update(pkg.glob("weights/*.pt"))
    for v in params.values():
        if isinstance(v, str | Path) and str(v).endswith(".pt") and Path(v).is_file():
            files.add(Path(v).resolve())
    return sorted(files)


def check_components(cfg: RunConfig, pm: MsmemPluginManager) -> dict[str, str]:
    """Check, without building anything, that every component the config names is registered and
    accepts its params (``PluginError`` naming it otherwise); returns ``{distribution: version}`` of
    the distributions that provide them, under ``weights`` a hash of the weights files the
    components may load (``artifact_files``), so that new weights are not mistaken for the old, and
    under ``components`` a hash of every component's resolved config (its defaults filled in), so that
    a plugin whose default changed is not mistaken for the old one either."""
    from importlib.metadata import PackageNotFoundError, version

    dists = set()
    weights: set[Path] = set()
    resolved = {}
    for kind, ref, where, config in resolved_components(cfg, pm):
        resolved[where] = {"name": ref.name, "config": config.model_dump(mode="json")}
        dists.add(pm.registered(kind)[ref.name].distribution)
        weights.update(artifact_files(pm.spec(kind, ref.name), dict(ref.params)))
        check_named_weights(ref, where)
    out = {"components": hashlib.sha256(json.dumps(resolved, sort_keys=True, default=str).encode()).hexdigest()[:16]}
    for d in sorted(dists):
        try:
            out[d] = version(d)
        except (PackageNotFoundError, ValueError):
            out[d] = "unknown"
    if weights:
        h = hashlib.sha256()
        for f in sorted(weights):
            st = f.stat()
            h.update(_file_sha256(f, st.st_size, st.st_mtime_ns).encode())
        out["weights"] = h.hexdigest()[:16]
    return out


def _prefixed_error(prefix: str, message: str) -> UserError:
    return UserError(prefix + message)


def check_named_weights(ref: ComponentRef, where: str) -> None:
    """A weights file a component's params name explicitly (an existing ``.pt`` path) loads with the safe
    loader and holds only finite tensors, or a ``UserError`` names the component, the file and the reason
    before anything runs (a bench would otherwise record every episode as crashed)."""
    from msmem_core.util.artifacts import load_state

    for key, v in ref.params.items():
        if isinstance(v, str | Path) and str(v).endswith(".pt") and Path(v).is_file():
            load_state(Path(v), functools.partial(_prefixed_error, f"{where}: {ref.name}'s {key}: "))


def resolved_components(cfg: RunConfig, pm: MsmemPluginManager) -> list[tuple[str, ComponentRef, str, Any]]:
    """``component_refs`` with each component's config as ``build_episode`` will build it (its params
    checked against its config model, run-wide values and defaults filled in; ``PluginError`` naming
    the component and the field otherwise)."""
    common = run_wide(cfg)  # as build_episode gives them
    return [(kind, ref, where, pm.validate(kind, ref, where=where, **common))
            for kind, ref, where in component_refs(cfg, pm)]


def check_params(cfg: RunConfig, pm: MsmemPluginManager) -> list[tuple[str, ComponentRef, str]]:
    """Check that every component the config names is registered and accepts its params, as
    ``build_episode`` will build it (``PluginError`` naming the component and the field otherwise);
    returns ``component_refs``."""
    return [(kind, ref, where) for kind, ref, where, _ in resolved_components(cfg, pm)]


def run_wide(cfg: RunConfig) -> dict[str, Any]:
    """Run-wide values a component receives for config fields of the same name the user left unset
    (``class_map`` only when the config sets one)."""
    out = {"camera": cfg.camera, "gripper": cfg.gripper, "viewpoints": cfg.viewpoints, "seed": cfg.seed}
    return out | ({"class_map": cfg.class_map} if cfg.class_map is not None else {})


def class_remedy(model: BeliefModel, mappable: bool) -> str:
    """What to do about a learned model whose classes do not fit the scene's: fix its class map, set one
    (``mappable``: its config takes a ``class_map``), or use other models."""
    if model.trained_classes is not None:
        return ("set class_map to map each of the scene's object classes, in the scene's order, to a distinct "
                "class the weights know")
    other = ("use the analytic models there (-c examples/scenes/analytic-effects.yaml: analytic-observation, "
             "push-analytic, grasp-analytic)")
    train = "train one on scenes with these classes"
    if mappable:
        return ("set class_map to map each of the scene's object classes, in the scene's order, to a distinct one "
                f"of these (a top-level class_map gives it to every learned model), {other}, or {train}")
    return f"{other} or {train}"


def build_episode(cfg: RunConfig, pm: MsmemPluginManager, scene: SceneSpec | None = None) -> Episode:
    configure_threads()  # before the plugins built here load torch
    common = run_wide(cfg)
    observe_model = pm.build("belief-model", cfg.observation_model, where="observation_model", **common)
    if not isinstance(observe_model, ObservationModel):
        raise PluginError(f"belief model {cfg.observation_model.name!r} cannot update from observations")
    models: list[tuple[str, str, BeliefModel]] = [("observation_model", cfg.observation_model.name, observe_model)]
    skills = []
    for i, ref in enumerate(cfg.skills):
        skill = pm.build("skill", ref, where=f"skills.{i}", **common)
        effect = None
        if skill.category == "manipulation":
            eref, where = effect_ref(cfg, pm, i)
            if not eref:
                raise PluginError(f"skill {ref.name!r} needs an effect_model in config (skills.{i}.effect_model)")
            effect = pm.build("belief-model", eref, where=where, **common)
            if not isinstance(effect, EffectModel):
                raise PluginError(f"belief model {eref.name!r} cannot predict effects ({where})")
            models.append((where, eref.name, effect))
        skills.append(BoundSkill(ref.name, skill, effect))
    terms = [(t.name, t.weight, pm.build("objective-term", t, where=f"objective.{i}", **common))
             for i, t in enumerate(cfg.objective)]
    robot = pm.build("robot", cfg.robot, where="robot", **common)
    if not isinstance(robot, Robot):
        raise PluginError(f"robot {cfg.robot.name!r} is not a msmem_core.interfaces.Robot")
    sim = pm.build("simulator", cfg.simulator, where="simulator", **common)
    if robot.arm:
        sim.attach_robot(robot)  # the arm replaces the floating gripper (a backend that cannot refuses)
    scene = scene or resolve_scene(cfg, pm.object_classes())  # after the plugins, so a bad name fails fast
    for where, name, model in models:
        if model.classes is not None and (why := class_mismatch(model.classes, scene.class_names,
                                                                model.trained_classes)):
            mappable = "class_map" in pm.spec("belief-model", name).config_model.model_fields
            raise PluginError(f"{where}: {name} does not fit the classes of scene {scene.name!r}: {why}; "
                              f"{class_remedy(model, mappable)}")
    viewpoints = generate_viewpoints(cfg.viewpoints, scene.shelf)
    start = cfg.msas.start_view if cfg.msas.start_view is not None else default_start_view(cfg.viewpoints)
    reach = robot.reach_camera(viewpoints[start], scene.shelf)
    if not reach.reachable:
        where = "msas.start_view" if cfg.msas.start_view is not None else "the default start view"
        raise UserError(f"robot {cfg.robot.name!r} cannot reach {where} ({start}): {reach.reason}; "
                        "set msas.start_view to a view it reaches (`msmem robot reach --json` lists them)")
    scene_estimate(cfg, scene, any(b.skill.category == "manipulation" for b in skills))
    ig = IGService(cfg.grid_spec(scene.shelf), cfg.camera, viewpoints, scene.shelf, cfg.ig)
    return Episode(cfg, scene, sim, observe_model, skills, Objective(terms), ig, viewpoints, robot=robot)


class MetricTracker:
    """Ground truth and per-step metrics; GT is recomputed only when objects moved.

    Besides the IoUs and Position Change, every step reports the paper's Table II object counts
    (``metrics.object_counts``: ``correctly_found``, ``misclassified``, ``not_found``,
    ``hallucinated``; docs/reference/metrics.md) over the objects still in the shelf, and
    ``removed``: objects of the scene no longer in the shelf (grasped out, or pushed or fallen out so
    that none of their voxels is left in the shelf interior), which the four counts leave out.

    The paper's own metrics (``metrics.paper_counts``: ``occupancy_miou``, ``semantic_miou_2d``,
    ``occupancy_ece``, ``semantic_ece``) are scored on the shelf interior (``shelf_interior_mask``);
    the counts behind the latest call are kept in ``paper_counts`` for the episode's final metrics.
    """

    def __init__(self, ep: Episode) -> None:
        self.ep = ep
        self.grid = ep.ig.grid
        self.initial = ep.sim.object_poses()
        self._gt_poses: dict[int, np.ndarray] | None = None
        self.objects = {o.id: o for o in ep.scene.objects}
        self.walls = shelf_wall_mask(self.grid, ep.scene.shelf)
        self.interior = shelf_interior_mask(self.grid, ep.scene.shelf)
        self.paper_counts: dict[str, list[int] | list[float]] = {}
        self._refresh(self.initial)

    def _refresh(self, poses: dict[int, np.ndarray]) -> None:
        objs = [self.objects[i] for i in poses]
        self.gt_inst = voxelize_instances(objs, self.grid, poses=poses)
        self.gt_inst[self.walls] = -1  # metrics are about the shelf interior
        self.gt_occ = self.gt_inst >= 0
        lut = np.zeros(max(self.objects, default=0) + 2, dtype=np.int16)  # object id + 1 -> class; -1 -> 0
        for o in self.objects.values():
            lut[o.id + 1] = o.class_id
        self.gt_cls = lut[self.gt_inst + 1]  # same as voxelize(): where objects share a voxel the later one wins
        present = np.unique(self.gt_inst[self.gt_occ]).tolist()
        self.present_classes = {i: self.objects[i].class_id for i in present}
        self.mask = observable_mask(objs, poses, self.ep.scene.shelf, self.ep.viewpoints, self.ep.cfg.camera, self.grid)
        self._gt_poses = {k: v.copy() for k, v in poses.items()}

    def __call__(self, belief: EvidentialMap) -> dict[str, float]:
        poses = self.ep.sim.object_poses()
        assert self._gt_poses is not None
        moved = set(poses) != set(self._gt_poses) or any(
            np.abs(poses[i] - self._gt_poses[i]).max() > 1e-4 for i in poses
        )
        if moved:
            self._refresh(poses)
        p, probs = belief.expected_occupancy(), belief.class_probs()
        pred_occ, pred_cls = prediction_from_belief(p, probs)
        pred_occ &= ~self.walls  # the shelf itself is known; metrics are about the objects
        pred_cls[self.walls] = 0
        self.paper_counts = paper_counts(p, probs, pred_cls, self.gt_occ, self.gt_cls, self.interior)
        return {
            "occupancy_iou": occupancy_iou(pred_occ, self.gt_occ),
            "observable_iou": observable_iou(pred_occ, self.gt_occ, self.mask),
            "semantic_miou": semantic_miou(pred_cls, self.gt_cls),
            "semantic_miou_bev": semantic_miou_bev(pred_cls, self.gt_cls),
            **paper_metrics_from_counts(self.paper_counts),
            **belief_nll(p, probs, self.gt_occ, self.gt_cls, self.interior),
            # objects still in the shelf (as the object counts; knocked-out ones count as removed)
            "position_change_m": position_change_m(self.initial, {i: poses[i] for i in self.present_classes}),
            **object_counts(pred_occ, pred_cls, self.gt_inst, self.present_classes),
            "removed": len(self.objects) - len(self.present_classes),
        }


def arm_record(ep: Episode, d: Decision) -> dict[str, Any] | None:
    """The arm's configuration for the step's action (a robot with an arm only): the IK answer for a
    view's camera pose, or the last configuration along a manipulation's tool path, with the points
    ``Robot.link_points`` draws the arm by; or why the robot cannot reach it. ``execution``: what the
    simulator's arm could not do while executing it (``Simulator.robot_notes``; docs/explanation/robots.md)."""
    robot = ep.robot
    if robot is None or not robot.arm:
        return None
    rec = _arm_configuration(robot, ep, d)
    if notes := ep.sim.robot_notes():  # this step's, even when the action names no pose to draw
        rec = {**(rec or {}), "execution": notes}
    return rec


def _arm_configuration(robot: Robot, ep: Episode, d: Decision) -> dict[str, Any] | None:
    """``arm_record`` without the execution notes: None when the action names no camera pose or tool path."""
    if d.skill.skill.category == "perception":
        if not isinstance(d.action, PerceptionAction):
            return None
        reach = robot.reach_camera(ep.viewpoints[d.action.view], ep.scene.shelf)
    else:
        path = d.skill.skill.tool_path(d.action, ep.workspace)
        if path is None:
            return None
        reach = robot.reach_path(path, ep.scene.shelf)
    if not reach.reachable or reach.joints is None:
        return {"reachable": False, "reason": reach.reason}
    points = robot.link_points(reach.joints)
    return {"reachable": True, "joints": [round(q, 5) for q in reach.joints],
            "points": np.round(points, 4).tolist()}


def run_episode(ep: Episode, out_dir: Path | None = None, progress: Any = None,
                tracer: Tracer | None = None) -> dict[str, Any]:
    """Run MSAS for ``cfg.steps`` actions; returns the final metrics (and writes the run folder).
    ``tracer`` observes every stage of every step (``msmem_core.util.trace``).

    An exception a component raises (a skill, belief model, objective term, simulator or robot the
    plugin manager built) becomes a :class:`~msmem_core.errors.ComponentFailure` naming it, its plugin
    and distribution, the step underway and the partial run folder; a failed write of the run folder
    (a full disk) a ``UserError`` naming the file and the folder (``runfolder.writing``)."""
    with named_failures(lambda: len(ep.records), out_dir):
        return _run_episode(ep, out_dir, progress, tracer)


def _run_episode(ep: Episode, out_dir: Path | None, progress: Any, tracer: Tracer | None) -> dict[str, Any]:
    cfg = ep.cfg
    set_threads(cfg.threads)
    ep.sim.reset(ep.scene)
    metrics = MetricTracker(ep)
    grid = ep.ig.grid
    initial: dict[str, float] = {}
    if out_dir is not None:
        with writing(out_dir / "config.json", out_dir):
            out_dir.mkdir(parents=True, exist_ok=True)
            (out_dir / "config.json").write_text(cfg.model_dump_json(indent=2))
        with writing(out_dir / "scene.json", out_dir):
            ep.scene.to_json(out_dir / "scene.json")
        with writing(out_dir / "steps.jsonl", out_dir):
            steps_file = (out_dir / "steps.jsonl").open("w")
    counts: Counter[str] = Counter()
    snapshot_steps = set(cfg.snapshot_steps())
    t0 = t_last = time.perf_counter()

    def on_start(b: EvidentialMap) -> None:  # after the start view: the steps are timed from here
        nonlocal t0, t_last
        initial.update(metrics(b))
        t0 = t_last = time.perf_counter()

    def on_step(step: int, d: Decision, outcome: Outcome, b: EvidentialMap) -> None:
        nonlocal t_last
        now = time.perf_counter()
        m = metrics(b)
        counts[d.skill.name] += 1
        rec = {
            "step": step, "skill": d.skill.name, "action": d.action.model_dump(), "objective": d.value,
            "terms": d.terms, "best_per_skill": d.best, "candidates": d.candidates,
            "funnel": d.funnel,  # per skill asked: candidates left after each stage (interfaces.Funnel)
            # only with an arm (docs/explanation/robots.md): candidates checked against the robot, and those it
            # cannot follow
            **({"reach_checked": d.reach_checked, "unreachable": d.unreachable} if d.reach_checked else {}),
            **({"arm": arm} if (arm := arm_record(ep, d)) is not None else {}),
            "success": outcome.success, "fell_or_left": outcome.fell_or_left, "info": outcome.info,
            "metrics": m, "seconds": now - t_last,
        }
        t_last = now
        ep.records.append(rec)
        if out_dir is not None:
            with writing(out_dir / "steps.jsonl", out_dir):
                steps_file.write(dumps(rec) + "\n")
                steps_file.flush()
            if step in snapshot_steps:
                with writing(snap := out_dir / f"belief_step{step}.npz", out_dir):
                    save_snapshot(snap, b, metrics.gt_occ, metrics.gt_cls)
        if progress is not None:
            progress(rec)

    try:
        belief = run_msas(ep.sim, ep.observe_model, ep.skills, ep.objective, ep.ig, ep.workspace, cfg.msas, cfg.steps,
                          ep.start_view, cfg.seed, on_step, on_start, tracer)
    except (KeyboardInterrupt, SystemError) as e:  # step N: the one underway (steps.jsonl holds 0 to N-1)
        if not isinstance(e, KeyboardInterrupt) and not caused_by_interrupt(e):
            raise
        where = f"; partial run in {out_dir}" if out_dir is not None else ""
        raise Interrupted(f"interrupted at step {len(ep.records)}{where}") from e
    finally:
        if out_dir is not None:
            with writing(out_dir / "steps.jsonl", out_dir):
                steps_file.close()
    final: dict[str, Any] = dict(ep.records[-1]["metrics"]) if ep.records else dict(initial)
    final.update({
        "initial": initial,
        "actions": dict(counts),
        "falls": sum(1 for r in ep.records if r["fell_or_left"]),  # manipulations after which an object fell or left
        "steps": len(ep.records),
        "seconds_total": time.perf_counter() - t0,
        "seconds_per_step": (time.perf_counter() - t0) / max(1, len(ep.records)),
        "scene": ep.scene.name,
        "method": cfg.method,
        "paper_counts": metrics.paper_counts,  # of the final belief; msmem bench sums them over scenes
    })
    if out_dir is not None:
        with writing(out_dir / "metrics.json", out_dir):
            (out_dir / "metrics.json").write_text(dumps(final, indent=2))
        with writing(out_dir / "belief_final.npz", out_dir):
            belief.save(out_dir / "belief_final.npz")
        with writing(out_dir / "gt_final.npz", out_dir):
            save_ground_truth(out_dir / "gt_final.npz", grid, metrics.gt_occ, metrics.gt_cls)
    return final

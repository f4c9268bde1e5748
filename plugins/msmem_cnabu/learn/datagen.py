"""Training data for the CNABU networks: belief before, action, simulator ground truth after.

Per scene seed (every random choice from ``np.random.default_rng([seed, kind])``, the scene and the
simulator's segmentation noise from the seed): generate a shelf scene (``msmem_core.world.scenegen``),
reset the simulator (``simulator``, ``--sim``: any backend, built by the plugin manager), observe the
episode's start view and ``min_views``-``max_views`` random views into an analytic belief
(``msmem_analytic``), then by kind:

- ``observe``: ``observe_samples`` times: a random unvisited view is rendered; its ray masks
  (free / occupied / class seen, ``AnalyticObservationModel.masks``) are the action; the belief
  before and the ground truth (objects do not move) are recorded; the view is integrated. With
  ``manipulate_after`` K (post-manipulation sequences), after K recorded views the
  ``manipulate_skill`` (push: UPS; grasp: UGS, as ``push`` / ``grasp`` below) proposes candidates
  from the belief and one, drawn at random, is executed for real (``execute_measured``): a sample
  whose action JSON is ``{"manipulation": "push", "action": ...}`` (or ``"grasp"``), whose masks are
  empty and whose ground truth is the world after it (``CNABUShard.manipulation``); the belief
  becomes the analytic effect model's prediction (``push-analytic``, ``grasp-analytic``), as in an
  episode, and the remaining views (and their ground truth) see the changed world. With
  ``manipulate_tries`` T, a skill that proposes nothing is asked again after each of the next views,
  up to T times in all.
  ``info["manipulation"]`` records the candidates, the displacements and the voxels the push changed
  in the ground truth, or that the skill proposed nothing (then the scene is a plain sequence).
- ``push`` / ``grasp``: ``states`` belief states; in each the skill proposes candidates from the
  belief (UPS sampler of ``msmem_push``; UGS of ``msmem_grasp`` with its FE-UMGF buffer, FE-vMF
  weights if installed, else its geometric fallback) and ``actions_per_state`` of them, drawn at
  random, are each executed under physics from a ``snapshot`` and the ground truth after it is
  voxelised from the simulator's object poses (``voxelize.voxelize``); then ``restore``.
  Between states one of the candidates is executed for real (the world changes, the belief keeps
  its now partly stale evidence as in an episode) and ``views_between`` more views are integrated.

Shards: one ``scene_<seed>.npz`` per scene, written atomically (tmp + rename); a rerun skips the
shards that exist and load, and regenerates corrupt ones. Evidence is stored as float16 (the
analytic counts are small integers), masks as bool, compressed. Fields (S states, N samples):

| field | shape | content |
| --- | --- | --- |
| ``alpha``, ``beta`` | [S, X, Y, Z] f16 | belief evidence before |
| ``eta`` | [S, C, X, Y, Z] f16 | |
| ``gt_occ_before``, ``gt_cls_before`` | [S, X, Y, Z] bool / int8 | ground truth at the state |
| ``state`` | [N] | state of each sample |
| ``act_vox`` | [N, A, X, Y, Z] bool | the action's voxel channels (``features``) |
| ``act_scalars`` | [N, M] f32 | the action's scalar channels |
| ``gt_occ``, ``gt_cls`` | [N, X, Y, Z] bool / int8 | ground truth after the action |
| ``actions`` | [N] str | the action's JSON (observe: the view index and camera pose) |
| ``success``, ``moved`` | [N] | the skill's outcome, objects moved > 5 mm |
| ``state_view`` | [S] | the last view integrated before the state (re-observed by eval's timing) |
| ``interior``, ``grid``, ``kind``, ``seed``, ``version`` | | |
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from msmem_cnabu.network import KINDS, Kind, action_channel_counts
from msmem_core.errors import UserError
from msmem_core.interfaces import Workspace
from msmem_core.learn import datagen
from msmem_core.learn.datagen import DatagenSummary, ShardTask, read_manifest, read_npz, save_npz, shard_path
from msmem_core.msas import MOVED_M, execute_measured
from msmem_core.plugins import ComponentRef
from msmem_core.world.grid import GridSpec
from msmem_core.world.scenegen import SceneGenConfig

SHARD_VERSION = 1


class CNABUDataConfig(BaseModel):
    """How one scene's CNABU samples are made (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    kind: Kind
    voxel_m: float = Field(0.01, gt=0.001, le=0.05)
    margin_voxels: int = Field(1, ge=1, le=10)
    require_hard: bool = False
    """Hard scenes instead of random 30-45 % occupancy shelves (slower to generate: docs/explanation/cnabu.md)."""
    generator: SceneGenConfig | None = None
    """The scene generator's settings (``msmem scene generate --generator``: e.g. scenes of mesh classes
    only); None: the built-in classes. ``require_hard`` above replaces the file's. The shard records
    the scene's class names (``info["classes"]``) and its beliefs have that many classes."""
    min_views: int = Field(1, ge=0)
    max_views: int = Field(6, ge=0)
    """Random views integrated (after the start view) before the first sample."""
    observe_samples: int = Field(6, ge=1)
    """observe: consecutive views recorded per scene."""
    manipulate_after: int | None = Field(None, ge=0)
    """observe: after this many recorded views (0: right after the views before the first sample), the
    ``manipulate_skill`` proposes candidates from the analytic belief and one of them, drawn at random,
    is executed for real; it is recorded as a manipulation sample (its action's JSON under
    ``"manipulation"``, empty masks, the ground truth after it) and the belief becomes the effect model's
    prediction (``push-analytic``), as in an episode. The remaining views see the moved world. When the
    skill proposes nothing the scene stays a plain observe sequence (``info["manipulation"]`` says so).
    None: no manipulation."""
    manipulate_skill: Literal["push", "grasp"] = "push"
    """observe: the skill ``manipulate_after`` executes (grasp: a grasp removes the object it holds,
    so the views after it see where it stood)."""
    manipulate_tries: int = Field(1, ge=1)
    """observe: when the skill proposes nothing after ``manipulate_after`` views, it is asked again after
    each next recorded view, up to this many times in all (a view must still follow)."""
    states: int = Field(2, ge=1)
    """push/grasp: belief states per scene."""
    actions_per_state: int = Field(4, ge=1)
    """push/grasp: candidates executed (each from a snapshot) per state."""
    propose_tries: int = Field(3, ge=1)
    """push/grasp: when the skill proposes nothing, two more views are integrated and it is asked
    again, up to this many times per state."""
    views_between: tuple[int, int] = (1, 3)
    """push/grasp: views integrated after the real action between two states (uniform, inclusive)."""
    label_noise: float = Field(0.05, ge=0.0, le=1.0)
    """The simulator's structured segmentation noise (its default)."""
    observation_model: ComponentRef = ComponentRef(name="analytic-observation")
    """push/grasp: the belief model the views are integrated with, so the effect networks learn on the
    beliefs they will see in episodes (``cnabu-map``: the completed belief). observe needs the analytic
    model (its samples are the analytic ray masks)."""
    simulator: ComponentRef = ComponentRef(name="pybullet")
    """The backend the scenes are simulated in (``--sim``); its ``seed`` is the scene seed and its
    ``label_noise`` the one above, unless ``params`` set them."""

    @model_validator(mode="after")
    def _views(self) -> CNABUDataConfig:
        if self.min_views > self.max_views:
            raise ValueError(f"min_views {self.min_views} > max_views {self.max_views}")
        if self.manipulate_after is not None and self.manipulate_after >= self.observe_samples:
            raise ValueError(f"manipulate_after {self.manipulate_after} must be below observe_samples "
                             f"{self.observe_samples} (views must follow the manipulation)")
        if self.kind == "observe" and self.observation_model.name != "analytic-observation":
            raise ValueError(f"observation_model {self.observation_model.name!r}: observe samples are the analytic "
                             "ray masks; only push and grasp data take another observation model")
        lo, hi = self.views_between
        if lo < 0 or hi < lo:
            raise ValueError("views_between must be (lo, hi) with 0 <= lo <= hi")
        return self


class ShardError(datagen.ShardError):
    """A CNABU shard is missing fields, inconsistent or unreadable."""


# ------------------------------------------------------------------------------------------ shards
_WORKSPACE_KEYS = ("interior_m", "tool", "gripper")
"""Fields push and grasp actions had before the workspace came with the context instead."""


@dataclass
class CNABUShard:
    """One scene's samples (see the module docstring for the fields)."""

    kind: str
    seed: int
    grid: GridSpec
    interior: NDArray[np.float64]
    alpha: NDArray[np.float16]
    beta: NDArray[np.float16]
    eta: NDArray[np.float16]
    gt_occ_before: NDArray[np.bool_]
    gt_cls_before: NDArray[np.int8]
    state: NDArray[np.int64]
    act_vox: NDArray[np.bool_]
    act_scalars: NDArray[np.float32]
    gt_occ: NDArray[np.bool_]
    gt_cls: NDArray[np.int8]
    actions: NDArray[np.str_]
    success: NDArray[np.bool_]
    moved: NDArray[np.int64]
    state_view: NDArray[np.int64]
    info: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.state)

    @property
    def num_states(self) -> int:
        return len(self.alpha)

    def belief(self, s: int) -> Any:
        """State ``s``'s belief as a float32 ``EvidentialMap``."""
        from msmem_core.map.belief import EvidentialMap

        return EvidentialMap(self.grid, self.alpha[s].astype(np.float32), self.beta[s].astype(np.float32),
                             self.eta[s].astype(np.float32))

    @property
    def workspace(self) -> Workspace:
        """The ``Workspace`` the samples were made in: the shard's grid, the shelf with its interior,
        the default gripper (the skills datagen builds use it)."""
        from msmem_core.world.scene import ShelfSpec

        x_lo, _, _, x_hi, y_hi, z_hi = (float(v) for v in self.interior)
        return Workspace(self.grid, ShelfSpec(width_m=x_hi - x_lo, depth_m=y_hi, height_m=z_hi))

    def action(self, i: int) -> Any:
        """Sample ``i``'s action as the skill's pydantic model (push / grasp) or a dict (observe)."""
        data = json.loads(str(self.actions[i]))
        for key in _WORKSPACE_KEYS:  # carried by the actions of shards made before they stopped doing so
            data.pop(key, None)
        if self.kind == "push":
            from msmem_push.skill import PushAction

            return PushAction.model_validate(data)
        if self.kind == "grasp":
            from msmem_grasp.skill import GraspAction

            return GraspAction.model_validate(data)
        return data

    def manipulation(self, i: int) -> Any | None:
        """observe: sample ``i``'s manipulation (the skill's pydantic action) if it is one
        (``CNABUDataConfig.manipulate_after``), else None (a view)."""
        if self.kind != "observe":
            return None
        data = json.loads(str(self.actions[i]))
        if "manipulation" not in data:
            return None
        return _ACTIONS[data["manipulation"]]().model_validate(data["action"])

    def masks(self, i: int) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
        """observe: (free, occ, seen [C, ...]) of sample ``i``."""
        v = self.act_vox[i]
        return v[0], v[1], v[2:]

    def arrays(self) -> dict[str, Any]:
        out: dict[str, Any] = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("grid", "info")}
        out["grid"] = np.asarray(self.grid.model_dump_json())
        out["info"] = np.asarray(json.dumps(self.info))
        out["kind"] = np.asarray(self.kind)
        out["seed"] = np.asarray(self.seed)
        out["version"] = np.asarray(SHARD_VERSION)
        return out


_NAMES = [f.name for f in fields(CNABUShard)]


def _push_action() -> Any:
    from msmem_push.skill import PushAction

    return PushAction


def _grasp_action() -> Any:
    from msmem_grasp.skill import GraspAction

    return GraspAction


_ACTIONS: dict[str, Callable[[], Any]] = {"push": _push_action, "grasp": _grasp_action}
"""The action model of each skill ``manipulate_after`` can execute."""


def predicted_belief(effect: Any, belief: Any, action: Any, workspace: Workspace) -> Any:
    """The belief after a manipulation: the effect model's prediction for ``action``, applied as the
    MSAS loop applies it (``msmem_core.msas.run_msas`` with its default ``disturbed_evidence_cap``
    None: the prediction as is)."""
    return effect.predict(belief, [action], workspace).belief(0)


def _fail(path: Path, what: str, kind: str = "KIND") -> ShardError:
    return ShardError(f"{path}: {what}; rerun `msmem datagen cnabu --kind {kind}` with the same arguments to "
                      "regenerate it (finished shards are kept)")


def _check(z: dict[str, Any], path: Path) -> None:
    kind = str(z["kind"])
    if kind not in KINDS:
        raise _fail(path, f"unknown kind {kind!r}")
    grid = GridSpec.model_validate_json(str(z["grid"]))
    shape = tuple(grid.shape)
    s, n = z["alpha"].shape[0], z["state"].shape[0]
    c = z["eta"].shape[1] if z["eta"].ndim == 5 else -1
    a, m = action_channel_counts(kind, c)
    expected = {
        "alpha": (s, *shape), "beta": (s, *shape), "eta": (s, c, *shape), "gt_occ_before": (s, *shape),
        "gt_cls_before": (s, *shape), "state": (n,), "act_vox": (n, a, *shape), "act_scalars": (n, m),
        "gt_occ": (n, *shape), "gt_cls": (n, *shape), "actions": (n,), "success": (n,), "moved": (n,),
        "state_view": (s,), "interior": (6,),
    }
    for key, shp in expected.items():
        if tuple(z[key].shape) != shp:
            raise _fail(path, f"field {key!r} has shape {tuple(z[key].shape)}, expected {shp}: inconsistent shard",
                        kind)
    if n and (z["state"].min() < 0 or z["state"].max() >= s):
        raise _fail(path, f"state index out of range [0, {s})", kind)


def load_shard(path: str | Path) -> CNABUShard:
    """Read and validate a shard; any problem raises :class:`ShardError` naming the file."""
    path = Path(path)
    z = read_npz(path, _NAMES, "CNABU", lambda what: _fail(path, what))
    if int(z["version"]) != SHARD_VERSION:
        raise _fail(path, f"shard version {int(z['version'])}, this msmem reads {SHARD_VERSION}", str(z["kind"]))
    _check(z, path)
    return CNABUShard(
        kind=str(z["kind"]), seed=int(z["seed"]), grid=GridSpec.model_validate_json(str(z["grid"])),
        interior=z["interior"].astype(np.float64), alpha=z["alpha"], beta=z["beta"], eta=z["eta"],
        gt_occ_before=z["gt_occ_before"].astype(bool), gt_cls_before=z["gt_cls_before"].astype(np.int8),
        state=z["state"].astype(np.int64), act_vox=z["act_vox"].astype(bool),
        act_scalars=z["act_scalars"].astype(np.float32), gt_occ=z["gt_occ"].astype(bool),
        gt_cls=z["gt_cls"].astype(np.int8), actions=z["actions"], success=z["success"].astype(bool),
        moved=z["moved"].astype(np.int64), state_view=z["state_view"].astype(np.int64),
        info=json.loads(str(z["info"])),
    )


def save_shard(path: str | Path, shard: CNABUShard) -> None:
    """Write atomically: a temporary file in the same folder, then rename."""
    save_npz(path, shard.arrays())


def list_shards(data_dir: str | Path, kind: str | None = None) -> list[Path]:
    """The shards of a data folder, sorted; a missing or empty folder (or one of another kind, per
    its ``dataset.json``) is a clear error."""
    d = Path(data_dir)
    paths = datagen.list_shards(d, f"`msmem datagen cnabu --kind {kind or 'KIND'} --out {d}`")
    manifest = read_manifest(d)
    if kind is not None and manifest is not None:
        have = manifest.get("config", {}).get("kind")
        if have is not None and have != kind:
            raise UserError(f"{d} holds {have!r} data (see {d / datagen.MANIFEST}), not {kind!r}")
    return paths


# ------------------------------------------------------------------------------------ one scene
class _Recorder:
    """Collects states and samples of one scene."""

    def __init__(self) -> None:
        self.states: list[tuple[Any, NDArray[np.bool_], NDArray[np.int16], int]] = []
        self.samples: list[dict[str, Any]] = []

    def state(self, belief: Any, gt: tuple[NDArray[np.bool_], NDArray[np.int16]], view: int) -> int:
        self.states.append((belief.copy(), gt[0], gt[1], view))
        return len(self.states) - 1

    def sample(self, state: int, vox: NDArray[np.bool_], scalars: NDArray[np.float32],
               gt: tuple[NDArray[np.bool_], NDArray[np.int16]], action: str, success: bool, moved: int) -> None:
        self.samples.append({"state": state, "vox": vox, "scalars": scalars, "gt_occ": gt[0], "gt_cls": gt[1],
                             "action": action, "success": success, "moved": moved})

    def shard(self, kind: str, seed: int, grid: GridSpec, interior: Sequence[float], info: dict[str, Any]
              ) -> CNABUShard:
        used = sorted({s["state"] for s in self.samples})
        remap = {s: i for i, s in enumerate(used)}
        states = [self.states[s] for s in used]
        a, m = action_channel_counts(kind, states[0][0].num_classes if states else 15)
        shape = tuple(grid.shape)
        ns = len(self.samples)

        def stack(xs: list[Any], dtype: Any, empty: tuple[int, ...]) -> NDArray[Any]:
            return np.stack(xs).astype(dtype) if xs else np.zeros(empty, dtype)

        c = states[0][0].num_classes if states else 15
        return CNABUShard(
            kind=kind, seed=seed, grid=grid, interior=np.asarray(interior, np.float64),
            alpha=stack([b.alpha for b, *_ in states], np.float16, (0, *shape)),
            beta=stack([b.beta for b, *_ in states], np.float16, (0, *shape)),
            eta=stack([b.eta for b, *_ in states], np.float16, (0, c, *shape)),
            gt_occ_before=stack([g for _, g, _, _ in states], bool, (0, *shape)),
            gt_cls_before=stack([g for _, _, g, _ in states], np.int8, (0, *shape)),
            state=np.array([remap[s["state"]] for s in self.samples], np.int64),
            act_vox=stack([s["vox"] for s in self.samples], bool, (0, a, *shape)),
            act_scalars=stack([s["scalars"] for s in self.samples], np.float32, (0, m)),
            gt_occ=stack([s["gt_occ"] for s in self.samples], bool, (0, *shape)),
            gt_cls=stack([s["gt_cls"] for s in self.samples], np.int8, (0, *shape)),
            actions=np.array([s["action"] for s in self.samples], dtype=np.str_) if ns else np.zeros(0, np.str_),
            success=np.array([s["success"] for s in self.samples], bool),
            moved=np.array([s["moved"] for s in self.samples], np.int64),
            state_view=np.array([v for *_, v in states], np.int64),
            info=info,
        )


def _ground_truth(sim: Any, scene: Any, grid: GridSpec) -> tuple[NDArray[np.bool_], NDArray[np.int16]]:
    from msmem_core.world.voxelize import voxelize

    poses = sim.object_poses()
    objects = {o.id: o for o in scene.objects}
    return voxelize([objects[i] for i in poses if i in objects], grid, poses=poses)


def make_shard(seed: int, config: CNABUDataConfig) -> CNABUShard:
    """Simulate one scene and record its samples (see the module docstring)."""
    from msmem_analytic.observation import AnalyticObservationModel

    from msmem_core.map.belief import EvidentialMap
    from msmem_core.sim.build import build_simulator
    from msmem_core.world.scenegen import generate_scene
    from msmem_core.world.viewpoints import ViewpointConfig, default_start_view, generate_viewpoints

    cfg = config
    rng = np.random.default_rng([seed, KINDS.index(cfg.kind)])
    gen = cfg.generator.model_copy(update={"require_hard": cfg.require_hard}) if cfg.generator else None
    scene = generate_scene(seed, gen or SceneGenConfig(require_hard=cfg.require_hard))
    grid = GridSpec.around_box(scene.shelf.interior_lower, scene.shelf.interior_upper, cfg.voxel_m, cfg.margin_voxels)
    lo, hi = scene.shelf.interior_lower, scene.shelf.interior_upper
    interior = (*map(float, lo), *map(float, hi))
    vp_cfg = ViewpointConfig()
    viewpoints = generate_viewpoints(vp_cfg, scene.shelf)
    model = AnalyticObservationModel()
    observer = model if cfg.kind == "observe" else _observation_model(cfg.observation_model)
    sim = build_simulator(cfg.simulator, seed=seed, label_noise=cfg.label_noise)
    rec = _Recorder()
    visited: list[int] = []
    t_sim = 0.0
    manip: dict[str, Any] | None = None

    def fresh_views(k: int) -> list[int]:
        free = np.setdiff1d(np.arange(len(viewpoints)), visited)
        return [int(v) for v in rng.choice(free, size=min(k, len(free)), replace=False)]

    def look(belief: EvidentialMap, views: Sequence[int]) -> EvidentialMap:
        for v in views:
            belief = observer.update(belief, sim.observe(viewpoints[v]))
            visited.append(int(v))
        return belief

    try:
        sim.reset(scene)
        belief = look(EvidentialMap.empty(grid, scene.num_classes), [default_start_view(vp_cfg)])
        belief = look(belief, fresh_views(int(rng.integers(cfg.min_views, cfg.max_views + 1))))
        if cfg.kind == "observe":
            gt = _ground_truth(sim, scene, grid)
            from msmem_cnabu.features import observe_channels

            def propose(skill: Any, b: EvidentialMap) -> list[Any]:
                return _propose(cfg.manipulate_skill, skill, b, scene.shelf, viewpoints, visited, rng, seed,
                                len(visited))

            after = cfg.manipulate_after
            for k, v in enumerate(fresh_views(cfg.observe_samples)):
                due = after is not None and after <= k < after + cfg.manipulate_tries
                if due and not (manip or {}).get("executed"):
                    t0 = time.perf_counter()
                    belief, gt, manip = _manipulate(cfg.manipulate_skill, belief, sim, scene, grid, rng, rec,
                                                    visited[-1], observe_channels, propose)
                    t_sim += time.perf_counter() - t0
                obs = sim.observe(viewpoints[v])
                free, occ, seen = model.masks(belief, obs)
                s = rec.state(belief, gt, visited[-1])
                pose = np.asarray(viewpoints[v]).round(6).tolist()
                rec.sample(s, observe_channels(free, occ, seen), np.zeros(0, np.float32), gt,
                           json.dumps({"view": v, "camera_to_world": pose}), True, 0)
                belief = model.apply_masks(belief, free, occ, seen)  # the masks once per view
                visited.append(v)
        else:
            skill = _skill(cfg.kind, seed)
            ctx = SimpleNamespace(shelf=scene.shelf)  # what a skill's execute reads of a DecisionContext
            workspace = Workspace(grid, scene.shelf)
            step = 0
            for state_i in range(cfg.states):
                actions: list[Any] = []
                for _ in range(cfg.propose_tries):  # no candidate yet: look again (as an episode would)
                    actions = _propose(cfg.kind, skill, belief, scene.shelf, viewpoints, visited, rng, seed, step)
                    step += 1
                    if actions:
                        break
                    belief = look(belief, fresh_views(2))
                if actions:
                    gt0 = _ground_truth(sim, scene, grid)
                    s = rec.state(belief, gt0, visited[-1])
                    pick = rng.choice(len(actions), size=min(cfg.actions_per_state, len(actions)), replace=False)
                    from msmem_cnabu.features import manipulation_channels

                    chosen = [actions[int(i)] for i in pick]
                    vox, scalars, _ = manipulation_channels(cfg.kind, belief, chosen, workspace)
                    for a, av, sc in zip(chosen, vox, scalars, strict=True):
                        token = sim.snapshot()
                        t0 = time.perf_counter()
                        out = execute_measured(skill, sim, a, ctx)
                        t_sim += time.perf_counter() - t0
                        rec.sample(s, av, sc, _ground_truth(sim, scene, grid), a.model_dump_json(), bool(out.success),
                                   len(out.info.get("moved", [])))
                        sim.restore(token)
                    if state_i + 1 < cfg.states:  # the world moves on: one candidate for real
                        skill.execute(sim, actions[int(rng.integers(len(actions)))], ctx)  # the world moves on
                if state_i + 1 < cfg.states:
                    lo_v, hi_v = cfg.views_between
                    belief = look(belief, fresh_views(int(rng.integers(lo_v, hi_v + 1))))
    finally:
        sim.close()
    info = {"scene": scene.name, "objects": len(scene.objects), "views": visited, "sim_execute_s": t_sim,
            "config": cfg.model_dump(mode="json"), "classes": list(scene.class_names)}
    if manip is not None:
        info["manipulation"] = manip
    return rec.shard(cfg.kind, seed, grid, interior, info)


def _observation_model(ref: ComponentRef) -> Any:
    """The observation model ``ref`` names, built by the plugin manager (one torch thread per worker)."""
    from msmem_core.interfaces import ObservationModel
    from msmem_core.plugins import get_plugin_manager

    model = get_plugin_manager().build("belief-model", ref, where="observation_model", threads=1)
    if not isinstance(model, ObservationModel):
        raise UserError(f"observation_model: belief model {ref.name!r} cannot update from observations")
    return model


def _manipulate(skill_name: str, belief: Any, sim: Any, scene: Any, grid: GridSpec, rng: np.random.Generator,
                rec: _Recorder, view: int, observe_channels: Callable[..., NDArray[np.bool_]],
                propose: Callable[[Any, Any], list[Any]]
                ) -> tuple[Any, tuple[NDArray[np.bool_], NDArray[np.int16]], dict[str, Any]]:
    """observe with ``manipulate_after``: one candidate of the skill (``propose(skill, belief)``), drawn at
    random, executed for real and recorded as a manipulation sample; returns (the belief the skill's
    analytic effect model predicts, the ground truth after, what ``info["manipulation"]`` records).
    Without candidates: the belief and ground truth as they were (``info["executed"]`` False)."""
    skill = _skill(skill_name, 0)
    workspace = Workspace(grid, scene.shelf)
    gt0 = _ground_truth(sim, scene, grid)
    actions = propose(skill, belief)
    effect = f"{skill_name}-analytic"
    info: dict[str, Any] = {"skill": skill_name, "effect_model": effect, "candidates": len(actions)}
    if not actions:
        return belief, gt0, {**info, "executed": False, "reason": f"the {skill_name} skill proposed no candidate"}
    a = actions[int(rng.integers(len(actions)))]
    s = rec.state(belief, gt0, view)
    out = execute_measured(skill, sim, a, SimpleNamespace(shelf=scene.shelf))
    gt = _ground_truth(sim, scene, grid)
    shape = tuple(grid.shape)
    empty = np.zeros(shape, bool)
    record = json.dumps({"manipulation": skill_name, "action": a.model_dump(mode="json")})
    rec.sample(s, observe_channels(empty, empty, np.zeros((belief.num_classes, *shape), bool)),
               np.zeros(0, np.float32), gt, record, bool(out.success), len(out.info.get("moved", [])))
    moved = {str(i): round(d, 4) for i, d in out.displacement_m.items() if d > MOVED_M}
    info |= {"executed": True, "sample": len(rec.samples) - 1, "success": bool(out.success),
             "displacement_m": moved, "fell_or_left": list(out.fell_or_left),
             "voxels_changed": int((gt[0] != gt0[0]).sum())}
    if skill_name == "grasp":
        info["removed"] = [int(i) for i in out.removed]
    from msmem_core.plugins import get_plugin_manager

    model = get_plugin_manager().build("belief-model", effect, where="manipulate_skill")
    return predicted_belief(model, belief, a, workspace), gt, info


def _skill(kind: str, seed: int) -> Any:
    if kind == "push":
        from msmem_push.skill import PushConfig, PushSkill

        return PushSkill(PushConfig())
    from msmem_grasp.skill import GraspConfig, GraspSkill

    # the grasps as predicted, without the turned twins (``turn_to``) the skill proposes by default: the
    # data the shipped networks were trained on came from grasps as predicted
    return GraspSkill(GraspConfig(seed=seed, turn_to=()))


def _propose(kind: str, skill: Any, belief: Any, shelf: Any, viewpoints: NDArray[np.float64], visited: list[int],
             rng: np.random.Generator, seed: int, step: int) -> list[Any]:
    """The skill's candidates from the belief (as in an episode step)."""
    if kind == "push":
        return list(skill.sample(belief, shelf, rng))
    from msmem_grasp.fpp import virtual_front_views

    views = np.concatenate([viewpoints[sorted(set(visited))].reshape(-1, 4, 4), virtual_front_views()])
    hyp = skill.predict(belief, shelf, views, int(np.random.default_rng([seed, step, 7]).integers(2**31)))
    skill.buffer.update(hyp, belief)
    return list(skill.executable(belief, shelf))


# ---------------------------------------------------------------------------------------- dataset
def run_shard_task(task: ShardTask) -> dict[str, Any]:
    """Executor entry point: make and write one shard; returns a small summary."""
    t0 = time.perf_counter()
    cfg = CNABUDataConfig.model_validate_json(task.config_json)
    shard = make_shard(task.seed, cfg)
    path = shard_path(task.out, task.seed)
    save_shard(path, shard)
    return {"seed": task.seed, "samples": len(shard), "states": shard.num_states,
            "seconds": time.perf_counter() - t0, "sim_execute_s": shard.info.get("sim_execute_s", 0.0),
            "bytes": path.stat().st_size}


def _class_names(generator: dict[str, Any] | None) -> list[str]:
    """The classes a generator's scenes hold, by name (None: the built-ins)."""
    if not generator:
        return ["(built-in)"]
    own = [c["name"] for c in generator.get("classes", [])]
    return own if generator.get("builtin_classes", True) is False else ["(built-in)", *own]


def generate_dataset(
    out_dir: str | Path,
    seeds: Sequence[int],
    config: CNABUDataConfig,
    executor: str = "local",
    workers: int = 1,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> DatagenSummary:
    """Make the shards of ``seeds`` in ``out_dir`` that are missing (or corrupt), in parallel."""
    from msmem_core.sim.build import check_simulator

    out = Path(out_dir)
    old = read_manifest(out)
    if old is not None and old.get("config", {}).get("kind") not in (None, config.kind):
        raise UserError(f"{out} already holds {old['config']['kind']!r} data (see {out / datagen.MANIFEST}); "
                        f"use another --out for {config.kind!r}")
    datagen.check_same_simulator(out, old, config.simulator)
    if old is not None and _class_names(old.get("config", {}).get("generator")) != _class_names(
            config.model_dump(mode="json")["generator"]):
        raise UserError(f"{out} holds scenes of other classes than --generator gives (see {out / datagen.MANIFEST}); "
                        "use another --out")
    check_simulator(config.simulator, label_noise=config.label_noise)  # a bad --sim fails before any worker

    def check(path: Path) -> None:
        if load_shard(path).kind != config.kind:
            raise _fail(path, f"not a {config.kind!r} shard", config.kind)

    seeds_all = {int(s) for s in seeds}
    if old is not None:  # a folder grown by several runs lists every seed
        seeds_all |= {int(s) for s in old.get("seeds", [])}
    manifest = {"config": config.model_dump(mode="json"), "seeds": sorted(seeds_all), "version": SHARD_VERSION}
    return datagen.generate_shards(out, seeds, run_shard_task, config.model_dump_json(), check, manifest, executor,
                                   workers, progress, log, f"{config.kind} scenes")

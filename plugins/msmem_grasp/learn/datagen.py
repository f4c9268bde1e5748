"""Training data for FE-vMF (paper sec. "Data generation", scaled to a CPU).

Per scene seed: generate a shelf scene, reset the simulator (objects settle; ``simulator``, ``--sim``:
any backend, built by the plugin manager, default PyBullet), observe 3-10
random viewpoints into an analytic belief, project the belief's surface with FPP from those views,
and label every point: positive if it lies within max(2 mm, half a voxel) of a ground-truth antipodal
contact (``grasps_in_scene`` at the settled poses), with the approach, directed baseline and width of
up to ``max_grasps`` GT grasps at that contact (nearest first, padded, masked).

One ``scene_<seed>.npz`` per scene, written atomically (tmp + rename), so a killed run resumes by
skipping the shards that exist and load; a shard that exists but does not load is reported and
regenerated. ``dataset.json`` records the config and the seeds.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.errors import UserError
from msmem_core.learn import datagen
from msmem_core.learn.datagen import DatagenSummary, ShardTask, read_npz, save_npz, shard_path
from msmem_core.plugins import ComponentRef
from msmem_grasp.antipodal import AntipodalConfig, GraspSet
from msmem_grasp.fpp import FPPConfig, SurfaceCloud, frontier_points
from msmem_grasp.learn.losses import GraspTargets, assign_targets

SHARD_VERSION = 1


class GraspDataConfig(BaseModel):
    """How one training scene is made and labelled."""

    model_config = ConfigDict(extra="forbid")

    min_views: int = Field(3, ge=1)
    max_views: int = Field(10, ge=1)
    """Each scene is observed from a uniform number of random viewpoints in [min_views, max_views]."""
    voxel_m: float = Field(0.01, gt=0.001, le=0.05)
    require_hard: bool = False
    """Hard scenes (> 3 objects hidden from all views; slower to generate: docs/explanation/grasp.md) instead of
    the paper's training scenes, plain random arrangements with 30-45 % floor occupancy."""
    label_radius_m: float | None = Field(None, gt=0.0)
    """A point is positive within this distance of a GT contact (None: max(2 mm, half a voxel))."""
    max_grasps: int = Field(16, ge=1)
    """GT grasps kept per positive point (nearest contacts first)."""
    fpp: FPPConfig = FPPConfig()
    antipodal: AntipodalConfig = AntipodalConfig()
    simulator: ComponentRef = ComponentRef(name="pybullet")
    """The backend the scenes settle and are observed in (``--sim``); its ``camera`` is FPP's and its
    ``seed`` the scene seed, unless ``params`` set them."""

    def radius_m(self) -> float:
        return self.label_radius_m if self.label_radius_m is not None else max(0.002, 0.5 * self.voxel_m)


# ------------------------------------------------------------------------------------------ shards
class ShardError(datagen.ShardError):
    """A grasp shard file is missing fields, has inconsistent shapes or cannot be read."""


@dataclass(frozen=True)
class GraspShard:
    """One labelled cloud: N points, P positives, G grasp slots per positive (see module docstring)."""

    points: NDArray[np.float32]  # [N, 3]
    normals: NDArray[np.float32]  # [N, 3]
    occupancy: NDArray[np.float32]  # [N]
    positive_index: NDArray[np.int64]  # [P]
    approach: NDArray[np.float32]  # [P, G, 3]
    baseline: NDArray[np.float32]  # [P, G, 3]
    width: NDArray[np.float32]  # [P, G]
    mask: NDArray[np.bool_]  # [P, G]
    seed: int
    views: NDArray[np.int64]  # viewpoint indices the belief was built from

    def __len__(self) -> int:
        return len(self.points)

    @property
    def label(self) -> NDArray[np.float32]:
        y = np.zeros(len(self.points), np.float32)
        y[self.positive_index] = 1.0
        return y

    def features(self) -> NDArray[np.float32]:
        """FE-vMF input features [N, 4] (``msmem_grasp.fpp.FEATURES``)."""
        return np.concatenate([self.normals, self.occupancy[:, None]], axis=1).astype(np.float32)

    def targets(self) -> GraspTargets:
        return GraspTargets(
            num_points=len(self.points),
            positive_index=torch.from_numpy(self.positive_index),
            approach=torch.from_numpy(self.approach.astype(np.float32)),
            baseline=torch.from_numpy(self.baseline.astype(np.float32)),
            width=torch.from_numpy(self.width.astype(np.float32)),
            mask=torch.from_numpy(self.mask),
        )

    def arrays(self) -> dict[str, NDArray[Any]]:
        out = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self)}
        out["version"] = np.asarray(SHARD_VERSION)
        return out


def _check_shapes(z: dict[str, NDArray[Any]], path: Path) -> None:
    n = z["points"].shape[0]
    p = z["positive_index"].shape[0]
    g = z["mask"].shape[1] if z["mask"].ndim == 2 else -1
    expected = {
        "points": (n, 3), "normals": (n, 3), "occupancy": (n,), "positive_index": (p,),
        "approach": (p, g, 3), "baseline": (p, g, 3), "width": (p, g), "mask": (p, g),
    }
    for key, shape in expected.items():
        if z[key].shape != shape:
            raise ShardError(f"{path}: field {key!r} has shape {z[key].shape}, expected {shape}: the shard is"
                             " inconsistent; rerun `msmem datagen grasp` with the same arguments to regenerate it")
    if p and (z["positive_index"].min() < 0 or z["positive_index"].max() >= n):
        raise ShardError(f"{path}: positive_index out of range [0, {n})")


def load_shard(path: str | Path) -> GraspShard:
    """Read and validate a shard; any problem raises :class:`ShardError` naming the file."""
    path = Path(path)

    def fail(what: str) -> ShardError:
        return ShardError(f"{path}: {what}; rerun `msmem datagen grasp` with the same arguments to regenerate it")

    z = read_npz(path, [f.name for f in fields(GraspShard)], "grasp", fail)
    if int(z["version"]) != SHARD_VERSION:
        raise ShardError(f"{path}: shard version {int(z['version'])}, this msmem reads {SHARD_VERSION}; regenerate")
    _check_shapes(z, path)
    return GraspShard(
        points=z["points"].astype(np.float32), normals=z["normals"].astype(np.float32),
        occupancy=z["occupancy"].astype(np.float32), positive_index=z["positive_index"].astype(np.int64),
        approach=z["approach"].astype(np.float32), baseline=z["baseline"].astype(np.float32),
        width=z["width"].astype(np.float32), mask=z["mask"].astype(bool), seed=int(z["seed"]),
        views=z["views"].astype(np.int64),
    )


def save_shard(path: str | Path, shard: GraspShard) -> None:
    """Write atomically: a temporary file in the same folder, then rename."""
    arrays = shard.arrays()
    for key in ("approach", "baseline"):
        arrays[key] = arrays[key].astype(np.float16)  # unit vectors: 1e-3 is plenty, halves the size
    save_npz(path, arrays)


def list_shards(data_dir: str | Path) -> list[Path]:
    """The shards of a data folder, sorted; a missing or empty folder is a clear error."""
    return datagen.list_shards(data_dir, f"`msmem datagen grasp --out {Path(data_dir)}`")


# ------------------------------------------------------------------------------------ one scene
def label_cloud(cloud: SurfaceCloud, grasps: GraspSet, radius_m: float, max_grasps: int) -> GraspTargets:
    """Positives and their GT grasps (``assign_targets``) for a cloud."""
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))  # noqa: E731
    return assign_targets(t(cloud.points), t(grasps.contacts), t(grasps.approach), t(grasps.baseline),
                          t(grasps.width), radius_m=radius_m, max_grasps=max_grasps)


def scene_views(seed: int, config: GraspDataConfig, num_views: int) -> NDArray[np.int64]:
    """The random viewpoint indices of a scene (seeded by the scene seed)."""
    rng = np.random.default_rng([seed, 1])
    k = int(rng.integers(config.min_views, config.max_views + 1))
    return np.sort(rng.choice(num_views, size=min(k, num_views), replace=False)).astype(np.int64)


def make_shard(seed: int, config: GraspDataConfig | None = None) -> GraspShard:
    """Generate, observe, project and label one scene."""
    from msmem_analytic.observation import AnalyticObservationModel

    from msmem_core.map.belief import EvidentialMap
    from msmem_core.sim.build import build_simulator
    from msmem_core.world.grid import GridSpec
    from msmem_core.world.scenegen import SceneGenConfig, generate_scene
    from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints
    from msmem_grasp.antipodal import grasps_in_scene

    cfg = config or GraspDataConfig()
    if cfg.min_views > cfg.max_views:
        raise UserError(f"min_views {cfg.min_views} > max_views {cfg.max_views}")
    gen = SceneGenConfig(require_hard=cfg.require_hard)
    scene = generate_scene(seed, gen)
    grid = GridSpec.around_box(scene.shelf.interior_lower, scene.shelf.interior_upper, cfg.voxel_m, 1)
    poses_all = generate_viewpoints(ViewpointConfig(), scene.shelf)
    views = scene_views(seed, cfg, len(poses_all))
    sim = build_simulator(cfg.simulator, camera=cfg.fpp.camera, seed=seed)
    try:
        sim.reset(scene)
        model = AnalyticObservationModel()
        belief = EvidentialMap.empty(grid)
        for v in views:
            belief = model.update(belief, sim.observe(poses_all[v]))
        settled = sim.object_poses()
    finally:
        sim.close()
    cloud = frontier_points(belief, poses_all[views], cfg.fpp, seed=seed, shelf=scene.shelf)
    per_object = grasps_in_scene(scene, settled, cfg.antipodal)
    sets = [g for oid, g in per_object.items() if oid in settled and len(g)]
    empty = GraspSet.empty()
    grasps = GraspSet(*(np.concatenate([getattr(g, f.name) for g in sets]) if sets else getattr(empty, f.name)
                        for f in fields(GraspSet)))
    tg = label_cloud(cloud, grasps, cfg.radius_m(), cfg.max_grasps)
    return GraspShard(
        points=cloud.points, normals=cloud.normals, occupancy=cloud.occupancy,
        positive_index=tg.positive_index.numpy().astype(np.int64),
        approach=tg.approach.numpy().astype(np.float32), baseline=tg.baseline.numpy().astype(np.float32),
        width=tg.width.numpy().astype(np.float32), mask=tg.mask.numpy().astype(bool),
        seed=seed, views=views,
    )


def run_shard_task(task: ShardTask) -> dict[str, Any]:
    """Executor entry point: make and write one shard; returns a small summary."""
    t0 = time.perf_counter()
    cfg = GraspDataConfig.model_validate_json(task.config_json)
    shard = make_shard(task.seed, cfg)
    path = shard_path(task.out, task.seed)
    save_shard(path, shard)
    return {"seed": task.seed, "points": len(shard), "positives": len(shard.positive_index),
            "seconds": time.perf_counter() - t0, "bytes": path.stat().st_size}


# ---------------------------------------------------------------------------------------- dataset
def generate_dataset(
    out_dir: str | Path,
    seeds: Sequence[int],
    config: GraspDataConfig | None = None,
    executor: str = "local",
    workers: int = 1,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> DatagenSummary:
    """Make the shards of ``seeds`` in ``out_dir`` that are missing (or corrupt), in parallel."""
    from msmem_core.sim.build import check_simulator

    cfg = config or GraspDataConfig()
    datagen.check_same_simulator(out_dir, datagen.read_manifest(out_dir), cfg.simulator)
    check_simulator(cfg.simulator, camera=cfg.fpp.camera)  # a bad --sim fails before any worker starts
    manifest = {"config": cfg.model_dump(mode="json"), "seeds": [int(s) for s in seeds], "version": SHARD_VERSION}
    return datagen.generate_shards(out_dir, seeds, run_shard_task, cfg.model_dump_json(), load_shard, manifest,
                                   executor, workers, progress, log, "scenes")

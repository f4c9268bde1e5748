"""The map ceiling of views alone, and what removing occluders is worth (``msmem eval ceiling``).

Per scene, N evenly spaced viewpoints of the run's viewpoint set are integrated, in index order, by
each observation model asked for, into an empty belief; the map is scored with the paper's metrics
(occupancy mIoU, 2-D semantic mIoU, on the shelf interior). The same is done on **oracle variants**
of the scene, built from the ground truth as a perfect grasp would leave it:

- ``scene``: the scene as it is;
- ``front-occluder``: without the one visible object that hides the most hidden objects;
- ``all-occluders``: without every visible object that hides a hidden object.

An object is *hidden* when the N views see fewer than ``min_pixels`` strided pixels of it
(``msmem_core.world.visibility``); object O *hides* H when a ray that would hit H alone in the
empty shelf hits O first (``visibility.occluders``). Hidden objects are never removed: a grasp can
only take what the camera sees. The difference between a variant's score and the scene's is the
headroom a manipulation policy can at best exploit with that observation model; the ``scene`` row
is the most views alone can give.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.config import RunConfig
from msmem_core.errors import UserError
from msmem_core.interfaces import ObservationModel
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import ComponentRef
from msmem_core.run.metrics import paper_metrics_from_counts, sum_paper_counts
from msmem_core.run.runner import MetricTracker, build_episode, run_wide
from msmem_core.world.camera import CameraConfig
from msmem_core.world.scene import SceneSpec
from msmem_core.world.visibility import MIN_VISIBLE_PIXELS, occluders, visible_objects

VARIANTS = ("scene", "front-occluder", "all-occluders")
"""The oracle variants, in the order they are reported."""


@dataclass(frozen=True)
class Variant:
    """A scene with some objects removed (``removed``: their ids), and why."""

    name: str
    scene: SceneSpec
    removed: tuple[int, ...]
    hidden: tuple[int, ...]
    """The objects hidden from the views in the scene as it is."""


def evenly_spaced(num_views: int, n: int) -> NDArray[np.int64]:
    """``n`` view indices spread evenly over ``0 .. num_views - 1`` (all of them when n >= num_views)."""
    if n < 1:
        raise UserError(f"--views must be at least 1, got {n}")
    if n >= num_views:
        return np.arange(num_views, dtype=np.int64)
    return np.unique(np.round(np.linspace(0, num_views - 1, n)).astype(np.int64))


def oracle_variants(scene: SceneSpec, viewpoints: NDArray[np.float64], camera: CameraConfig,
                    names: Sequence[str] = VARIANTS, stride: int = 4,
                    min_pixels: int = MIN_VISIBLE_PIXELS) -> list[Variant]:
    """The requested variants of ``scene`` for these viewpoints (module docstring)."""
    bad = [n for n in names if n not in VARIANTS]
    if bad:
        raise UserError(f"unknown variant {', '.join(bad)}; variants: {', '.join(VARIANTS)}")
    hidden = visible_objects(scene.objects, scene.shelf, viewpoints, camera, stride).hidden(min_pixels)
    hides: dict[int, set[int]] = {}
    pixels: dict[int, int] = {}
    for target, by in occluders(scene.objects, hidden, scene.shelf, viewpoints, camera, stride).items():
        for o, px in by.items():
            if o in hidden:
                continue
            hides.setdefault(o, set()).add(target)
            pixels[o] = pixels.get(o, 0) + px
    removed: dict[str, tuple[int, ...]] = {"scene": ()}
    front = max(hides, key=lambda o: (len(hides[o]), pixels[o], -o)) if hides else None
    removed["front-occluder"] = () if front is None else (front,)
    removed["all-occluders"] = tuple(sorted(hides))
    out = []
    for name in names:
        gone = set(removed[name])
        sub = scene.model_copy(update={"objects": tuple(o for o in scene.objects if o.id not in gone)})
        out.append(Variant(name, sub, removed[name], tuple(hidden)))
    return out


@dataclass
class CeilingRow:
    """One scene variant mapped by one observation model."""

    scene: int
    variant: str
    model: str
    removed: tuple[int, ...]
    hidden: tuple[int, ...]
    metrics: dict[str, float]
    counts: dict[str, Any] = field(repr=False)

    def as_dict(self) -> dict[str, Any]:
        return {"scene": self.scene, "variant": self.variant, "model": self.model, "removed": list(self.removed),
                "hidden": list(self.hidden), **{k: self.metrics[k] for k in ("occupancy_miou", "semantic_miou_2d")}}


def model_refs(cfg: RunConfig, names: Sequence[str]) -> list[ComponentRef]:
    """The observation models to compare: the config's own for ``default``, else a name with no params."""
    return [cfg.observation_model if n == "default" else ComponentRef(name=n) for n in names]


def map_variant(cfg: RunConfig, pm: Any, variant: Variant, views: NDArray[np.int64],
                models: Sequence[tuple[str, ObservationModel]], scene_index: int) -> list[CeilingRow]:
    """Render the variant's views once and integrate them with every model."""
    ep = build_episode(cfg, pm, scene=variant.scene)
    try:
        ep.sim.reset(ep.scene)
        truth = MetricTracker(ep)
        frames = [ep.sim.observe(ep.viewpoints[v]) for v in views]
        rows = []
        for name, model in models:
            belief = EvidentialMap.empty(ep.ig.grid, ep.scene.num_classes)
            for obs in frames:
                belief = model.update(belief, obs)
            m = truth(belief)
            rows.append(CeilingRow(scene_index, variant.name, name, variant.removed, variant.hidden, m,
                                   dict(truth.paper_counts)))
        return rows
    finally:
        ep.sim.close()


def ceiling(cfg: RunConfig, pm: Any, scenes: Sequence[tuple[int, SceneSpec]], num_views: int = 100,
            observe: Sequence[str] = ("default", "analytic-observation"), variants: Sequence[str] = VARIANTS,
            progress: bool = True) -> list[CeilingRow]:
    """Every (scene, variant, observation model) mapped with ``num_views`` evenly spaced views."""
    if bad := [n for n in variants if n not in VARIANTS]:
        raise UserError(f"unknown variant {', '.join(bad)}; variants: {', '.join(VARIANTS)}")
    refs = model_refs(cfg, observe)
    common = run_wide(cfg)
    rows: list[CeilingRow] = []
    bar = task = None
    if progress:
        from msmem_core.util.progress import progress_bar

        bar = progress_bar("ceiling", "{task.description}")
        task = bar.add_task("", total=len(scenes) * len(variants))
    try:
        for index, scene in scenes:
            ep0 = build_episode(cfg, pm, scene=scene)
            views = evenly_spaced(len(ep0.viewpoints), num_views)
            viewpoints, camera = ep0.viewpoints[views], cfg.camera
            ep0.sim.close()
            models = []
            for ref, name in zip(refs, observe, strict=True):
                model = pm.build("belief-model", ref, where="--observe", **common)
                if not isinstance(model, ObservationModel):
                    raise UserError(f"--observe {ref.name}: this belief model cannot update from observations")
                models.append((ref.name if name != "default" else f"{ref.name} (config)", model))
            for variant in oracle_variants(scene, viewpoints, camera, variants):
                rows.extend(map_variant(cfg, pm, variant, views, models, index))
                if bar is not None:
                    bar.update(task, advance=1, description=f"scene {index} {variant.name}")
    finally:
        if bar is not None:
            bar.stop()
    return rows


def summary(rows: Sequence[CeilingRow]) -> list[dict[str, Any]]:
    """Per (variant, model): the pooled paper metrics (counts summed over scenes, as the reference's
    ``Cumulative_mIoU``) and the per-scene mean."""
    out = []
    keys = ("occupancy_miou", "semantic_miou_2d")
    for variant in dict.fromkeys(r.variant for r in rows):
        for model in dict.fromkeys(r.model for r in rows):
            sel = [r for r in rows if r.variant == variant and r.model == model]
            if not sel:
                continue
            pooled = paper_metrics_from_counts(sum_paper_counts([r.counts for r in sel]))
            out.append({"variant": variant, "model": model, "scenes": len(sel),
                        **{f"pooled_{k}": pooled[k] for k in keys},
                        **{f"mean_{k}": float(np.mean([r.metrics[k] for r in sel])) for k in keys}})
    return out


def format_table(rows: Sequence[CeilingRow]) -> str:
    """Markdown: one line per scene, variant and model, then the pooled and mean summary."""
    lines = ["| scene | variant | removed | observation model | occupancy mIoU | 2-D semantic mIoU |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.scene} | {r.variant} | {','.join(map(str, r.removed)) or '-'} | {r.model} | "
                     f"{r.metrics['occupancy_miou']:.3f} | {r.metrics['semantic_miou_2d']:.3f} |")
    lines += ["", "| variant | observation model | scenes | occupancy mIoU pooled (mean) | "
              "2-D semantic mIoU pooled (mean) |", "|---|---|---|---|---|"]
    for s in summary(rows):
        lines.append(f"| {s['variant']} | {s['model']} | {s['scenes']} | {s['pooled_occupancy_miou']:.3f} "
                     f"({s['mean_occupancy_miou']:.3f}) | {s['pooled_semantic_miou_2d']:.3f} "
                     f"({s['mean_semantic_miou_2d']:.3f}) |")
    return "\n".join(lines)

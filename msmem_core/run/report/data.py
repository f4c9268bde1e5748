"""What a run report shows, computed from a run folder (:func:`msmem_core.run.runfolder.load_run`): the
voxels of a belief and of the ground truth, the camera path, the executed manipulations, the arm, the shelf
outline and the run's summary. Numpy only: the figures (:mod:`msmem_core.run.report.figures`) draw these.

Only surface voxels (an occupied voxel with a free 6-neighbour) are kept: the picture is the same and the
file several times smaller. The shelf boards (outside the interior) are left out; the interior is outlined.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.map.belief import EvidentialMap
from msmem_core.run.runfolder import RunData
from msmem_core.world.grid import GridSpec

METRIC_KEYS = ("occupancy_iou", "observable_iou", "semantic_miou", "semantic_miou_bev")
PAPER_METRIC_KEYS = ("occupancy_miou", "semantic_miou_2d")
"""The paper's own mIoUs (docs/reference/metrics.md), drawn dashed beside METRIC_KEYS; runs from before them lack
them."""
PAPER_SUMMARY_KEYS = (*PAPER_METRIC_KEYS, "occupancy_ece", "semantic_ece")


# --------------------------------------------------------------------------------------- geometry
def _interior(shelf: Any, grid: GridSpec) -> NDArray[np.bool_]:
    """Voxels inside the shelf interior or in front of it (everything but the boards)."""
    c = grid.centers()
    lo, hi = shelf.interior_lower, shelf.interior_upper
    return np.all((c > lo) & (c < hi), axis=-1) | ((c[..., 1] < lo[1]) & np.all(c[..., [0, 2]] > lo[[0, 2]], axis=-1)
                                                    & np.all(c[..., [0, 2]] < hi[[0, 2]], axis=-1))


def surface(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Voxels of ``mask`` with at least one 6-neighbour outside it."""
    m = np.pad(mask, 1)
    inner = m[1:-1, 1:-1, 1:-1].copy()
    for ax in range(3):
        for sh in (-1, 1):
            inner &= np.roll(m, sh, axis=ax)[1:-1, 1:-1, 1:-1]
    return mask & ~inner


@dataclass
class VoxelLayer:
    """Points to draw for one belief or ground truth: centres, class ids and per-point values."""

    xyz: NDArray[np.float32]
    cls: NDArray[np.int16]
    values: dict[str, NDArray[np.float32]] = field(default_factory=dict)


def belief_layer(belief: EvidentialMap, shelf: Any, tau_chi: float) -> VoxelLayer:
    """Surface voxels with expected occupancy > 0.5 (boards excluded), argmax class (-1 unknown),
    occupancy probability, semantic vacuity and occupancy entropy (nats)."""
    p = belief.expected_occupancy()
    keep = surface((p > 0.5) & _interior(shelf, belief.grid))
    c = belief.grid.centers()[keep].astype(np.float32)
    return VoxelLayer(c, belief.argmax_class(tau_chi)[keep].astype(np.int16), {
        "occupancy": p[keep].astype(np.float32),
        "vacuity": belief.vacuity()[keep].astype(np.float32),
        "occupancy entropy": belief.occupancy_entropy()[keep].astype(np.float32),
    })


def gt_layer(grid: GridSpec, occ: NDArray[np.bool_], cls: NDArray[np.integer]) -> VoxelLayer:
    keep = surface(np.asarray(occ, dtype=bool))
    return VoxelLayer(grid.centers()[keep].astype(np.float32), np.asarray(cls)[keep].astype(np.int16))


def camera_path(run: RunData, upto: int) -> list[tuple[str, NDArray[np.float64]]]:
    """(label, camera-to-world pose) of the start view and every view chosen at steps <= ``upto``."""
    from msmem_core.world.viewpoints import default_start_view, generate_viewpoints

    cfg = run.config
    views = generate_viewpoints(cfg.viewpoints, run.scene.shelf)
    start = cfg.msas.start_view if cfg.msas.start_view is not None else default_start_view(cfg.viewpoints)
    out = [("start", views[start])]
    for rec in run.steps:
        v = rec["action"].get("view")  # PerceptionAction.view, the viewpoint's index: not a skill name
        if rec["step"] <= upto and isinstance(v, int) and 0 <= v < len(views):
            out.append((str(rec["step"]), views[v]))
    return out


def arm_at(run: RunData, upto: int) -> tuple[int, NDArray[np.float64]] | None:
    """(step, [L, 3] points) of the arm in the last step <= ``upto`` whose record has its configuration
    (``arm.points``: runs with a robot that has an arm); None when there is none."""
    found = None
    for rec in run.steps:
        arm = rec.get("arm") or {}
        if rec["step"] <= upto and arm.get("points"):
            found = (int(rec["step"]), np.asarray(arm["points"], dtype=np.float64))
    return found


@dataclass
class Arrow:
    step: int
    kind: str
    start: NDArray[np.float64]
    end: NDArray[np.float64]


def arrow_of(action: dict[str, Any]) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Start and end (3-D) of an action with ``start_m``, ``direction`` and ``length_m``; a 2-D start
    is lifted to ``height_m`` (or 5 cm)."""
    if not all(k in action for k in ("start_m", "direction", "length_m")):
        return None
    try:
        s = np.asarray(action["start_m"], dtype=np.float64).ravel()
        u = np.asarray(action["direction"], dtype=np.float64).ravel()
        length = float(action["length_m"])
    except (TypeError, ValueError):
        return None
    z = float(action.get("height_m", 0.05)) if len(s) == 2 else None
    s3 = np.array([*s[:2], z]) if z is not None else s[:3]
    u3 = np.array([*u[:2], 0.0]) if len(u) == 2 else u[:3]
    n = float(np.linalg.norm(u3))
    if len(s3) != 3 or len(u3) != 3 or n < 1e-12 or not math.isfinite(length):
        return None
    return s3, s3 + length * u3 / n


def pose_of(action: dict[str, Any]) -> NDArray[np.float64] | None:
    """A 4x4 ``pose`` or ``grasp_pose`` of an action."""
    for key in ("grasp_pose", "pose"):
        if key in action:
            try:
                t = np.asarray(action[key], dtype=np.float64)
            except (TypeError, ValueError):
                continue
            if t.shape == (4, 4) and np.all(np.isfinite(t)):
                return t
    return None


def gripper_segments(pose: NDArray[np.float64], gripper: Any, opening_m: float) -> list[NDArray[np.float64]]:
    """Edges (pairs of world points) of the gripper's finger and palm boxes at ``pose``."""
    segs = []
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    edges = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
    for centre, half in gripper.boxes(opening_m):
        local = centre + corners * half
        world = local @ pose[:3, :3].T + pose[:3, 3]
        segs += [np.stack([world[i], world[j]]) for i, j in edges]
    return segs


def manipulations(run: RunData, upto: int) -> tuple[list[Arrow], list[tuple[int, str, NDArray[np.float64], float]]]:
    """Arrows and gripper poses (step, kind, pose, opening) of the actions executed at steps <= ``upto``."""
    arrows, grasps = [], []
    for rec in run.steps:
        if rec["step"] > upto:
            continue
        a = rec["action"]
        ar = arrow_of(a)
        if ar is not None:
            arrows.append(Arrow(rec["step"], str(a.get("kind", rec["skill"])), *ar))
        t = pose_of(a)
        if t is not None:
            opening = a.get("width_m", a.get("opening_m", run.config.gripper.max_opening_m))
            grasps.append((rec["step"], str(a.get("kind", rec["skill"])), t, float(opening)))
    return arrows, grasps


def shelf_edges(shelf: Any) -> list[NDArray[np.float64]]:
    lo, hi = shelf.interior_lower, shelf.interior_upper
    pts = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return [np.stack([pts[i], pts[j]]) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]


# ---------------------------------------------------------------------------------------- summary
def summary_rows(run: RunData) -> list[tuple[str, str]]:
    """(label, text) rows of the run's summary: what ran, on which scene, and its final metrics."""
    cfg, m = run.config, run.metrics
    hidden = run.scene.hidden_objects
    rows = [
        ("run folder", str(run.run_dir)), ("method", cfg.method), ("scene", run.scene.name),
        ("objects (hidden from all views)", f"{len(run.scene.objects)} ({'?' if hidden is None else hidden})"),
        ("simulator", cfg.simulator.name), ("skills", ", ".join(s.name for s in cfg.skills)),
        ("objective", " + ".join(f"{t.weight:g} * {t.name}" for t in cfg.objective)),
        ("steps", str(len(run.steps))), ("actions", json.dumps(m.get("actions", {}))),
    ]
    rows += [(k, f"{m[k]:.4g}") for k in (*METRIC_KEYS, "position_change_m", "seconds_per_step") if k in m]
    rows += [(f"{k} (paper)", f"{m[k]:.4g}") for k in PAPER_SUMMARY_KEYS if k in m]
    return rows

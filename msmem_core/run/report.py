"""Run reports: an interactive, self-contained ``report.html`` and PNG snapshots of a run folder.

``write_report(run_dir)`` reads what the runner wrote (``config.json``, ``scene.json``,
``steps.jsonl``, ``metrics.json``, ``belief_step{N}.npz``, ``belief_final.npz``, ``gt_final.npz``)
and writes:

- ``report.html``: plotly with plotly.js inline (opens offline). A 3-D view of the belief at the
  snapshot steps (voxels with expected occupancy > 0.5, coloured by argmax class, or by semantic
  vacuity or occupancy entropy: a toggle) beside the ground truth at the same step, the camera path
  (chosen viewpoints with step numbers) and the executed manipulations, drawn generically from
  ``steps.jsonl``: an action with ``start_m`` + ``direction`` + ``length_m`` is an arrow (pushes,
  nudges), one with a 4x4 ``pose`` or ``grasp_pose`` a gripper glyph (grasps). Below it: IoU,
  Position Change, objective terms and the best value of every skill per step, with the chosen
  action kind marked, and a table of the steps.
- ``report_metrics.png`` and ``report_belief.png``: the same curves and a 3-D scatter of the final
  belief against the ground truth (matplotlib, Agg), for papers and terminals.

Only surface voxels (an occupied voxel with a free 6-neighbour) are drawn: the picture is the same and
the file several times smaller. The shelf boards (outside the interior) are not drawn as voxels; the
interior is outlined. This module is numpy-only at import; plotly and matplotlib load lazily.
"""

from __future__ import annotations

import html
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.map.belief import EvidentialMap
from msmem_core.run.runfolder import RunData, load_run
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import SceneSpec

CLASS_COLORS: tuple[str, ...] = (
    "#b0b0b0", "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
    "#7f7f7f", "#bcbd22", "#17becf", "#aec7e8", "#ffbb78", "#98df8a", "#ff9896",
)
"""Colour of each built-in class id (0 background, grey) in every report figure."""
EXTRA_COLORS: tuple[str, ...] = ("#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#5254a3", "#8ca252",
                                 "#bd9e39", "#ad494a", "#a55194")
"""Colours of a scene's own classes without ``color_rgb``, in turn."""
UNKNOWN_COLOR = "#202020"
"""Colour of occupied voxels whose class is unknown (vacuity >= tau_chi)."""
SKILL_SYMBOLS = ("circle", "diamond", "square", "x", "triangle-up", "cross", "star")
REPORT_FILES = ("report.html", "report_metrics.png", "report_belief.png")
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


def _polyline(segs: list[NDArray[np.float64]]) -> tuple[list[float | None], ...]:
    xs: list[float | None] = []
    ys: list[float | None] = []
    zs: list[float | None] = []
    for s in segs:
        for p in s:
            xs.append(round(float(p[0]), 4))
            ys.append(round(float(p[1]), 4))
            zs.append(round(float(p[2]), 4))
        xs.append(None)
        ys.append(None)
        zs.append(None)
    return xs, ys, zs


# ------------------------------------------------------------------------------------- plotly figures
def class_palette(scene: SceneSpec) -> tuple[list[str], list[str]]:
    """(names, colours) of class ids -1 (unknown), 0 (background), 1, ... for a scene: the built-ins'
    colours, then each of the scene's own classes' ``color_rgb`` or the next of ``EXTRA_COLORS``."""
    colors = [UNKNOWN_COLOR, *CLASS_COLORS]
    for i, c in enumerate(scene.object_classes[len(CLASS_COLORS) - 1:]):
        rgb = c.color_rgb
        colors.append("#" + "".join(f"{round(255 * v):02x}" for v in rgb) if rgb is not None
                      else EXTRA_COLORS[i % len(EXTRA_COLORS)])
    return ["unknown", *scene.class_names], colors


def _class_colorscale(colors: list[str]) -> list[list[float | str]]:
    """Discrete colour scale over ids -1 (unknown) .. C-1, for cmin = -1.5, cmax = C - 0.5."""
    n = len(colors)
    scale: list[list[float | str]] = []
    for i, c in enumerate(colors):
        scale += [[i / n, c], [(i + 1) / n, c]]
    return scale


def _class_marker(cls: NDArray[np.int16], show_scale: bool, palette: tuple[list[str], list[str]]) -> dict[str, Any]:
    names, colors = palette
    n = len(colors) - 1
    return {
        "color": cls, "colorscale": _class_colorscale(colors), "cmin": -1.5, "cmax": n - 0.5, "showscale": show_scale,
        "colorbar": {"title": {"text": "class"}, "tickvals": list(range(-1, n)),
                     "ticktext": names, "len": 0.9, "x": 1.02},
    }


COLOURINGS = (
    ("class", None, None, None),
    ("vacuity", "Viridis", 0.0, 1.0),
    ("occupancy entropy", "Viridis", 0.0, math.log(2.0)),
)
"""(name, colour scale, cmin, cmax) of the belief colourings the report toggles between."""


def figure_3d(run: RunData) -> Any:
    """The belief at every snapshot step beside the ground truth, with camera path and manipulations."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    cfg, shelf = run.config, run.scene.shelf
    palette = class_palette(run.scene)
    names_all = np.array(palette[0])
    fig = make_subplots(rows=1, cols=2, specs=[[{"type": "scene"}, {"type": "scene"}]], horizontal_spacing=0.02,
                        subplot_titles=("belief", "ground truth"))
    edges = _polyline(shelf_edges(shelf))
    always: list[int] = []
    for col in (1, 2):
        fig.add_trace(go.Scatter3d(x=edges[0], y=edges[1], z=edges[2], mode="lines", name="shelf interior",
                                   line={"color": "#555", "width": 2}, hoverinfo="skip", showlegend=col == 1),
                      row=1, col=col)
        always.append(len(fig.data) - 1)
    groups: list[list[int]] = []
    belief_traces: list[int] = []
    layers: list[VoxelLayer] = []
    shown = len(run.snapshots) - 1  # the final belief is shown first; buttons select the others
    for si, snap in enumerate(run.snapshots):
        first = si == shown
        idx: list[int] = []
        bl = belief_layer(snap.belief, shelf, cfg.msas.tau_chi)
        layers.append(bl)
        names = names_all[bl.cls + 1]
        custom = np.stack([bl.values["occupancy"], bl.values["vacuity"], bl.values["occupancy entropy"]], axis=1)
        fig.add_trace(go.Scatter3d(
            x=bl.xyz[:, 0], y=bl.xyz[:, 1], z=bl.xyz[:, 2], mode="markers", name="belief p > 0.5",
            marker={"size": 2.5, "symbol": "square", **_class_marker(bl.cls, True, palette)},
            text=names, customdata=custom, visible=first, legendgroup="belief",
            hovertemplate="%{text}<br>p %{customdata[0]:.2f}, vacuity %{customdata[1]:.2f}, "
                          "H_occ %{customdata[2]:.2f}<extra>belief</extra>"), row=1, col=1)
        idx.append(len(fig.data) - 1)
        belief_traces.append(len(fig.data) - 1)
        gl = gt_layer(snap.belief.grid, snap.gt_occ, snap.gt_cls)
        fig.add_trace(go.Scatter3d(
            x=gl.xyz[:, 0], y=gl.xyz[:, 1], z=gl.xyz[:, 2], mode="markers", name="ground truth",
            marker={"size": 2.5, "symbol": "square", **_class_marker(gl.cls, False, palette)},
            text=names_all[np.clip(gl.cls, 0, len(names_all) - 2) + 1], visible=first,
            hovertemplate="%{text}<extra>ground truth</extra>"), row=1, col=2)
        idx.append(len(fig.data) - 1)
        cams = camera_path(run, snap.step)
        pos = np.array([t[:3, 3] for _, t in cams])
        fig.add_trace(go.Scatter3d(
            x=pos[:, 0], y=pos[:, 1], z=pos[:, 2], mode="lines+markers+text", name="camera path",
            text=[lab for lab, _ in cams], textposition="top center", visible=first,
            marker={"size": 4, "color": "#d62728"}, line={"color": "#d62728", "width": 3},
            hovertemplate="view at step %{text}<extra>camera</extra>"), row=1, col=1)
        idx.append(len(fig.data) - 1)
        looks = _polyline([np.stack([t[:3, 3], t[:3, 3] + 0.08 * t[:3, 2]]) for _, t in cams])
        fig.add_trace(go.Scatter3d(x=looks[0], y=looks[1], z=looks[2], mode="lines", name="viewing direction",
                                   line={"color": "#ff9896", "width": 4}, visible=first, hoverinfo="skip"),
                      row=1, col=1)
        idx.append(len(fig.data) - 1)
        arrows, grasps = manipulations(run, snap.step)
        for col in (1, 2):
            if arrows:
                segs = _polyline([np.stack([a.start, a.end]) for a in arrows])
                fig.add_trace(go.Scatter3d(
                    x=segs[0], y=segs[1], z=segs[2], mode="lines", name="push / nudge path",
                    line={"color": "#000", "width": 6}, visible=first, showlegend=col == 1,
                    hoverinfo="skip"), row=1, col=col)
                idx.append(len(fig.data) - 1)
                ends = np.array([a.end for a in arrows])
                dirs = np.array([(a.end - a.start) / max(float(np.linalg.norm(a.end - a.start)), 1e-9)
                                 for a in arrows])
                fig.add_trace(go.Cone(
                    x=ends[:, 0], y=ends[:, 1], z=ends[:, 2], u=dirs[:, 0], v=dirs[:, 1], w=dirs[:, 2],
                    anchor="tip", sizemode="absolute", sizeref=0.03, showscale=False,
                    colorscale=[[0, "#000"], [1, "#000"]], visible=first, name="manipulation",
                    text=[f"{a.kind} at step {a.step}" for a in arrows],
                    hovertemplate="%{text}<extra></extra>"), row=1, col=col)
                idx.append(len(fig.data) - 1)
            if grasps:
                segs = _polyline([s for _, _, t, w in grasps for s in gripper_segments(t, cfg.gripper, w)])
                fig.add_trace(go.Scatter3d(
                    x=segs[0], y=segs[1], z=segs[2], mode="lines", name="grasp",  # glyph legend, not a skill name
                    line={"color": "#9467bd", "width": 4}, visible=first, showlegend=col == 1,
                    hoverinfo="skip"), row=1, col=col)
                idx.append(len(fig.data) - 1)
        arm = arm_at(run, snap.step)
        if arm is not None:
            for col in (1, 2):
                fig.add_trace(go.Scatter3d(
                    x=arm[1][:, 0], y=arm[1][:, 1], z=arm[1][:, 2], mode="lines+markers", name=f"arm (step {arm[0]})",
                    line={"color": "#7f7f7f", "width": 9}, marker={"size": 3, "color": "#444"}, visible=first,
                    showlegend=col == 1, hoverinfo="skip"), row=1, col=col)
                idx.append(len(fig.data) - 1)
        groups.append(idx)

    n = len(fig.data)
    step_buttons = []
    for si, (snap, idx) in enumerate(zip(run.snapshots, groups, strict=True)):
        vis = [i in always or i in idx for i in range(n)]
        step_buttons.append({"label": f"step {snap.step}" + (" (final)" if si == len(groups) - 1 else ""),
                             "method": "update",
                             "args": [{"visible": vis}, {"annotations[0].text": f"belief {snap.label}",
                                                         "annotations[1].text": f"ground truth {snap.label}"}]})
    colour_buttons = []
    for name, scale, lo, hi in COLOURINGS:
        args: dict[str, Any]
        if scale is None:
            markers = [_class_marker(layer.cls, True, palette) for layer in layers]
            args = {f"marker.{k}": [m[k] for m in markers] for k in ("color", "colorscale", "cmin", "cmax", "colorbar")}
        else:
            args = {"marker.color": [layer.values[name] for layer in layers],
                    "marker.colorscale": scale, "marker.cmin": lo, "marker.cmax": hi,
                    "marker.colorbar": {"title": {"text": name}, "len": 0.9, "x": 1.02}}
        colour_buttons.append({"label": f"colour: {name}", "method": "restyle", "args": [args, belief_traces]})
    fig.layout.annotations[0].text = f"belief {run.snapshots[shown].label}"
    fig.layout.annotations[1].text = f"ground truth {run.snapshots[shown].label}"
    # both scenes show the same box (shelf and every camera), so the synchronised views match
    cam_xyz = np.array([t[:3, 3] for _, t in camera_path(run, len(run.steps))]
                       + [p for r in run.steps for p in (r.get("arm") or {}).get("points", [])])
    box_lo = np.minimum(shelf.interior_lower, cam_xyz.min(axis=0)) - 0.03
    box_hi = np.maximum(shelf.interior_upper, cam_xyz.max(axis=0)) + 0.03
    ext = box_hi - box_lo
    axes = {f"{a}axis": {"title": {"text": f"{a} (m)"}, "range": [float(box_lo[i]), float(box_hi[i])]}
            for i, a in enumerate("xyz")}
    scene = {"aspectmode": "manual", "aspectratio": dict(zip("xyz", (ext / ext.max()).tolist(), strict=True)),
             "camera": {"eye": {"x": 0.2, "y": -1.15, "z": 0.65}}, **axes}
    fig.update_layout(
        height=680, margin={"l": 0, "r": 0, "t": 70, "b": 0}, scene=scene, scene2=scene,
        legend={"orientation": "h", "x": 0.0, "y": -0.02, "yanchor": "top"},
        updatemenus=[
            {"type": "buttons", "direction": "right", "x": 0.0, "y": 1.13, "xanchor": "left", "buttons": step_buttons,
             "showactive": True, "active": shown},
            {"type": "dropdown", "x": 0.6, "y": 1.13, "xanchor": "left", "buttons": colour_buttons, "active": 0},
        ],
    )
    return fig


def _skill_symbols(run: RunData) -> dict[str, str]:
    skills = [s["skill"] for s in run.steps]
    order = list(dict.fromkeys([r.name for r in run.config.skills] + skills))
    return {s: SKILL_SYMBOLS[i % len(SKILL_SYMBOLS)] for i, s in enumerate(order)}


def figure_metrics(run: RunData) -> Any:
    """IoU, Position Change, objective terms and best value per skill per step, action kinds marked."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    steps = [r["step"] for r in run.steps]
    initial = run.metrics.get("initial", {})
    fig = make_subplots(rows=4, cols=1, shared_xaxes=True, vertical_spacing=0.06,
                        subplot_titles=("IoU (step -1: the start view)", "Position Change (m)",
                                        "objective of the chosen action and its terms",
                                        "best objective value of each skill"))
    x0 = [-1] if initial else []
    for key in METRIC_KEYS:
        ys = ([initial[key]] if initial else []) + [r["metrics"].get(key) for r in run.steps]
        fig.add_trace(go.Scatter(x=x0 + steps, y=ys, mode="lines+markers", name=key, legendgroup="iou"), row=1, col=1)
    for key in PAPER_METRIC_KEYS:
        if any(key in r["metrics"] for r in run.steps):
            ys = ([initial.get(key)] if initial else []) + [r["metrics"].get(key) for r in run.steps]
            fig.add_trace(go.Scatter(x=x0 + steps, y=ys, mode="lines+markers", name=f"{key} (paper)",
                                     line={"dash": "dash"}, legendgroup="iou"), row=1, col=1)
    ys = ([initial.get("position_change_m", 0.0)] if initial else []) + [
        r["metrics"].get("position_change_m") for r in run.steps]
    fig.add_trace(go.Scatter(x=x0 + steps, y=ys, mode="lines+markers", name="position_change_m"), row=2, col=1)
    fig.add_trace(go.Scatter(x=steps, y=[r["objective"] for r in run.steps], mode="lines", name="objective",
                             line={"color": "#333"}), row=3, col=1)
    terms = list(dict.fromkeys(k for r in run.steps for k in r.get("terms", {})))
    for t in terms:
        fig.add_trace(go.Scatter(x=steps, y=[r.get("terms", {}).get(t) for r in run.steps], mode="lines",
                                 name=f"term {t}", line={"dash": "dot"}), row=3, col=1)
    symbols = _skill_symbols(run)
    for skill, sym in symbols.items():
        recs = [r for r in run.steps if r["skill"] == skill]
        if recs:
            fig.add_trace(go.Scatter(
                x=[r["step"] for r in recs], y=[r["objective"] for r in recs], mode="markers",
                name=f"chosen: {skill}", marker={"symbol": sym, "size": 11, "line": {"width": 1, "color": "#000"}},
                customdata=[json.dumps(r["action"])[:300] for r in recs],
                hovertemplate="step %{x}: " + skill + " %{y:.3g}<br>%{customdata}<extra></extra>"), row=3, col=1)
    skills = list(dict.fromkeys(k for r in run.steps for k in r.get("best_per_skill", {})))
    for skill in skills:
        fig.add_trace(go.Scatter(
            x=steps, y=[r.get("best_per_skill", {}).get(skill) for r in run.steps], mode="lines+markers",
            name=f"best {skill}", marker={"symbol": symbols.get(skill, "circle")},
            customdata=[r.get("candidates", {}).get(skill, 0) for r in run.steps],
            hovertemplate="step %{x}: %{y:.3g} (%{customdata} candidates)<extra>" + skill + "</extra>"), row=4, col=1)
    for r in run.steps:
        if r["action"].get("category") == "manipulation":
            fig.add_vrect(x0=r["step"] - 0.4, x1=r["step"] + 0.4, fillcolor="#ffbb78", opacity=0.35, line_width=0)
    fig.update_xaxes(title_text="step", row=4, col=1, dtick=1 if len(steps) <= 40 else None)
    fig.update_layout(height=900, margin={"l": 60, "r": 20, "t": 40, "b": 40}, hovermode="closest")
    return fig


# ------------------------------------------------------------------------------------------- HTML page
_ERROR_HOOK = """<script>
window.msmemErrors = [];
window.addEventListener('error', function (e) { window.msmemErrors.push(String(e.message)); });
(function () { var orig = console.error; console.error = function () {
  window.msmemErrors.push(Array.prototype.join.call(arguments, ' ')); return orig.apply(console, arguments); }; })();
</script>"""

_DONE_SCRIPT = """<script>
function msmemPlotDone() {
  var el = document.getElementById('msmem-status');
  var plots = document.querySelectorAll('.js-plotly-plot');
  var drawn = 0;
  plots.forEach(function (p) {  // a 3-D scene without WebGL shows plotly's .no-webgl notice instead
    if (p._fullLayout && p.dataset.msmemRendered === '1' && !p.querySelector('.no-webgl')) { drawn += 1; }
  });
  el.dataset.plots = String(drawn);
  el.dataset.errors = String(window.msmemErrors.length);
  el.textContent = drawn + ' of ' + el.dataset.expected + ' plots drawn, ' + window.msmemErrors.length + ' errors'
    + (window.msmemErrors.length ? ': ' + window.msmemErrors.join(' | ') : '');
  document.title = 'msmem report: ' + el.dataset.steps + ' steps, ' + drawn + ' plots';
}
window.addEventListener('load', function () { msmemPlotDone(); setTimeout(msmemPlotDone, 1000); });
</script>"""

_SYNC_CAMERAS = """
var gd = document.getElementById('{plot_id}');
gd.dataset.msmemRendered = '1';
var syncing = false;
gd.on('plotly_relayout', function (ev) {
  if (syncing) { return; }
  var out = {};
  if (ev['scene.camera']) { out['scene2.camera'] = ev['scene.camera']; }
  if (ev['scene2.camera']) { out['scene.camera'] = ev['scene2.camera']; }
  if (Object.keys(out).length) { syncing = true; Plotly.relayout(gd, out).then(function () { syncing = false; }); }
});
msmemPlotDone();
"""

_STYLE = """<style>
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; font-size: 0.85em; }
td, th { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
.summary td { text-align: left; }
#msmem-status { color: #888; font-size: 0.8em; }
</style>"""


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def _summary_table(run: RunData) -> str:
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
    return "<table class='summary'>" + "".join(
        f"<tr><th class='l'>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
        for k, v in rows) + "</table>"


def _steps_table(run: RunData) -> str:
    head = ["step", "skill", "objective", "candidates", *METRIC_KEYS, "position_change_m", "seconds", "action"]
    out = ["<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for r in run.steps:
        a = {k: v for k, v in r["action"].items() if k not in ("kind", "category", "tool", "interior_m")}
        cells = [r["step"], r["skill"], r["objective"], json.dumps(r.get("candidates", {})),
                 *(r["metrics"].get(k, "") for k in (*METRIC_KEYS, "position_change_m")), r.get("seconds", "")]
        out.append("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in cells)
                   + f"<td class='l'><code>{html.escape(json.dumps(a)[:160])}</code></td></tr>")
    return "".join(out) + "</table>"


def render_html(run: RunData) -> str:
    """The report page (plotly.js inline: no network needed)."""
    f3d, fm = figure_3d(run), figure_metrics(run)
    post = _SYNC_CAMERAS
    div3d = f3d.to_html(full_html=False, include_plotlyjs=True, post_script=post, config={"responsive": True})
    divm = fm.to_html(full_html=False, include_plotlyjs=False,
                      post_script="document.getElementById('{plot_id}').dataset.msmemRendered = '1'; msmemPlotDone();")
    title = f"msmem report: {run.config.method}, {run.scene.name}, {len(run.steps)} steps"
    snaps = ",".join(str(s.step) for s in run.snapshots)
    return "\n".join([
        "<!DOCTYPE html>", "<html lang='en'><head><meta charset='utf-8'>", f"<title>{html.escape(title)}</title>",
        _ERROR_HOOK, _STYLE, _DONE_SCRIPT, "</head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p id='msmem-status' data-steps='{len(run.steps)}' data-snapshots='{snaps}' data-expected='2'"
        " data-plots='0' data-errors='0'>rendering...</p>",
        _summary_table(run),
        "<h2>Belief and ground truth</h2>",
        "<p>Voxels with expected occupancy &gt; 0.5 (surface voxels; the shelf boards are outlined, not drawn). "
        "Buttons: the step whose belief is shown (the camera path and manipulations up to it); menu: colour by "
        "argmax class (unknown where vacuity &ge; tau_chi), semantic vacuity or occupancy entropy. "
        "Red: camera path (labels are step numbers); black arrows: pushes and nudges; purple: grasps.</p>",
        div3d, "<h2>Metrics per step</h2>", "<p>Shaded: steps whose chosen action was a manipulation.</p>", divm,
        "<h2>Steps</h2>", _steps_table(run), "</body></html>",
    ])


# --------------------------------------------------------------------------------------------- PNGs
def _hex_rgb(c: str) -> tuple[float, float, float]:
    return tuple(int(c[i : i + 2], 16) / 255 for i in (1, 3, 5))  # type: ignore[return-value]


def _class_rgb(cls: NDArray[np.integer], colors: list[str]) -> NDArray[np.float64]:
    table = np.array([_hex_rgb(c) for c in colors])
    return table[np.clip(np.asarray(cls) + 1, 0, len(table) - 1)]


def png_metrics(run: RunData, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(8, 8), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axs = fig.subplots(3, 1, sharex=True)
    steps = [r["step"] for r in run.steps]
    initial = run.metrics.get("initial", {})
    x0 = [-1] if initial else []
    for key in METRIC_KEYS:
        axs[0].plot(x0 + steps, ([initial[key]] if initial else []) + [r["metrics"][key] for r in run.steps],
                    marker=".", label=key)
    for key in PAPER_METRIC_KEYS:
        if all(key in r["metrics"] for r in run.steps):
            ys = ([initial.get(key, np.nan)] if initial else []) + [r["metrics"][key] for r in run.steps]
            axs[0].plot(x0 + steps, ys, marker=".", ls="--", label=f"{key} (paper)")
    axs[0].set_ylabel("IoU")
    axs[0].legend(fontsize=7, loc="best")
    axs[1].plot(x0 + steps, ([initial.get("position_change_m", 0.0)] if initial else [])
                + [r["metrics"]["position_change_m"] for r in run.steps], marker=".", color="#8c564b")
    axs[1].set_ylabel("Position Change (m)")
    axs[2].plot(steps, [r["objective"] for r in run.steps], color="#333", lw=1, label="objective")
    for t in dict.fromkeys(k for r in run.steps for k in r.get("terms", {})):
        axs[2].plot(steps, [r.get("terms", {}).get(t, np.nan) for r in run.steps], ls=":", label=f"term {t}")
    markers = dict(zip(_skill_symbols(run), "oDsx^P*", strict=False))
    for skill, mk in markers.items():
        recs = [r for r in run.steps if r["skill"] == skill]
        if recs:
            axs[2].scatter([r["step"] for r in recs], [r["objective"] for r in recs], marker=mk, s=40,
                           edgecolors="k", zorder=3, label=f"chosen: {skill}")
    axs[2].set_ylabel("objective")
    axs[2].set_xlabel("step")
    axs[2].xaxis.set_major_locator(MaxNLocator(integer=True))
    axs[2].legend(fontsize=7, loc="best")
    for ax in axs:
        for r in run.steps:
            if r["action"].get("category") == "manipulation":
                ax.axvspan(r["step"] - 0.4, r["step"] + 0.4, color="#ffbb78", alpha=0.4, lw=0)
    fig.suptitle(f"{run.config.method}, {run.scene.name}: metrics per step (shaded: manipulation)", fontsize=10)
    fig.savefig(path)


def png_belief(run: RunData, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    snap = run.final
    shelf = run.scene.shelf
    palette = class_palette(run.scene)
    bl = belief_layer(snap.belief, shelf, run.config.msas.tau_chi)
    gl = gt_layer(snap.belief.grid, snap.gt_occ, snap.gt_cls)
    fig = Figure(figsize=(12, 5.2), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    lo, hi = shelf.interior_lower, shelf.interior_upper
    cams = np.array([t[:3, 3] for _, t in camera_path(run, snap.step)])
    arrows, _ = manipulations(run, snap.step)
    arm = arm_at(run, snap.step)
    for i, (layer, title) in enumerate(((bl, f"belief {snap.label} (p > 0.5)"), (gl, "ground truth"))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        ax.scatter(layer.xyz[:, 0], layer.xyz[:, 1], layer.xyz[:, 2], c=_class_rgb(layer.cls, palette[1]), s=2,
                   marker="s", depthshade=False, linewidths=0)
        for seg in shelf_edges(shelf):
            ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color="#555", lw=0.8)
        for a in arrows:
            ax.quiver(*a.start, *(a.end - a.start), color="k", lw=2, arrow_length_ratio=0.3)
        if i == 0 and len(cams):
            ax.plot(cams[:, 0], cams[:, 1], cams[:, 2], "o-", color="#d62728", ms=3, lw=1)
        shown = cams if i == 0 and len(cams) else np.zeros((0, 3))
        if arm is not None:
            ax.plot(arm[1][:, 0], arm[1][:, 1], arm[1][:, 2], "o-", color="#7f7f7f", ms=3, lw=4, mfc="#444")
            shown = np.concatenate([shown, arm[1]])
        ax.set_xlim(min(lo[0], shown[:, 0].min(initial=lo[0])), max(hi[0], shown[:, 0].max(initial=hi[0])))
        ax.set_ylim(min(lo[1], shown[:, 1].min(initial=lo[1])), hi[1])
        ax.set_zlim(min(lo[2], shown[:, 2].min(initial=lo[2])), max(hi[2], shown[:, 2].max(initial=hi[2])))
        xr, yr, zr = (np.ptp(np.array(ax.get_xlim())), np.ptp(np.array(ax.get_ylim())), np.ptp(np.array(ax.get_zlim())))
        ax.set_box_aspect((xr, yr, zr))
        ax.view_init(elev=25, azim=-70)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (m)", fontsize=8)
        ax.set_ylabel("y (m)", fontsize=8)
        ax.set_zlabel("z (m)", fontsize=8)
        ax.tick_params(labelsize=6)
    present = sorted({int(c) for c in np.concatenate([bl.cls, gl.cls])})
    from matplotlib.patches import Patch

    handles = [Patch(color=_class_rgb(np.array([c]), palette[1])[0], label=palette[0][c + 1]) for c in present]
    fig.legend(handles=handles, loc="outside lower center", ncols=min(8, max(1, len(handles))), fontsize=7)
    fig.suptitle(f"{run.config.method}, {run.scene.name}: final belief vs ground truth "
                 f"(occupancy IoU {run.metrics.get('occupancy_iou', float('nan')):.3f})", fontsize=11)
    fig.savefig(path)


# ------------------------------------------------------------------------------------------- entry
def write_report(run_dir: str | Path, png: bool = True) -> list[Path]:
    """Write ``report.html`` (and, with ``png``, the two PNGs) into the run folder; returns the paths."""
    run = load_run(run_dir)
    out = [run.run_dir / "report.html"]
    out[0].write_text(render_html(run), encoding="utf-8")
    if png:
        out += [run.run_dir / "report_metrics.png", run.run_dir / "report_belief.png"]
        png_metrics(run, out[1])
        png_belief(run, out[2])
    return out

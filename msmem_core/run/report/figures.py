"""The run report's figures, drawn from :mod:`msmem_core.run.report.data`.

- plotly (``report.html``): :func:`figure_3d`, the belief at every snapshot step beside the ground truth
  with the camera path, manipulations and arm, a step toggle and a colouring menu (argmax class, semantic
  vacuity, occupancy entropy); :func:`figure_metrics`, IoU, Position Change, objective terms and the best
  value of every skill per step.
- matplotlib (Agg, PNG): :func:`png_metrics` and :func:`png_belief`, the same curves and the final belief
  against the ground truth, for papers and terminals.

plotly and matplotlib load inside the functions: importing this module needs numpy only.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.run.report.data import (
    METRIC_KEYS,
    PAPER_METRIC_KEYS,
    VoxelLayer,
    arm_at,
    belief_layer,
    camera_path,
    gripper_segments,
    gt_layer,
    manipulations,
    shelf_edges,
)
from msmem_core.run.runfolder import RunData
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


def _polyline(segs: list[NDArray[np.float64]]) -> tuple[list[float | None], ...]:
    """Segments as the x, y, z lists of one plotly line trace (None between segments, 4 decimals)."""
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

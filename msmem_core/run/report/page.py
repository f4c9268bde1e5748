"""The run report's page: ``report.html`` from the figures (:mod:`msmem_core.run.report.figures`), the
run's summary and steps, and the page's script and style (``report.js``, ``report.css``, package data of
``msmem_core.run.report``); :func:`write_report` writes it and the PNG snapshots into a run folder.
"""

from __future__ import annotations

import functools
import html
import json
import re
from importlib import resources
from pathlib import Path
from typing import Any

from msmem_core.run.report.data import METRIC_KEYS, summary_rows
from msmem_core.run.report.figures import figure_3d, figure_metrics, png_belief, png_metrics
from msmem_core.run.runfolder import RunData, load_run

REPORT_FILES = ("report.html", "report_metrics.png", "report_belief.png")
"""The files :func:`write_report` writes into a run folder (the PNGs with ``png``)."""
_SECTION = re.compile(r"^//= ([\w-]+)[^\n]*\n", re.M)


def _package_text(name: str) -> str:
    return resources.files("msmem_core.run.report").joinpath(name).read_text(encoding="utf-8")


@functools.cache
def _scripts() -> dict[str, str]:
    """The sections of ``report.js`` by name: the text after each line ``//= NAME: ...`` up to the next
    one, without the blank lines around it."""
    parts = _SECTION.split(_package_text("report.js"))
    return {name: text.strip("\n") for name, text in zip(parts[1::2], parts[2::2], strict=True)}


@functools.cache
def _style() -> str:
    """The page's style sheet, ``report.css``."""
    return _package_text("report.css")


# ------------------------------------------------------------------------------------------- HTML page
def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def _summary_table(run: RunData) -> str:
    return "<table class='summary'>" + "".join(
        f"<tr><th class='l'>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
        for k, v in summary_rows(run)) + "</table>"


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
    js = _scripts()
    div3d = f3d.to_html(full_html=False, include_plotlyjs=True, post_script=f"\n{js['sync-cameras']}\n",
                        config={"responsive": True})
    divm = fm.to_html(full_html=False, include_plotlyjs=False, post_script=js["metrics-drawn"])
    title = f"msmem report: {run.config.method}, {run.scene.name}, {len(run.steps)} steps"
    snaps = ",".join(str(s.step) for s in run.snapshots)
    return "\n".join([
        "<!DOCTYPE html>", "<html lang='en'><head><meta charset='utf-8'>", f"<title>{html.escape(title)}</title>",
        f"<script>\n{js['error-hook']}\n</script>", f"<style>\n{_style()}</style>",
        f"<script>\n{js['plot-done']}\n</script>", "</head><body>",
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

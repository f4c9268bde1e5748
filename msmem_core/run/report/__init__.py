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

The package's modules: ``data`` (what the report shows, computed from the run folder: voxel layers,
camera path, manipulations, the summary), ``figures`` (the plotly and matplotlib figures), ``page``
(report.html, with the script ``report.js`` and the style sheet ``report.css`` as package data, and
``write_report``). It is numpy-only at import; plotly and matplotlib load lazily.
"""

from msmem_core.run.report.data import arm_at
from msmem_core.run.report.figures import class_palette, figure_3d, figure_metrics, png_belief, png_metrics
from msmem_core.run.report.page import REPORT_FILES, render_html, write_report

__all__ = [
    "REPORT_FILES",
    "arm_at",
    "class_palette",
    "figure_3d",
    "figure_metrics",
    "png_belief",
    "png_metrics",
    "render_html",
    "write_report",
]

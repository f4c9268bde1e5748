"""Run reports: every ``msmem run`` writes report.html and PNGs; the page renders in a headless browser
without console errors and shows the run's steps; manipulations are drawn from any action shape."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from msmem_core.run.report import REPORT_FILES, render_html, write_report
from msmem_core.run.runfolder import load_run
from tests.support.defaults import ANALYTIC

ROOT = Path(__file__).resolve().parents[1]
MSMEM = str(Path(sys.executable).with_name("msmem"))
STEPS = 3
SMALL = {**ANALYTIC, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 4}}
SCENE = {"name": "three", "objects": [
    {"id": 0, "class_name": "cracker_box", "position_m": [-0.15, 0.08, 0.0]},
    {"id": 1, "class_name": "tomato_soup_can", "position_m": [-0.15, 0.25, 0.0]},
    {"id": 2, "class_name": "sugar_box", "position_m": [0.2, 0.2, 0.0]},
]}
CHROME_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run", "--enable-unsafe-swiftshader", "--enable-logging=stderr", "--v=0",
    "--virtual-time-budget=20000",
)
"""Headless, offline, software WebGL (plotly's 3-D scenes need WebGL; without a GPU Chromium only
provides SwiftShader when asked)."""


def chromium() -> str | None:
    for name in (os.environ.get("MSMEM_CHROMIUM", ""), "chromium", "chromium-browser", "google-chrome",
                 "google-chrome-stable"):
        if name and (path := shutil.which(name)):
            return path
    return None


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real 3-step PyBullet run through the CLI (which writes the report)."""
    tmp = tmp_path_factory.mktemp("report")
    (tmp / "scene.json").write_text(json.dumps(SCENE))
    (tmp / "small.json").write_text(json.dumps(SMALL))
    out = tmp / "run"
    res = subprocess.run([MSMEM, "run", "-q", "--config", str(tmp / "small.json"), "--scene", str(tmp / "scene.json"),
                          "--steps", str(STEPS), "--out", str(out)], capture_output=True, text=True, timeout=600,
                         check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"report: {out / 'report.html'}" in res.stdout
    return out


def test_every_run_writes_snapshots_ground_truth_and_a_self_contained_report(run_dir):
    for name in ("belief_step0.npz", f"belief_step{STEPS // 2}.npz", f"belief_step{STEPS - 1}.npz", "gt_final.npz",
                 "report.html", "report_metrics.png", "report_belief.png"):
        assert (run_dir / name).is_file(), name
    for name in ("report_metrics.png", "report_belief.png"):
        data = (run_dir / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n", name
        assert len(data) > 20_000, name
    with np.load(run_dir / "belief_step0.npz") as f:
        assert f["alpha"].dtype == np.float16
        assert f["gt_occ"].any()
    assert sum(p.stat().st_size for p in run_dir.glob("belief_step*.npz")) < 1_000_000, "snapshots stay small"
    page = (run_dir / "report.html").read_text()
    assert not re.search(r"<script[^>]+src=", page), "plotly.js is inline: the report opens offline"
    assert f"data-steps='{STEPS}'" in page
    assert f"data-snapshots='0,{STEPS // 2},{STEPS - 1}'" in page


def test_msmem_report_rewrites_the_report_of_a_run_folder(run_dir, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns("report*"))
    res = subprocess.run([MSMEM, "report", str(copy), "--no-png"], capture_output=True, text=True, timeout=300,
                         check=False)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == [str(copy / "report.html")]
    assert not (copy / "report_belief.png").exists()


def test_pushes_and_grasps_are_drawn_from_any_action_with_their_fields(run_dir, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy)
    steps = [json.loads(line) for line in (copy / "steps.jsonl").read_text().splitlines()]
    grasp_pose = np.eye(4)
    grasp_pose[:3, 3] = (0.2, 0.15, 0.1)
    steps[1]["action"] = {"kind": "push", "category": "manipulation", "start_m": [0.0, 0.05], "direction": [0.0, 1.0],
                          "length_m": 0.1, "height_m": 0.02}
    steps[2]["action"] = {"kind": "grasp", "category": "manipulation", "grasp_pose": grasp_pose.tolist(),
                          "width_m": 0.05}
    (copy / "steps.jsonl").write_text("".join(json.dumps(s) + "\n" for s in steps))
    run = load_run(copy)
    from msmem_core.run.report import figure_3d

    fig = figure_3d(run)
    final = [t for t in fig.data if t.visible is True]
    names = {t.name for t in final}
    assert {"push / nudge path", "grasp", "camera path", "belief p > 0.5", "ground truth"} <= names
    path = next(t for t in final if t.name == "push / nudge path")
    assert list(path.y[:2]) == pytest.approx([0.05, 0.15])
    assert list(path.z[:2]) == pytest.approx([0.02, 0.02])
    grasp = next(t for t in final if t.name == "grasp")
    assert len(grasp.x) == 3 * 12 * 3, "three boxes (fingers, palm) of 12 edges"
    assert "push at step 1" in render_html(run)


def test_a_run_writes_the_paper_metrics_per_step_and_final_and_the_report_shows_them(run_dir, tmp_path):
    from msmem_core.run.metrics import PAPER_COUNT_KEYS, PAPER_METRIC_KEYS, paper_metrics_from_counts

    final = json.loads((run_dir / "metrics.json").read_text())
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    for rec in (final, final["initial"], *(s["metrics"] for s in steps)):
        assert set(PAPER_METRIC_KEYS) <= set(rec)
        assert 0.0 < rec["occupancy_miou"] <= 1.0
        assert 0.0 < rec["semantic_miou_2d"] <= 1.0
    assert set(final["paper_counts"]) == set(PAPER_COUNT_KEYS)
    assert paper_metrics_from_counts(final["paper_counts"]) == pytest.approx({k: final[k] for k in PAPER_METRIC_KEYS})
    assert final["occupancy_miou"] == steps[-1]["metrics"]["occupancy_miou"]
    assert all("paper_counts" not in s["metrics"] for s in steps), "step records stay small"
    page = (run_dir / "report.html").read_text()
    assert "occupancy_miou (paper)" in page
    assert "semantic_ece (paper)" in page
    # a run folder written before the paper metrics existed still gets a report
    old = tmp_path / "old"
    shutil.copytree(run_dir, old, ignore=shutil.ignore_patterns("report*"))
    strip = lambda m: {k: v for k, v in m.items() if k not in (*PAPER_METRIC_KEYS, "paper_counts")}  # noqa: E731
    (old / "steps.jsonl").write_text("".join(json.dumps({**s, "metrics": strip(s["metrics"])}) + "\n" for s in steps))
    (old / "metrics.json").write_text(json.dumps({**strip(final), "initial": strip(final["initial"])}))
    assert [p.name for p in write_report(old)] == list(REPORT_FILES)
    assert "occupancy_miou (paper)" not in (old / "report.html").read_text()


def test_report_renders_in_headless_chromium_without_console_errors(run_dir, tmp_path):
    browser = chromium()
    if browser is None:
        pytest.skip("no Chromium found (apt-get install chromium, or set MSMEM_CHROMIUM): the report's rendering is "
                    "not checked")
    with tempfile.TemporaryDirectory(prefix="msmem-chromium-") as profile:
        res = subprocess.run([browser, *CHROME_FLAGS, f"--user-data-dir={profile}", "--dump-dom",
                              (run_dir / "report.html").as_uri()], capture_output=True, text=True, timeout=300,
                             check=False)
    assert res.returncode == 0, res.stderr[-3000:]
    console = [line for line in res.stderr.splitlines() if "CONSOLE" in line]
    errors = [line for line in console if "Uncaught" in line or "ERROR:CONSOLE" in line]
    assert not errors, "\n".join(errors)
    status = re.search(r'<p id="msmem-status"([^>]*)>([^<]*)</p>', res.stdout)
    assert status, "the status element is missing from the rendered page"
    attrs = dict(re.findall(r'data-([a-z]+)="([^"]*)"', status.group(1)))
    assert attrs["errors"] == "0", status.group(2)
    assert attrs["steps"] == str(STEPS)
    assert attrs["plots"] == attrs["expected"] == "2", status.group(2)
    assert f"<title>msmem report: {STEPS} steps, 2 plots</title>" in res.stdout
    assert 'class="no-webgl"' not in res.stdout, "the 3-D view needs WebGL (software: --enable-unsafe-swiftshader)"


def test_report_steps_choose_the_snapshots_and_an_empty_shelf_still_reports(tmp_path):
    """``report_steps`` picks the saved beliefs (steps past the end are ignored); a run whose ground
    truth is empty (the fake simulator: nothing but the back wall) still gets a report."""
    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import build_episode, run_episode
    from msmem_core.testing import FakeSimulator
    from msmem_core.world.scene import SceneSpec

    cfg = load_config("view-only", None, {**SMALL, "steps": 3, "report_steps": [1, 7]})
    ep = build_episode(cfg, get_plugin_manager(), scene=SceneSpec(name="empty"))
    ep.sim = FakeSimulator(cfg.camera)
    run_episode(ep, tmp_path)
    assert sorted(p.name for p in tmp_path.glob("belief_step*.npz")) == ["belief_step1.npz"]
    paths = write_report(tmp_path)
    assert [p.name for p in paths] == list(REPORT_FILES)
    run = load_run(tmp_path)
    assert [s.step for s in run.snapshots] == [1, 2], "the final belief is added when the last step has no snapshot"

"""A skill from a separately installed package is offered by MSAS: examples/msmem-nudge installed into
a throwaway folder, its skill proposed, scored and (where it wins) executed in ``msmem run``, its own tests green."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from msmem_core.config import deep_merge
from tests.support.defaults import ANALYTIC

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "msmem-nudge"
PY = sys.executable
MSMEM = str(Path(PY).with_name("msmem"))
ENV = {k: v for k, v in os.environ.items() if k not in ("MSMEM_PLUGINS", "MSMEM_DISABLE_PLUGIN_AUTOLOAD")}
SCENE = EXAMPLE / "demo_scene.json"
"""Low objects at the front (nudgeable) hiding small ones behind them."""


@pytest.fixture(scope="module")
def nudge_package(tmp_path_factory) -> Iterator[None]:
    """Install the example package into a throwaway folder (``pip install --target``: no dependencies, no
    build isolation, offline), never into the live environment, and hand it to the subprocesses below
    on ``PYTHONPATH`` ahead of this checkout, so it is found as an installed distribution is."""
    target = tmp_path_factory.mktemp("nudge") / "site"
    cmd = [PY, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index", "--target",
           str(target), str(EXAMPLE)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=ENV, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    here = [str(ROOT / d) for d in ("", "plugins", "simulators")]
    ENV["PYTHONPATH"] = os.pathsep.join([str(target), *here])
    try:
        yield
    finally:
        ENV.pop("PYTHONPATH")


def test_the_installed_package_registers_its_components(nudge_package):
    out = subprocess.run([MSMEM, "plugins", "--json"], capture_output=True, text=True, timeout=300, env=ENV,
                         check=False)
    assert out.returncode == 0, out.stderr
    rows = {(c["kind"], c["name"]): c["distribution"] for c in json.loads(out.stdout)["components"]}
    assert rows[("skill", "nudge")] == "msmem-nudge"
    assert rows[("belief-model", "nudge-effect")] == "msmem-nudge"
    assert rows[("objective-term", "travel-cost")] == "msmem-nudge"


def test_msas_proposes_scores_and_executes_the_nudge(nudge_package, tmp_path):
    """The shipped slow_camera.yaml (nudge.yaml with views made very expensive by travel-cost, so a
    nudge wins as soon as one is proposed: the composed objective, not the test, decides) and a small
    camera."""
    cfg = yaml.safe_load((EXAMPLE / "slow_camera.yaml").read_text())
    cfg = deep_merge(cfg, {**ANALYTIC, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 4}})
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    run = tmp_path / "run"
    out = subprocess.run([MSMEM, "run", "-q", "--no-report", "--config", str(tmp_path / "config.yaml"), "--scene",
                          str(SCENE), "--steps", "5", "--out", str(run)],
                         capture_output=True, text=True, timeout=900, env=ENV, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    steps = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
    offered = [s for s in steps if s["candidates"].get("nudge", 0) > 0]
    assert offered, f"no step proposed a nudge: {[s['candidates'] for s in steps]}"
    assert all("nudge" in s["best_per_skill"] for s in offered), "proposed nudges are scored"
    chosen = [s for s in steps if s["skill"] == "nudge"]
    assert chosen, f"the nudge never won: {[s['best_per_skill'] for s in steps]}"
    first = chosen[0]
    assert first["action"]["kind"] == "nudge", first
    assert first["success"], first
    assert first["terms"]["travel-cost"] < -8.0
    if first["step"] + 1 < len(steps):
        assert steps[first["step"] + 1]["skill"] == "view", "a manipulation is followed by its associated view"
    assert steps[-1]["metrics"]["position_change_m"] > 0.005, "the nudged object moved"


@pytest.mark.slow  # integration (subprocesses or a full scene build); CI runs it in make test-slow
def test_the_example_package_own_tests_pass(nudge_package):
    out = subprocess.run([PY, "-m", "pytest", "-q", "-p", "no:cacheprovider"], cwd=EXAMPLE, capture_output=True,
                         text=True, timeout=900, env=ENV, check=False)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert " passed" in out.stdout

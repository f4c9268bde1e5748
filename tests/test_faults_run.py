"""Fault injection for ``msmem run`` and Ctrl-C: run folders are written atomically, an
existing --out is never mixed with a new run, a bad --out fails before any work, and Ctrl-C says
where the partial run is."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from typer.testing import CliRunner

from msmem_core.cli import build_app
from tests.test_commands import MSMEM, PYTHONPATH, ROOT, SCENE, run_cli

SMALL = "camera: {width_px: 160, height_px: 120}\nig: {ray_stride_px: 8}\n"


@pytest.fixture
def small_config(tmp_path) -> Path:
    path = tmp_path / "small.yaml"
    path.write_text(SMALL)
    return path


def _run(config: Path, out: Path, *args: str):
    return CliRunner().invoke(build_app(), ["run", "-m", "view-only", "-c", str(config), "--scene", SCENE,
                                            "-q", "--no-report", "--out", str(out), *args])


def test_an_existing_run_folder_is_refused_and_overwrite_replaces_it_whole(tmp_path, small_config):
    out = tmp_path / "run"
    first = _run(small_config, out, "--steps", "3")
    assert first.exit_code == 0, first.output
    assert (out / "belief_step2.npz").exists()
    again = _run(small_config, out, "--steps", "1")
    assert "exists and is not empty; give --overwrite" in str(again.exception)
    replaced = _run(small_config, out, "--steps", "1", "--overwrite")
    assert replaced.exit_code == 0, replaced.output
    assert not (out / "belief_step2.npz").exists()  # nothing of the first run is left
    assert len((out / "steps.jsonl").read_text().splitlines()) == 1
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("run")] == ["run"]  # no temporary left


def test_run_folder_json_is_strict(tmp_path, small_config):
    out = tmp_path / "run"
    assert _run(small_config, out, "--steps", "1").exit_code == 0

    def refuse(token: str) -> None:
        raise ValueError(f"bare {token} in JSON")

    json.loads((out / "metrics.json").read_text(), parse_constant=refuse)
    for line in (out / "steps.jsonl").read_text().splitlines():
        json.loads(line, parse_constant=refuse)


@pytest.mark.parametrize("where", ["file", "under-a-file"])
def test_a_bad_out_is_one_line_rc_2_before_the_episode_is_built(tmp_path, where):
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" if where == "file" else tmp_path / "file" / "run"
    res = run_cli("run", "-m", "view-only", "--out", str(out), "--sim", "nosuch")  # a bad --sim would fail later
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("msmem: error: ")
    assert str(tmp_path / "file") in lines[0]
    assert "simulator" not in lines[0]


def test_os_and_memory_errors_are_one_line_rc_2(monkeypatch, capsys):
    import msmem_core.cli.app as app

    for error, line in [(OSError(28, "No space left on device", "/data/x.npz"),
                         "msmem: error: No space left on device: /data/x.npz"),
                        (MemoryError("Unable to allocate 67.0 GiB for an array with shape (4096, 4096, 1024)"),
                         "msmem: error: out of memory: Unable to allocate 67.0 GiB for an array with shape "
                         "(4096, 4096, 1024)")]:
        def raiser(current: BaseException) -> Callable[[], None]:
            def command() -> None:
                raise current
            return command

        show = raiser(error)
        monkeypatch.setattr(app, "CORE_COMMANDS", {**app.CORE_COMMANDS, "config": {"show": show}})
        monkeypatch.setattr(sys, "argv", ["msmem", "config", "show"])
        with pytest.raises(SystemExit) as exit_:
            app.main()
        assert exit_.value.code == 2
        assert capsys.readouterr().err == line + "\n"


def _default_sigint() -> None:
    """In the child before exec: Ctrl-C's default action. A test run started as a background job (``cmd &``
    in a script) inherits SIGINT ignored, and Python then installs no KeyboardInterrupt handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow  # about 10 s: kept out of `make test`'s five minutes, run by CI's `make test-slow`
def test_ctrl_c_names_the_step_and_the_partial_run_and_exits_130(tmp_path, small_config):
    out = tmp_path / "run"
    env = {"PYTHONPATH": PYTHONPATH, "PATH": "/usr/bin:/bin"}
    proc = subprocess.Popen([MSMEM, "run", "-m", "view-only", "-c", str(small_config), "--scene", SCENE, "-q",
                             "--steps", "40", "--out", str(out)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
    deadline = time.time() + 300
    steps = []
    while time.time() < deadline and proc.poll() is None:
        steps = list(tmp_path.glob("run.partial-*/steps.jsonl"))
        if steps and steps[0].read_text().count("\n") >= 1:
            break
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    last = err.strip().splitlines()[-1]
    partial = steps[0].parent
    done = len(steps[0].read_text().splitlines())
    assert last == f"msmem: interrupted at step {done}; partial run in {partial}"
    assert not out.exists()  # --out holds a complete run or nothing


IG_LOOP = """
import os, signal, threading, traceback
from msmem_core.map.ig import IGService
from msmem_core.testing import default_workspace, small_viewpoints
from msmem_core.testing.builders import belief_with_boxes
from msmem_core.world.camera import CameraConfig
ws = default_workspace(0.01)
ig = IGService(ws.grid, CameraConfig(width_px=160, height_px=120), small_viewpoints(ws.shelf, 6), ws.shelf)
field = ig.prepare(belief_with_boxes(ws.grid, [((-0.05, 0.03, 0.0), (0.05, 0.08, 0.09), 9)]))
ig.view_ig(field, exact=True)
threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
try:
    while True:
        ig.view_ig(field, exact=True)
        ig.sweep(ig.after_view(field, 0), exact=True)
except BaseException as e:
    frame = traceback.extract_tb(e.__traceback__)[-1]
    print(type(e).__name__, frame.filename)
"""


def test_ctrl_c_during_the_numba_ig_sweep_is_a_keyboard_interrupt_between_kernels():
    res = subprocess.run([sys.executable, "-c", IG_LOOP], capture_output=True, text=True, timeout=300, cwd=ROOT,
                         env={"PYTHONPATH": PYTHONPATH, "PATH": "/usr/bin:/bin"}, check=False,
                         preexec_fn=_default_sigint)
    name, where = res.stdout.split()
    assert name == "KeyboardInterrupt", res.stdout + res.stderr
    assert where.endswith("msmem_core/util/interrupt.py"), where  # raised by msmem, not inside numba's glue


def test_ctrl_c_in_any_command_reaches_msmems_handler(monkeypatch, capsys):
    import msmem_core.cli.app as app

    def show() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(app, "CORE_COMMANDS", {**app.CORE_COMMANDS, "config": {"show": show}})
    monkeypatch.setattr(sys, "argv", ["msmem", "config", "show"])
    with pytest.raises(SystemExit) as exit_:
        app.main()
    assert exit_.value.code == 130
    assert capsys.readouterr().err == "msmem: interrupted\n"  # typer alone exits 130 silently


def _glue_error() -> SystemError:
    """What a Ctrl-C inside numba's glue code (e.g. unpickling a cached kernel's constant) raises."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as k:
            raise SystemError("<function _numba_unpickle> returned a result with an exception set") from k
    except SystemError as e:
        return e


def test_a_system_error_from_a_ctrl_c_is_an_interrupt_and_any_other_is_not(monkeypatch, capsys):
    import msmem_core.cli.app as app
    from msmem_core.util.interrupt import caused_by_interrupt

    assert caused_by_interrupt(_glue_error())
    assert not caused_by_interrupt(SystemError("a real bug"))
    for error, code, err in [(_glue_error(), 130, "msmem: interrupted\n"), (SystemError("a real bug"), None, None)]:
        def raiser(current: BaseException) -> Callable[[], None]:
            def command() -> None:
                raise current
            return command

        monkeypatch.setattr(app, "CORE_COMMANDS", {**app.CORE_COMMANDS, "config": {"show": raiser(error)}})
        monkeypatch.setattr(sys, "argv", ["msmem", "config", "show"])
        if code is None:
            with pytest.raises(SystemError, match="a real bug"):
                app.main()
            continue
        with pytest.raises(SystemExit) as exit_:
            app.main()
        assert exit_.value.code == code
        assert capsys.readouterr().err == err


def test_run_episode_reports_a_ctrl_c_in_kernel_glue_as_the_interrupted_step(tmp_path, monkeypatch):
    from msmem_core.config import load_config
    from msmem_core.errors import Interrupted
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run import runner
    from msmem_core.testing import FakeSimulator
    from tests.test_episode import SMALL, small_scene

    cfg = load_config("view-only", None, {**SMALL, "steps": 3})
    ep = runner.build_episode(cfg, get_plugin_manager(), scene=small_scene())
    ep.sim = FakeSimulator(cfg.camera)
    real = ep.observe_model.update
    calls = []

    def update(belief, obs):  # the third observation (step 1) is interrupted inside a kernel
        calls.append(1)
        if len(calls) == 3:
            raise _glue_error()
        return real(belief, obs)

    monkeypatch.setattr(ep.observe_model, "update", update)
    with pytest.raises(Interrupted, match=r"interrupted at step 1; partial run in"):
        runner.run_episode(ep, tmp_path / "run")

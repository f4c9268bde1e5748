"""One writer per output folder: ``msmem run``, ``bench`` and ``datagen`` lock their --out. Two real
processes each time: a holder (``tests/support/hold_lock.py``, or a real run) and the msmem command."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from msmem_core.run.lock import LOCK_NAME, FolderLocked, folder_lock, run_lock_file
from tests.test_commands import MSMEM, PYTHONPATH, ROOT, SCENE, run_cli

HOLD = str(ROOT / "tests" / "support" / "hold_lock.py")
SMALL = "camera: {width_px: 160, height_px: 120}\nig: {ray_stride_px: 8}\n"


@contextmanager
def holder(folder: Path, *args: str) -> Iterator[subprocess.Popen[str]]:
    """A process holding the lock of ``folder`` (it has printed ``locked``) while the block runs."""
    proc = subprocess.Popen([sys.executable, HOLD, str(folder), *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": PYTHONPATH})
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "locked"
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        assert proc.stdout is not None
        proc.stdout.close()


def _one_error_line(res: subprocess.CompletedProcess[str]) -> str:
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    return lines[0]


BENCH = ("bench", "--methods", "view-only", "--suite", "tune10", "--scenes", "0", "--steps", "1", "--workers", "1")


def test_a_second_bench_into_a_locked_folder_is_refused_naming_the_holder(tmp_path):
    out = tmp_path / "bench"
    with holder(out, "--seconds", "120") as proc:
        line = _one_error_line(run_cli(*BENCH, "--out", str(out)))
    assert line.startswith(f"msmem: error: {out} is being written by process {proc.pid} "
                           f"(hold_lock.py {out} --seconds 120; since ")
    assert "--wait" in line
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # the holder's: nothing planned, nothing written


def test_a_second_run_into_a_locked_run_folder_is_refused_before_any_work(tmp_path):
    out = tmp_path / "run"
    with holder(out, "--run") as proc:
        line = _one_error_line(run_cli("run", "-m", "view-only", "--sim", "nosuch", "--out", str(out)))
    assert f"msmem: error: {out} is being written by process {proc.pid} (hold_lock.py {out} --run; since " in line
    assert "nosuch" not in line  # refused before the config's components are even looked at
    assert [p.name for p in tmp_path.iterdir()] == [".run.msmem.lock"]  # the holder's: no partial folder


def test_a_second_datagen_into_a_locked_data_folder_is_refused(tmp_path):
    out = tmp_path / "data"
    with holder(out) as proc:
        line = _one_error_line(run_cli("datagen", "cnabu", "--kind", "observe", "--scenes", "1", "--out", str(out)))
    assert f"msmem: error: {out} is being written by process {proc.pid}" in line
    assert not (out / "dataset.json").exists()


def test_wait_waits_for_the_holder_then_goes_on(tmp_path):
    """With --wait the command says it waits and blocks until the holder releases the lock (on SIGUSR1),
    then takes it and goes on (here to the check of its --sim: a fast one-line error)."""
    out = tmp_path / "data"
    with holder(out) as proc:
        cmd = subprocess.Popen([MSMEM, "datagen", "cnabu", "--kind", "observe", "--scenes", "1", "--sim", "nosuch",
                                "--wait", "--out", str(out)], cwd=ROOT, env={**os.environ, "PYTHONPATH": PYTHONPATH},
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        assert cmd.stderr is not None
        first = cmd.stderr.readline()
        time.sleep(0.5)
        assert cmd.poll() is None, "it did not wait"
        proc.send_signal(signal.SIGUSR1)
        rest = cmd.communicate(timeout=120)[1]
        assert proc.wait(timeout=30) == 0  # the holder released the lock and ended normally
    assert first.startswith(f"msmem: waiting for process {proc.pid} (hold_lock.py {out}; since ")
    assert first.rstrip().endswith(f") to finish writing {out} (lock {out / LOCK_NAME})")
    assert cmd.returncode == 2, rest
    assert rest.strip().splitlines() == ["msmem: error: no simulator named 'nosuch'; available: pybullet, sapien"]


def test_a_lock_left_by_a_dead_process_is_taken_over(tmp_path):
    out = tmp_path / "run"
    with holder(out, "--run", "--die") as proc:
        proc.wait()  # killed with the lock held: its lock file stays behind, naming it
    assert proc.returncode == -9
    left = run_lock_file(out)
    assert f"pid={proc.pid}" in left.read_text()
    res = run_cli("run", "-m", "view-only", "--sim", "nosuch", "--out", str(out))
    assert res.returncode == 2, res.stderr
    first, last = res.stderr.strip().splitlines()
    assert first.startswith(f"msmem: taking over the lock {left} left by process {proc.pid} (hold_lock.py {out} "
                            "--run --die; since ")
    assert first.endswith("), which is no longer running")
    assert "no simulator named 'nosuch'" in last  # it went on past the lock
    assert not left.exists()


def test_the_lock_is_reentrant_in_a_process_and_exclusive_between_processes(tmp_path):
    with folder_lock(tmp_path / "f") as path, folder_lock(tmp_path / "f"):  # a command, then its library function
        assert path.read_text().startswith(f"pid={os.getpid()}\n")
    assert not (tmp_path / "f").exists()  # made for the lock, removed with it
    with holder(tmp_path / "g") as proc, pytest.raises(FolderLocked, match=f"process {proc.pid} "):
        with folder_lock(tmp_path / "g"):
            pass


@pytest.mark.slow  # one ~15 s run
def test_two_runs_started_together_into_one_folder_one_runs_the_other_is_refused(tmp_path):
    config = tmp_path / "small.yaml"
    config.write_text(SMALL)
    out = tmp_path / "run"
    args = [MSMEM, "run", "-m", "view-only", "-c", str(config), "--scene", SCENE, "--steps", "1", "-q",
            "--no-report", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": PYTHONPATH}
    procs = [subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.pid, *p.communicate(timeout=300), p.returncode) for p in procs]
    codes = sorted(rc for *_, rc in results)
    assert codes == [0, 2], results
    (winner, *_), (_, _, err, _) = sorted(results, key=lambda r: r[3])
    assert f"{out} is being written by process {winner} " in err
    assert (out / "metrics.json").is_file()

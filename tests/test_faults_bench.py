"""Fault injection for ``msmem bench`` and its executors: each test reproduces a failure
that used to pass silently (a wrong table with rc 0, a lost episode, an orphaned worker)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from msmem_core.errors import IncompleteError
from msmem_core.run.bench import FingerprintMismatch, run_bench, suite_scenes
from msmem_core.run.executors import TaskFailure, run_tasks
from tests.support.tasks import square_or_die
from tests.test_commands import run_cli

ROOT = Path(__file__).resolve().parents[1]


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for a reaper counts as dead)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


# ------------------------------------------------------------------------------------ workers
def test_a_dead_worker_is_that_tasks_failure_and_the_others_go_on():
    results = run_tasks(square_or_die, [1, 2, -1, 3, 4], workers=2, progress=False, threads=None)
    assert [r for i, r in enumerate(results) if i != 2] == [1, 4, 9, 16]
    failure = results[2]
    assert isinstance(failure, TaskFailure)
    assert failure.index == 2
    assert "worker process died" in failure.error


def test_a_dead_ray_worker_is_that_tasks_failure_and_the_others_go_on():
    """On Ray the dying task is retried once (``RAY_RETRIES``) and then comes back as its failure;
    the others finish (this used to raise WorkerCrashedError out of the whole run)."""
    pytest.importorskip("ray", reason="Ray is the optional extra msmem[ray]; not installed here")
    results = run_tasks(square_or_die, [1, 2, -1, 3], executor="ray", workers=2, progress=False, threads=None)
    assert [r for i, r in enumerate(results) if i != 2] == [1, 4, 9]
    failure = results[2]
    assert isinstance(failure, TaskFailure)
    assert failure.index == 2
    assert "worker process died" in failure.error


def test_a_worker_dying_between_two_submissions_is_a_failure_too(monkeypatch):
    """A worker may die after a wait returned and before the next submit, which then raises
    BrokenProcessPool itself (seen in CI). Reproduced: the pool kills one of its idle workers just
    before the fifth submission; every task still gets its result (none of them killed it)."""
    import concurrent.futures.process as cfp

    from msmem_core.run import executors

    class DyingPool(cfp.ProcessPoolExecutor):
        calls = 0

        def submit(self, fn, /, *args, **kwargs):
            type(self).calls += 1
            if type(self).calls == 5:
                victim = next(iter(self._processes.values()))
                victim.kill()
                victim.join()
                deadline = time.time() + 10
                while not self._broken and time.time() < deadline:
                    time.sleep(0.01)
            return super().submit(fn, *args, **kwargs)

    monkeypatch.setattr(executors, "ProcessPoolExecutor", DyingPool)
    results = run_tasks(square_or_die, [1, 2, 3, 4, 5, 6, 7, 8], workers=2, progress=False, threads=None)
    assert DyingPool.calls >= 5
    assert results == [x * x for x in range(1, 9)], "a task in flight on the killed worker is rerun alone"


def test_workers_exit_when_their_parent_is_killed(tmp_path):
    script = ("import sys; from msmem_core.run.executors import run_tasks; "
              "from tests.support.tasks import record_pid_and_sleep; "
              "run_tasks(record_pid_and_sleep, [sys.argv[1]] * 2, workers=2, progress=False, threads=None)")
    parent = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], cwd=ROOT)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and len(list(tmp_path.glob("*.pid"))) < 2:
            time.sleep(0.2)
        pids = [int(p.stem) for p in tmp_path.glob("*.pid")]
        assert len(pids) == 2, "the workers never started"
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()
    deadline = time.time() + 10
    while time.time() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.1)
    orphans = [p for p in pids if _alive(p)]
    for p in orphans:
        os.kill(p, signal.SIGKILL)
    assert not orphans, f"workers {orphans} outlived their parent"


# ------------------------------------------------------------------------------------ bench resume
FAST = {"steps": 2, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}
EPISODE = "episodes/view-only__scene00.json"


def _bench(out: Path, suite: str = "tune10", overrides: dict | None = None, **kwargs):
    return run_bench(["view-only"], suite_scenes(suite), [0], out, {**FAST, **(overrides or {})}, None, "local", 1, 1,
                     progress=False, suite=suite, **kwargs)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished one-episode bench (tune10 scene 0, two steps)."""
    out = tmp_path_factory.mktemp("bench")
    _bench(out)
    return out


@pytest.fixture
def bench_copy(finished, tmp_path) -> Path:
    shutil.copytree(finished, tmp_path / "bench")
    return tmp_path / "bench"


def test_episode_files_record_what_produced_them(finished):
    fp = json.loads((finished / EPISODE).read_text())["fingerprint"]
    assert set(fp) == {"method", "suite", "scene_sha256", "steps", "config_sha256", "plugins"}
    assert (fp["method"], fp["suite"], fp["steps"]) == ("view-only", "tune10", 2)
    assert "msmem" in fp["plugins"]


@pytest.mark.parametrize(("change", "named"), [
    ({"overrides": {"steps": 3}}, "steps 2 (now 3)"),
    ({"suite": "hard25"}, "suite tune10 (now hard25)"),
    ({"overrides": {"ig": {"ray_stride_px": 4}}}, "config_sha256"),
])
def test_resume_with_other_settings_stops_naming_the_file_and_what_differs(bench_copy, change, named):
    before = (bench_copy / EPISODE).read_text()
    with pytest.raises(FingerprintMismatch) as err:
        _bench(bench_copy, **change)
    message = str(err.value)
    assert "\n" not in message
    assert str(bench_copy / EPISODE) in message
    assert named in message
    assert "--rerun-mismatched" in message
    assert (bench_copy / EPISODE).read_text() == before  # nothing was run or written


def test_rerun_mismatched_reruns_with_the_new_settings(bench_copy):
    summary = _bench(bench_copy, overrides={"steps": 3}, rerun_mismatched=True)
    assert summary["ran"] == 1
    rec = json.loads((bench_copy / EPISODE).read_text())
    assert rec["fingerprint"]["steps"] == 3
    assert rec["metrics"]["views"] == 3


def _crash(folder: Path, error: str, trace: str) -> None:
    rec = json.loads((folder / EPISODE).read_text())
    (folder / EPISODE).write_text(json.dumps({"method": "view-only", "scene_index": 0, "status": "error",
                                              "error": error, "traceback": trace, "seconds": 1.0,
                                              "fingerprint": rec["fingerprint"]}))


def test_a_crashed_episode_is_retried_and_its_old_traceback_kept(bench_copy):
    _crash(bench_copy, "RuntimeError: flaky", "Traceback: old one")
    kept = _bench(bench_copy, retry_crashed=False)
    assert (kept["ran"], kept["errors"][0]["error"]) == (0, "RuntimeError: flaky")
    summary = _bench(bench_copy)
    assert summary["ran"] == 1
    assert summary["errors"] == []
    rec = json.loads((bench_copy / EPISODE).read_text())
    assert rec["status"] == "ok"
    assert rec["history"] == [{"error": "RuntimeError: flaky", "traceback": "Traceback: old one", "seconds": 1.0}]


def test_a_corrupt_episode_file_is_named_moved_aside_and_redone(bench_copy, capsys):
    truncated = (bench_copy / EPISODE).read_text()[:100]
    (bench_copy / EPISODE).write_text(truncated)
    summary = _bench(bench_copy)
    assert summary["ran"] == 1
    assert str(bench_copy / EPISODE) in capsys.readouterr().err
    assert (bench_copy / (EPISODE + ".corrupt")).read_text() == truncated
    assert json.loads((bench_copy / EPISODE).read_text())["status"] == "ok"


def test_the_table_counts_only_the_planned_episodes(bench_copy):
    foreign = bench_copy / "episodes" / "view-only__scene05.json"  # left by a run with other --scenes
    shutil.copy(bench_copy / EPISODE, foreign)
    summary = _bench(bench_copy)
    assert (summary["ran"], summary["skipped_finished"]) == (0, 1)
    assert summary["table"]["view-only"]["episodes"] == 1


def test_results_are_strict_json_with_null_for_nan(finished):
    def refuse(token: str) -> None:
        raise ValueError(f"bare {token} in JSON")

    results = json.loads((finished / "results.json").read_text(), parse_constant=refuse)
    episode = json.loads((finished / EPISODE).read_text(), parse_constant=refuse)
    assert episode["metrics"]["fell"] is None  # never manipulated: NaN in memory, null on disk
    assert results["summary"]["table"]["view-only"]["fell"] == [None, None]


def test_a_planned_episode_without_a_result_is_an_error_naming_it(bench_copy, monkeypatch):
    import msmem_core.run.bench as bench

    real = bench.write_atomic

    def unwritable(path: Path, data: object) -> None:
        if path.parent.name == "episodes":
            raise PermissionError(13, "Permission denied", str(path))
        real(path, data)

    monkeypatch.setattr(bench, "write_atomic", unwritable)
    (bench_copy / EPISODE).unlink()
    with pytest.raises(IncompleteError, match=r"1 of 1 planned episodes have no result: .*view-only__scene00\.json"):
        _bench(bench_copy)
    assert not (bench_copy / "episodes" / "view-only__scene00.json").exists()


def test_an_incomplete_bench_exits_1(monkeypatch, capsys):
    import msmem_core.run.bench as bench
    from msmem_core.cli.app import main

    def incomplete(*args: object, **kwargs: object) -> None:
        raise IncompleteError("1 of 1 planned episodes have no result: x.json (disk full)")

    monkeypatch.setattr(bench, "run_bench", incomplete)
    monkeypatch.setattr(sys, "argv", ["msmem", "bench", "--methods", "view-only", "--scenes", "0", "--out", "x"])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 1
    assert capsys.readouterr().err == "msmem: error: 1 of 1 planned episodes have no result: x.json (disk full)\n"


BAD_INPUT = [
    (["--steps", "-2"], "steps"),
    (["-c", "no/such/config.yaml"], "no/such/config.yaml"),
    (["--sim", "nosuch"], "no simulator named 'nosuch'"),
    (["--threads", "0"], "threads"),
    (["--workers", "0"], "workers"),
]


@pytest.mark.parametrize(("args", "named"), BAD_INPUT, ids=[a[0] for a, _ in BAD_INPUT])
def test_bad_bench_input_exits_2_and_records_nothing(tmp_path, args, named):
    res = run_cli("bench", "--methods", "view-only", "--suite", "tune10", "--scenes", "0", "--out",
                  str(tmp_path / "out"), *args)
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("msmem: error: ")
    assert named in lines[0]
    assert not (tmp_path / "out").exists()


def test_an_out_folder_that_is_a_file_exits_2_before_any_episode(tmp_path):
    (tmp_path / "file").write_text("")
    res = run_cli("bench", "--methods", "view-only", "--suite", "tune10", "--scenes", "0", "--out",
                  str(tmp_path / "file"))
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.startswith(f"msmem: error: cannot write bench results to {tmp_path / 'file' / 'episodes'}")


def test_the_fingerprint_follows_the_weights_a_component_may_load(tmp_path):
    """New weights under the same config and version are a mismatch, not a silent reuse."""
    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.bench import fingerprint, fingerprint_diff
    from msmem_core.run.runner import check_components

    pm = get_plugin_manager()
    analytic = {"observation_model": {"name": "analytic-observation"}}
    assert "weights" not in check_components(load_config("view-only", None, analytic), pm)  # the analytic loads none
    shipped = check_components(load_config("ours"), pm)["weights"]  # the learned effect models, FE-vMF
    import torch

    w = tmp_path / "map.pt"  # named weights must load (check_named_weights): two tiny state dicts
    torch.save({"a": torch.zeros(1)}, w)
    cfg = load_config("view-only", None, {"observation_model": {"name": "cnabu-map", "params": {"weights": str(w)}}})
    before = check_components(cfg, pm)
    assert before["weights"] != shipped
    torch.save({"a": torch.ones(1)}, w)
    after = check_components(cfg, pm)
    assert after["weights"] != before["weights"]
    scene = suite_scenes("tune10")[0]
    old, new = fingerprint(cfg, "tune10", scene, before), fingerprint(cfg, "tune10", scene, after)
    assert "plugins" in fingerprint_diff(old, new)


def test_the_fingerprint_follows_a_plugins_defaults_not_only_the_config_text(monkeypatch):
    """A component's resolved config is part of the fingerprint: naming a default explicitly changes
    nothing, another value does, and so does a plugin whose default changed under the same config and
    version (a resume would otherwise reuse episodes made under the old default)."""
    from msmem_grasp.skill import GraspConfig

    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import check_components

    pm = get_plugin_manager()

    def components(params: dict) -> str:
        return check_components(load_config("grasp-only", None, {"skill_params": {"grasp": params}}), pm)["components"]

    default = GraspConfig().min_lift_m
    assert components({}) == components({"min_lift_m": default})
    assert components({"min_lift_m": default + 0.01}) != components({})
    before = components({})
    monkeypatch.setattr(GraspConfig.model_fields["min_lift_m"], "default", default + 0.01)
    GraspConfig.model_rebuild(force=True)
    try:
        assert GraspConfig().min_lift_m == default + 0.01
        assert components({}) != before
    finally:
        monkeypatch.undo()
        GraspConfig.model_rebuild(force=True)
    assert GraspConfig().min_lift_m == default
    assert components({}) == before

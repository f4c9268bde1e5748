"""Small defects found by trying msmem as a careless user would, each with the test that holds its fix: a
full disk names the file and the partial folder; --workers >= 1 everywhere; bad --methods lists are one
line; `config show` validates plugin params; scenes get a size estimate and a refusal above a limit; a
dead bench worker is reported with the episode it ran. (Plugin warnings printed once:
tests/test_faults_plugins.py.)"""

from __future__ import annotations

import errno
import io
import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest

from msmem_core.errors import UserError
from msmem_core.learn.datagen import generate_shards
from msmem_core.run.bench import parse_methods, write_text_atomic
from msmem_core.run.estimate import DEFAULT_MAX_MINUTES, MINUTES_VAR, check_estimate, estimate
from msmem_core.run.executors import TaskFailure, run_tasks
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ObjectSpec, SceneSpec, ShelfSpec
from tests.support.tasks import square_or_die
from tests.test_commands import SCENE, run_cli

SMALL = "camera: {width_px: 160, height_px: 120}\nig: {ray_stride_px: 8}\n"
ENOSPC = os.strerror(errno.ENOSPC)  # "No space left on device"


def _one_error_line(res: Any) -> str:
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("msmem: error: ")
    return lines[0]


# ------------------------------------------------------------------------------------------ full disk
class _FullFile:
    """A file whose writes fail as on a full disk: ``OSError(ENOSPC)`` without a file name."""

    def __init__(self, real: Any) -> None:
        self._real = real

    def write(self, data: Any) -> int:
        raise OSError(errno.ENOSPC, ENOSPC)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)

    def __enter__(self) -> _FullFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self._real.close()


def full_disk_for(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    """Writes to any file called ``name`` fail as on a full disk (``io.open``, which ``Path.open``,
    ``Path.write_text`` and numpy's ``savez`` call)."""
    real_open = io.open

    def fake_open(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        handle = real_open(file, mode, *args, **kwargs)
        if isinstance(file, (str, os.PathLike)) and Path(file).name == name and any(c in mode for c in "wax"):
            return _FullFile(handle)
        return handle

    monkeypatch.setattr(io, "open", fake_open)


@pytest.mark.parametrize("name", ["steps.jsonl", "belief_final.npz"])
def test_a_full_disk_names_the_file_and_the_partial_run_folder(tmp_path, monkeypatch, capsys, name):
    import msmem_core.cli.app as app

    config = tmp_path / "small.yaml"
    config.write_text(SMALL)
    out = tmp_path / "run"
    full_disk_for(monkeypatch, name)
    monkeypatch.setattr(sys, "argv", ["msmem", "run", "-m", "view-only", "-c", str(config), "--scene", SCENE,
                                      "--steps", "2", "-q", "--no-report", "--out", str(out)])
    with pytest.raises(SystemExit) as exit_:
        app.main()
    assert exit_.value.code == 2
    [partial] = tmp_path.glob("run.partial-*")
    err = capsys.readouterr().err
    assert err == f"msmem: error: cannot write {partial / name}: {ENOSPC}; partial run in {partial}\n"
    assert not out.exists()


def test_a_full_disk_while_writing_the_bench_table_names_the_file(tmp_path, monkeypatch):
    full_disk_for(monkeypatch, "table.md.tmp" + str(os.getpid()))
    with pytest.raises(OSError) as raised:  # noqa: PT011 (the one `msmem` prints as "STRERROR: FILE")
        write_text_atomic(tmp_path / "table.md", "| table |\n")
    assert (raised.value.errno, raised.value.strerror, raised.value.filename) == (
        errno.ENOSPC, ENOSPC, str(tmp_path / "table.md"))
    assert list(tmp_path.iterdir()) == []  # no temporary left behind


# ------------------------------------------------------------------------------------------ --workers
def test_datagen_workers_0_is_one_line_and_writes_nothing(tmp_path):
    line = _one_error_line(run_cli("datagen", "cnabu", "--kind", "observe", "--scenes", "1", "--workers", "0",
                                   "--out", str(tmp_path / "data")))
    assert line == "msmem: error: --workers must be >= 1, got 0"
    assert not (tmp_path / "data").exists()


def test_workers_below_1_are_refused_by_the_executor_and_the_shard_writer(tmp_path):
    for workers in (0, -1):
        with pytest.raises(UserError, match=f"--workers must be >= 1, got {workers}"):
            run_tasks(square_or_die, [1, 2], workers=workers, progress=False)
        with pytest.raises(UserError, match=f"--workers must be >= 1, got {workers}"):
            generate_shards(tmp_path / "data", [0], square_or_die, "{}", print, {}, "local", workers, False, print,
                            "scenes")
    assert not (tmp_path / "data").exists()
    assert run_tasks(square_or_die, [1, 2], workers=None, progress=False, threads=None) == [1, 4]  # None: the CPUs


# ------------------------------------------------------------------------------------------ --methods
def test_bench_methods_comma_is_one_line_not_a_traceback(tmp_path):
    line = _one_error_line(run_cli("bench", "--methods", ",", "--suite", "tune10", "--out", str(tmp_path / "b")))
    assert line == "msmem: error: --methods ',': expected comma-separated method presets, e.g. view-only,push-only"
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize(("text", "named"), [
    ("", "expected comma-separated method presets"),
    (" , ", "expected comma-separated method presets"),
    ("view-only,,push-only", "an empty name between commas"),
    ("view-only,", "an empty name between commas"),
    ("view-only,view-only", "'view-only' is named twice"),
    ("view-only,nosuch", "nosuch"),
])
def test_bad_method_lists_are_one_line_errors(text, named):
    with pytest.raises(UserError, match=named) as raised:
        parse_methods(text)
    assert "\n" not in str(raised.value)


def test_good_method_lists_parse():
    assert parse_methods(" view-only , push-only ") == ["view-only", "push-only"]


def test_an_empty_scene_range_is_one_line():
    from msmem_core.run.bench import parse_range

    with pytest.raises(UserError, match=r"--scenes '5-2': the range '5-2' is empty"):
        parse_range("5-2", 10)


# ------------------------------------------------------------------------------------------ config show
@pytest.mark.parametrize(("text", "named"), [
    ("observation_model:\n  name: analytic-observation\n  params: {nosuch: 1}\n",
     "belief-model 'analytic-observation': observation_model.params.nosuch: Extra inputs are not permitted"),
    ("skills:\n  - name: view\n    params: {bogus: true}\n", "skill 'view': skills.0.params.bogus: Extra inputs"),
    ("simulator: {name: nosuch}\n", "no simulator named 'nosuch'"),
])
def test_config_show_validates_plugin_params(tmp_path, text, named):
    config = tmp_path / "c.yaml"
    config.write_text(text)
    line = _one_error_line(run_cli("config", "show", "-m", "view-only", "-c", str(config)))
    assert named in line


def test_config_show_prints_a_valid_config():
    res = run_cli("config", "show", "-m", "view-only")
    assert res.returncode == 0, res.stderr
    assert "method: view-only" in res.stdout


# ------------------------------------------------------------------------------------------ scene size
def lattice_scene(n: int, name: str = "crowd") -> SceneSpec:
    """``n`` tuna cans on a 3 m x 2 m shelf, a lattice of 9.5 cm in layers of 651 (plausible placements)."""
    pitch, nx, ny = 0.095, 31, 21
    objects = []
    for k in range(n):
        layer, cell = divmod(k, nx * ny)
        j, i = divmod(cell, nx)
        objects.append(ObjectSpec(id=k, class_name="tuna_fish_can",
                                  position_m=(-1.5 + 0.05 + i * pitch, 0.05 + j * pitch, 0.033 * layer)))
    return SceneSpec(name=name, shelf=ShelfSpec(width_m=3.0, depth_m=2.0, height_m=0.28), objects=tuple(objects))


@pytest.mark.slow  # integration (subprocesses or a full scene build); CI runs it in make test-slow
def test_a_1000_object_scene_is_refused_with_its_estimate(tmp_path):
    scene = tmp_path / "crowd.json"
    scene.write_text(lattice_scene(1000).model_dump_json())
    line = _one_error_line(run_cli("run", "-m", "push-only", "--scene", str(scene), "--steps", "40",
                                   "--out", str(tmp_path / "run")))
    assert line.startswith("msmem: error: scene 'crowd': 1000 objects on a grid of 1,830,120 voxels: about 1.1 GiB "
                           "and 44 min of work for the objects (")
    assert "more than the limit of 30 min; use fewer objects or steps, or raise the limit with " \
           "MSMEM_MAX_SCENE_MINUTES" in line
    assert [p.name for p in tmp_path.iterdir()] == ["crowd.json"]


def test_the_scene_estimate_counts_objects_grid_and_manipulation_steps(monkeypatch):
    grid = GridSpec(voxel_m=0.01, shape=(100, 50, 30))
    small = estimate(20, grid, 15, 40, manipulates=True)
    assert small.memory_bytes == 150_000 * 616 + 20 * 100_000  # the belief's 616 B a voxel, 0.1 MB an object
    assert small.seconds == pytest.approx(4e-6 * 190 + 0.065 * 20 * 41)
    assert check_estimate(small, "scene 'small'") is small
    views = estimate(1000, grid, 15, 40, manipulates=False)
    assert views.seconds == pytest.approx(4e-6 * 499_500 + 65)  # views never move objects: no refresh per step
    check_estimate(views, "scene 'views'")
    pushes = estimate(1000, grid, 15, 40, manipulates=True)
    assert pushes.seconds > 60 * DEFAULT_MAX_MINUTES
    with pytest.raises(UserError, match=r"scene 'pushes': 1000 objects .* more than the limit of 30 min"):
        check_estimate(pushes, "scene 'pushes'")
    monkeypatch.setenv(MINUTES_VAR, "60")
    assert check_estimate(pushes, "scene 'pushes'") is pushes
    monkeypatch.setenv(MINUTES_VAR, "soon")
    with pytest.raises(UserError, match="MSMEM_MAX_SCENE_MINUTES='soon': expected a positive number"):
        check_estimate(small, "scene 'small'")
    huge = estimate(10, GridSpec(voxel_m=0.001, shape=(3000, 2000, 2000)), 15, 1, False)
    monkeypatch.delenv(MINUTES_VAR)
    with pytest.raises(UserError, match=r"scene 'huge': .* more memory than the limit of .* GiB \(half of physical"):
        check_estimate(huge, "scene 'huge'")


def test_build_episode_refuses_a_scene_above_the_limit():
    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import build_episode

    cfg = load_config("push-only", None, {"steps": 40})
    with pytest.raises(UserError, match=r"^scene 'crowd': 1000 objects .* more than the limit of 30 min"):
        build_episode(cfg, get_plugin_manager(), scene=lattice_scene(1000))


# ------------------------------------------------------------------------------------------ dead workers
def test_a_dead_worker_is_told_with_the_tasks_in_flight_then_pinned_on_its_task():
    told: list[list[int]] = []
    results = run_tasks(square_or_die, [1, 2, -1, 3], workers=2, progress=False, threads=None,
                        on_worker_death=told.append)
    assert told
    assert all(2 in t for t in told)
    assert isinstance(results[2], TaskFailure)
    assert results[2].worker_died
    assert [results[i] for i in (0, 1, 3)] == [1, 4, 9]


@pytest.mark.slow  # two spawned workers and a rerun: about 40 s
def test_a_dead_bench_worker_is_reported_in_one_line_naming_its_episode(tmp_path, monkeypatch, capsys):
    from msmem_core.run.bench import run_bench, suite_scenes

    monkeypatch.setenv("MSMEM_PLUGINS", "failing=tests.support.failing_plugin")  # the spawned workers inherit it
    config = tmp_path / "dying.yaml"
    config.write_text(SMALL + "simulator:\n  name: dying-pybullet\n  params: {die_on: [tune10-00]}\n")
    out = tmp_path / "bench"
    summary = run_bench(["view-only"], suite_scenes("tune10"), [0, 1], out, {"steps": 1}, str(config), "local", 2,
                        1, progress=False, suite="tune10")
    episode = out / "episodes" / "view-only__scene00.json"
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("msmem bench: ")]
    assert err[0].startswith("msmem bench: a worker process died while running episode")
    assert "view-only scene 0" in err[0]
    assert err[-1] == (f"msmem bench: episode view-only scene 0 killed its worker process (killed, e.g. by the "
                       f"out-of-memory killer, or crashed in native code): recorded as crashed in {episode}; the "
                       "other episodes go on")
    assert [e["scene_index"] for e in summary["errors"]] == [0]
    assert json.loads(episode.read_text())["status"] == "error"
    assert summary["table"]["view-only"]["episodes"] == 1  # scene 1 finished

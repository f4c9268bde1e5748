"""Commands are plugins (hook ``msmem_commands``), and the commands that drive a simulator take it from
the plugin manager (``--sim NAME``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from msmem_core.cli import build_app
from msmem_core.cli.docgen import cli_reference
from msmem_core.errors import PluginError
from msmem_core.plugins import CommandSpec, ComponentRef, get_plugin_manager
from msmem_core.plugins.manager import PluginLoadWarning
from tests.support.recording_sim import built

ROOT = Path(__file__).resolve().parents[1]
MSMEM = str(Path(sys.executable).with_name("msmem"))
SCENE = str(ROOT / "msmem_core" / "suites" / "hard25" / "scene_01.json")
"""A scene file for runs that test something else than the scene (loads in under a second, where
generating a hard scene takes 2-20 s)."""
PYTHONPATH = os.pathsep.join(str(ROOT / d) for d in ("", "plugins", "simulators"))


def run_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    full_env = {**os.environ, "PYTHONPATH": PYTHONPATH, **(env or {})}
    return subprocess.run([MSMEM, *args], capture_output=True, text=True, env=full_env, timeout=300, check=False,
                          cwd=ROOT)


# ------------------------------------------------------------------------------------- the hook
def test_builtin_plugins_register_their_commands(plugin_manager):
    where = {r.spec.path: r.plugin for r in plugin_manager.commands()}
    assert where == {"datagen grasp": "grasp", "train fe-vmf": "grasp", "eval fe-vmf": "grasp",
                     "bench-grasp": "grasp", "datagen cnabu": "cnabu", "train cnabu": "cnabu",
                     "eval belief-models": "cnabu", "train cnabu-map": "cnabu", "eval map": "cnabu",
                     "perf push": "push", "robot": "robots"}


@pytest.mark.slow  # integration (subprocesses or a full scene build); CI runs it in make test-slow
def test_plugin_command_appears_in_help_and_runs():
    env = {"MSMEM_PLUGINS": "cmds=tests.support.command_plugin"}
    top = run_cli("--help", env=env)
    assert top.returncode == 0, top.stderr
    assert "hello" in top.stdout
    assert "Greet someone (test plugin)." in top.stdout
    assert "tools" in top.stdout
    out = run_cli("hello", "--name", "shelf", env=env)
    assert (out.returncode, out.stdout) == (0, "hello, shelf\n"), out.stderr
    assert run_cli("eval", "echo", "hi", env=env).stdout == "echo: hi\n"
    assert run_cli("tools", "shout", "hi", env=env).stdout == "HI\n"
    evals = run_cli("eval", "--help", env=env).stdout
    assert "echo" in evals
    assert "belief-models" in evals
    assert "fe-vmf" in evals
    assert "hello" not in run_cli("--help").stdout  # only while the plugin is registered
    listed = json.loads(run_cli("plugins", "--json", env=env).stdout)["commands"]
    assert {"command": "msmem eval echo", "distribution": "MSMEM_PLUGINS", "plugin": "cmds",
            "summary": "Print the text back (test plugin)."} in listed


def test_raising_command_hook_is_reported_and_the_rest_of_the_cli_works():
    env = {"MSMEM_PLUGINS": "badcmds=tests.support.raising_commands_plugin"}
    top = run_cli("--help", env=env)
    assert top.returncode == 0, top.stderr
    assert "msmem: warning: msmem plugin 'badcmds' (from MSMEM_PLUGINS): its msmem_commands hook failed" in top.stderr
    assert "broken on purpose" in top.stderr
    assert "Traceback" not in top.stderr
    assert "bench-grasp" in top.stdout
    assert "datagen" in top.stdout
    datagen = run_cli("datagen", "--help", env=env)
    assert "cnabu" in datagen.stdout
    assert "grasp" in datagen.stdout
    shown = run_cli("config", "show", "--method", "view-only", env=env)
    assert shown.returncode == 0
    assert "method: view-only" in shown.stdout


def test_raising_command_hook_is_named_by_the_manager(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "badcmds=tests.support.raising_commands_plugin")
    pm = get_plugin_manager()
    with pytest.warns(PluginLoadWarning, match=r"plugin 'badcmds' .*msmem_commands hook failed.*broken on purpose"):
        paths = {r.spec.path for r in pm.commands()}
    assert "badcmds" in pm.command_errors
    assert {"datagen cnabu", "perf push", "bench-grasp"} <= paths


def test_commands_that_cannot_join_are_left_out_naming_the_plugin(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "misplaced=tests.support.misplaced_commands_plugin")
    with pytest.warns(PluginLoadWarning) as caught:
        app = build_app()
    text = "\n".join(str(w.message) for w in caught)
    assert "plugin 'misplaced'" in text
    assert "group 'nosuchgroup', which does not exist" in text
    assert "'msmem run' clashes with one of msmem's own" in text
    assert "'msmem bad-signature' is not a valid typer command" in text
    assert "MixedAnnotatedAndDefaultStyleError" in text
    assert "'msmem empty-group' is not a valid typer command" in text
    runner = CliRunner()
    assert runner.invoke(app, ["ok"]).output == "ok\n"
    assert "Run one mapping episode" in runner.invoke(app, ["run", "--help"]).output  # the core's run is kept


def test_cli_reference_documents_msmem_commands_only(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "cmds=tests.support.command_plugin")
    assert "## `msmem hello`" in cli_reference(build_app())
    documented = cli_reference(build_app(builtin_only=True))
    assert "msmem hello" not in documented
    assert "### `msmem datagen cnabu`" in documented
    assert "### `msmem perf push`" in documented


@pytest.mark.parametrize(("kwargs", "error"), [
    ({"name": "Bad Name!", "action": print, "summary": "x"}, r"command name 'bad name!' must be lower-case"),
    ({"name": "ok", "action": print, "summary": "two\nlines"}, r"command 'ok': summary must be one non-empty line"),
    ({"name": "ok", "action": print, "summary": " "}, r"summary must be one non-empty line"),
    ({"name": "ok", "action": 3, "summary": "x"}, r"command 'ok': action must be a function or a typer.Typer"),
    ({"name": "ok", "action": print, "summary": "x", "group": "Not A Group"}, r"group 'Not A Group'"),
])
def test_command_spec_is_checked(kwargs, error):
    with pytest.raises(PluginError, match=error):
        CommandSpec(**kwargs)


# ------------------------------------------------------------------------------------------- --sim
SIM_COMMANDS = [
    ["datagen", "cnabu", "--kind", "observe", "--scenes", "1"],
    ["datagen", "grasp", "--scenes", "1"],
    ["bench-grasp", "--scenes", "0"],
    ["eval", "belief-models", "--kind", "push", "--data", "tests/data/cnabu_heldout/push"],
]


@pytest.mark.parametrize("args", SIM_COMMANDS, ids=[" ".join(a[:2]) for a in SIM_COMMANDS])
def test_unknown_sim_is_a_one_line_error_naming_it(args, tmp_path):
    out_args = ["--out", str(tmp_path / "out")] if args[0] != "eval" else []
    res = run_cli(*args, *out_args, "--sim", "nosuch")
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.strip().splitlines() == ["msmem: error: no simulator named 'nosuch'; available: pybullet, sapien"]
    assert not (tmp_path / "out").exists()  # nothing was started


def test_sim_without_its_extra_says_what_to_install(tmp_path):
    import warnings

    try:
        with warnings.catch_warnings():  # sapien warns at import when the system has no libvulkan
            warnings.simplefilter("ignore")
            import sapien  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("sapien is installed: the missing-extra path cannot be exercised here")
    res = run_cli("datagen", "grasp", "--scenes", "1", "--out", str(tmp_path / "out"), "--sim", "sapien")
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "msmem: error: simulator 'sapien' needs the optional dependency group 'sapien': pip install 'msmem[sapien]' "
        "(import failed: No module named 'sapien')"]


@pytest.fixture
def recording(monkeypatch, tmp_path):
    """The ``recording`` simulator registered; returns the log of the configs it is built with."""
    log = str(tmp_path / "sim.jsonl")
    monkeypatch.setenv("MSMEM_PLUGINS", "recording=tests.support.recording_sim")
    monkeypatch.setenv("MSMEM_TEST_SIM_LOG", log)
    return log


def test_datagen_cnabu_simulates_in_the_named_backend(recording, tmp_path):
    out = tmp_path / "data"
    res = CliRunner().invoke(build_app(), ["datagen", "cnabu", "--kind", "observe", "--scenes", "1", "--seed", "4",
                                           "--samples", "1", "--min-views", "0", "--max-views", "0", "-q",
                                           "--sim", "recording", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "simulator recording" in res.output
    assert json.loads((out / "dataset.json").read_text())["config"]["simulator"] == {"name": "recording", "params": {}}
    # the up-front check, then the scene's simulator: seeded by the scene, the data config's label noise
    assert [(c["seed"], c["label_noise"]) for c in built(recording)] == [(0, 0.05), (4, 0.05)]
    from msmem_cnabu.learn.datagen import load_shard

    shard = load_shard(out / "scene_000004.npz")
    assert shard.info["config"]["simulator"]["name"] == "recording"
    # another simulator's shards do not join this folder
    again = CliRunner().invoke(build_app(), ["datagen", "cnabu", "--kind", "observe", "--scenes", "1", "-q",
                                             "--out", str(out)])
    assert "holds data simulated in 'recording'" in str(again.exception)
    assert "not in 'pybullet'" in str(again.exception)


@pytest.mark.slow  # an end-to-end run or a benchmark: the slow suite (CI) runs it
def test_grasp_datagen_and_bench_build_the_named_backend(recording, tmp_path):
    from msmem_grasp.fpp import FPPConfig
    from msmem_grasp.learn.bench import GraspBenchConfig, run_scene
    from msmem_grasp.learn.datagen import GraspDataConfig, make_shard

    ref = ComponentRef(name="recording", params={"label_noise": 0.2})
    cfg = GraspDataConfig(min_views=1, max_views=1, fpp=FPPConfig(num_points=256), simulator=ref)
    make_shard(7, cfg)
    assert built(recording) == [{"camera": cfg.fpp.camera.model_dump(), "seed": 7, "label_noise": 0.2}]
    rows = run_scene((3, GraspBenchConfig(scene_seeds=[3], trials=2, views=1, view_policy="random",
                                          skill={"predictor": "geometric"}, simulator=ref)))
    assert len(rows) == 2
    assert [(c["seed"], c["label_noise"]) for c in built(recording)[1:]] == [(3000, 0.2), (3001, 0.2)]


def test_a_command_registered_twice_keeps_the_first_registered_plugins():
    """Two plugins add ``msmem eval dup-cmd``: the one registered first is kept, the warning names both
    (pluggy calls hook implementations last-registered first; the registry reads them in registration
    order)."""
    from types import SimpleNamespace

    from msmem_core.plugins import CommandSpec, get_plugin_manager, hookimpl
    from msmem_core.plugins.manager import PluginLoadWarning

    def plugin(tag: str) -> SimpleNamespace:
        @hookimpl
        def msmem_commands():
            yield CommandSpec(name="dup-cmd", action=lambda: None, summary=tag, group="eval")

        return SimpleNamespace(msmem_commands=msmem_commands)

    pm = get_plugin_manager(extra_plugins=[("first", plugin("first")), ("second", plugin("second"))])
    with pytest.warns(PluginLoadWarning, match=r"registered twice: by plugin 'first' from <code> \(kept\) and by "
                                               r"plugin 'second' from <code> \(left out\)"):
        kept = [c for c in pm.commands() if c.spec.name == "dup-cmd"]
    assert [c.plugin for c in kept] == ["first"]

"""A plugin that fails is named: an exception from a component during a run or a bench episode is one line
naming the component, its plugin and distribution, the step and the exception (and the partial run
folder), exit code 3; the traceback only with ``--debug``. Plugin load warnings are printed once."""

from __future__ import annotations

import sys
from collections.abc import Callable
from types import SimpleNamespace

import pytest
from msmem_view.skill import ViewAction

from msmem_core.errors import ComponentFailure
from msmem_core.plugins import ComponentRef, get_plugin_manager
from msmem_core.plugins.manager import Component, failed_component
from tests.test_commands import SCENE, run_cli

FAILING = {"MSMEM_PLUGINS": "failing=tests.support.failing_plugin"}
SMALL = "camera: {width_px: 160, height_px: 120}\nig: {ray_stride_px: 8}\n"
FLAKY = SMALL + "skills:\n  - name: flaky-view\n    params: {fail_at: 1}\n"
NAMED = "skill 'flaky-view' (plugin 'failing' from MSMEM_PLUGINS)"


@pytest.mark.slow  # an end-to-end run: the slow suite (CI) runs it
def test_a_component_that_raises_mid_run_is_one_line_naming_it_and_the_partial_folder_rc_3(tmp_path):
    config = tmp_path / "flaky.yaml"
    config.write_text(FLAKY)
    out = tmp_path / "run"
    res = run_cli("run", "-m", "view-only", "-c", str(config), "--scene", SCENE, "--steps", "3", "-q",
                  "--no-report", "--out", str(out), env=FAILING)
    assert res.returncode == 3, res.stdout + res.stderr
    [partial] = tmp_path.glob("run.partial-*")
    assert res.stderr.splitlines() == [
        f"msmem: error: {NAMED} failed at step 1: RuntimeError: flaky on purpose at call 1; partial run in {partial} "
        "(--debug shows the traceback)"]
    assert len((partial / "steps.jsonl").read_text().splitlines()) == 1  # step 0 done, step 1 failed
    assert not out.exists()


def test_debug_shows_the_traceback_of_a_component_failure(monkeypatch, capsys):
    import msmem_core.cli.app as app

    def show() -> None:
        try:
            raise RuntimeError("deep inside the plugin")
        except RuntimeError as e:
            raise ComponentFailure("skill 'x' (plugin 'p' from d) failed at step 2: RuntimeError: deep") from e

    monkeypatch.setattr(app, "CORE_COMMANDS", {**app.CORE_COMMANDS, "config": {"show": show}})
    monkeypatch.setattr(sys, "argv", ["msmem", "config", "show"])
    with pytest.raises(SystemExit) as exit_:
        app.main()
    assert exit_.value.code == app.EXIT_PLUGIN_FAILURE == 3
    assert capsys.readouterr().err == ("msmem: error: skill 'x' (plugin 'p' from d) failed at step 2: RuntimeError: "
                                       "deep (--debug shows the traceback)\n")
    monkeypatch.setattr(sys, "argv", ["msmem", "--debug", "config", "show"])
    with pytest.raises(ComponentFailure) as raised:
        app.main()
    assert isinstance(raised.value.__cause__, RuntimeError)  # the plugin's own traceback is chained


def test_the_component_named_is_the_innermost_one_on_the_traceback(monkeypatch):
    """A skill's helper function raising is the skill's failure; a simulator called by the skill is the
    simulator's; code no plugin manager built is nobody's."""
    monkeypatch.setenv("MSMEM_PLUGINS", FAILING["MSMEM_PLUGINS"])
    pm = get_plugin_manager()
    skill = pm.build("skill", "flaky-view")
    with pytest.raises(RuntimeError) as raised:
        skill.propose(None)
    assert failed_component(raised.value) == Component("skill", "flaky-view", "failing", "MSMEM_PLUGINS")
    assert str(failed_component(raised.value)) == NAMED

    sim = pm.build("simulator", "pybullet")
    with pytest.raises(Exception) as raised:  # noqa: PT011 (any error: the simulator is asked to observe from no pose)
        skill.execute(sim, ViewAction(view=0), SimpleNamespace(viewpoints=[None]))
    assert failed_component(raised.value) == Component("simulator", "pybullet", "pybullet", "msmem")

    class Caller:
        def call(self, fn: Callable[[], object]) -> object:
            return fn()

    with pytest.raises(ZeroDivisionError) as raised:
        Caller().call(lambda: 1 / 0)
    assert failed_component(raised.value) is None


def test_a_factory_that_raises_is_named_with_where_the_config_names_it(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", FAILING["MSMEM_PLUGINS"])
    pm = get_plugin_manager()
    with pytest.raises(ComponentFailure) as raised:
        pm.build("skill", ComponentRef(name="flaky-view", params={"fail_build": True}), where="skills.0")
    assert str(raised.value) == f"{NAMED} failed while being built (skills.0): ValueError: cannot build on purpose"


def test_a_bench_episode_whose_component_raises_is_recorded_naming_it(tmp_path, monkeypatch):
    from msmem_core.run.bench import run_bench, suite_scenes

    monkeypatch.setenv("MSMEM_PLUGINS", FAILING["MSMEM_PLUGINS"])
    config = tmp_path / "flaky.yaml"
    config.write_text(FLAKY)
    summary = run_bench(["view-only"], suite_scenes("tune10"), [0], tmp_path / "bench", {"steps": 2}, str(config),
                        "local", 1, 1, progress=False, suite="tune10")
    [error] = summary["errors"]
    assert error["error"] == f"ComponentFailure: {NAMED} failed at step 1: RuntimeError: flaky on purpose at call 1"
    assert "- view-only scene 0: ComponentFailure: skill 'flaky-view'" in (tmp_path / "bench" / "table.md").read_text()


def test_plugin_load_warnings_are_printed_once_per_process(tmp_path):
    """`msmem run` makes a plugin manager for its command line and another for the run: each loads the
    plugins, and the broken one's warning used to be printed by both."""
    res = run_cli("run", "-m", "view-only", "--sim", "nosuch", "--out", str(tmp_path / "run"),
                  env={"MSMEM_PLUGINS": "broken=tests.support.broken_plugin"})
    assert res.returncode == 2, res.stderr
    assert res.stderr.count("msmem plugin 'broken' (tests.support.broken_plugin, from MSMEM_PLUGINS) failed to "
                            "load and is skipped: RuntimeError: this plugin is broken on purpose") == 1, res.stderr

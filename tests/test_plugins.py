"""Plugin system: user stories of third-party plugins, broken plugins, clashes and typos."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from msmem_core.errors import PluginError
from msmem_core.plugins import ComponentRef, get_plugin_manager
from msmem_core.plugins.manager import PluginLoadWarning

ROOT = Path(__file__).resolve().parents[1]
MSMEM = str(Path(sys.executable).with_name("msmem"))
EXTRA_PATH: list[str] = []
"""Folders of throwaway installs (``pip install --target``) the CLI subprocesses see first."""


def run_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    here = [str(ROOT / d) for d in ("", "plugins", "simulators")]  # this checkout's plugins too
    path = os.pathsep.join([*EXTRA_PATH, *here])
    full_env = {**os.environ, "PYTHONPATH": path, **(env or {})}
    return subprocess.run([MSMEM, *args], capture_output=True, text=True, env=full_env, timeout=300, check=False)


def test_builtin_components_are_registered_through_entry_points(plugin_manager):
    rows = plugin_manager.listing()
    builtin = {(r["kind"], r["name"]) for r in rows if r["distribution"] == "msmem"}
    assert {("skill", "view"), ("skill", "push"), ("simulator", "pybullet"), ("simulator", "sapien"),
            ("belief-model", "analytic-observation"), ("objective-term", "ig"),
            ("objective-term", "semantic-entropy")} <= builtin


def test_env_plugin_is_listed_and_built_from_config(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "good=tests.support.good_plugin")
    pm = get_plugin_manager()
    assert pm.registered("skill")["wait"].distribution == "MSMEM_PLUGINS"
    skill = pm.build("skill", ComponentRef(name="wait", params={"seconds": 0.5}))
    assert skill.config.seconds == 0.5
    term = pm.build("objective-term", ComponentRef(name="constant", params={"value": 3}))
    assert term.value == 3.0


def test_bad_params_name_the_component_and_field(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "good=tests.support.good_plugin")
    pm = get_plugin_manager()
    with pytest.raises(PluginError, match=r"skill 'wait': skills\.2\.params\.seconds: .*greater than 0"):
        pm.build("skill", ComponentRef(name="wait", params={"seconds": -1}), where="skills.2")
    with pytest.raises(PluginError, match=r"params\.nosuch: Extra inputs are not permitted"):
        pm.build("skill", ComponentRef(name="wait", params={"nosuch": 1}))


def test_unknown_component_lists_the_available_ones(plugin_manager):
    with pytest.raises(PluginError, match=r"no simulator named 'nosuch'; available: pybullet, sapien"):
        plugin_manager.build("simulator", "nosuch")


def test_broken_plugin_is_named_in_a_warning_and_the_rest_load(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "broken=tests.support.broken_plugin,good=tests.support.good_plugin")
    with pytest.warns(PluginLoadWarning, match=r"plugin 'broken' .*broken on purpose"):
        pm = get_plugin_manager()
    assert "broken" in pm.load_errors
    assert {"view", "wait"} <= set(pm.skills())


def test_duplicate_name_is_refused_naming_both_origins(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "clash=tests.support.duplicate_plugin")
    pm = get_plugin_manager()
    with pytest.warns(PluginLoadWarning) as caught:
        skills = pm.skills()
    msg = str(caught[0].message)
    assert "plugin 'clash' (from MSMEM_PLUGINS) is skipped: its skill 'view' clashes with plugin 'view' " in msg
    assert msg.endswith("from msmem")
    assert pm.registered("skill")["view"].distribution == "msmem"
    assert skills["view"].description != "clash"


def test_duplicate_name_between_third_parties_is_an_error(monkeypatch, tmp_path):
    (tmp_path / "good_again.py").write_text("from tests.support.good_plugin import msmem_skills  # noqa: F401\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("MSMEM_PLUGINS", "good=tests.support.good_plugin,again=good_again")
    pm = get_plugin_manager()
    with pytest.raises(PluginError, match=r"skill name 'wait' is registered twice: by plugin") as e:
        pm.skills()
    assert "plugin 'good' from MSMEM_PLUGINS" in str(e.value)
    assert "plugin 'again' from MSMEM_PLUGINS" in str(e.value)


def test_hook_name_typo_is_caught(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "typo=tests.support.typo_plugin")
    with pytest.raises(PluginError, match=r"plugin 'typo' .*msmem_skils"):
        get_plugin_manager()


def test_malformed_msmem_plugins_value_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("MSMEM_PLUGINS", "just_a_module")
    with pytest.raises(PluginError, match="must look like name=module"):
        get_plugin_manager()


def test_trace_prints_hook_calls(monkeypatch, capsys):
    monkeypatch.setenv("MSMEM_TRACE_PLUGINS", "1")
    get_plugin_manager().skills()
    assert "msmem_skills() -> view (msmem): view" in capsys.readouterr().err


def test_optional_backend_registers_and_says_which_extra(plugin_manager):
    try:
        import sapien  # noqa: F401
    except ImportError:
        with pytest.raises(PluginError, match=r"pip install 'msmem\[sapien\]'"):
            plugin_manager.build("simulator", "sapien")
    else:
        pytest.skip("sapien is installed: the missing-extra path cannot be exercised here")


@pytest.fixture(scope="module")
def installed_third_party(tmp_path_factory):
    """A tiny separately installed distribution with an ``msmem`` entry point."""
    root = tmp_path_factory.mktemp("thirdparty")
    pkg = root / "msmem_tinyplugin"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "plugin.py").write_text(textwrap.dedent('''
        from pydantic import BaseModel, ConfigDict
        from msmem_core.plugins import ObjectiveTermSpec, hookimpl
        import numpy as np

        class TimeCostConfig(BaseModel):
            model_config = ConfigDict(extra="forbid")
            seconds_per_action: float = 1.0

        class TimeCost:
            applies_to = frozenset({"perception", "manipulation"})
            def __init__(self, config):
                self.config = config
            def score(self, ctx, batch):
                return -np.full(len(batch.actions), self.config.seconds_per_action)

        @hookimpl
        def msmem_objective_terms():
            yield ObjectiveTermSpec(name="time-cost", factory=TimeCost, config_model=TimeCostConfig,
                                    description="A time cost per action")
    '''))
    (root / "pyproject.toml").write_text(textwrap.dedent('''
        [build-system]
        requires = ["setuptools>=61"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "msmem-tinyplugin"
        version = "0.0.1"
        [project.entry-points.msmem]
        tiny = "msmem_tinyplugin.plugin"
        [tool.setuptools]
        packages = ["msmem_tinyplugin"]
    '''))
    # into a throwaway folder, never into the live environment: put on sys.path (and the CLI's PYTHONPATH)
    # for this module only, so its entry points are found as an installed distribution's are
    target = root / "site"
    pip = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
           "--target", str(target), str(root)]
    subprocess.run(pip, check=True, capture_output=True, timeout=300)
    sys.path.insert(0, str(target))
    EXTRA_PATH.append(str(target))
    importlib.invalidate_caches()
    try:
        yield "msmem-tinyplugin"
    finally:
        sys.path.remove(str(target))
        EXTRA_PATH.remove(str(target))
        for name in [m for m in sys.modules if m.startswith("msmem_tinyplugin")]:
            del sys.modules[name]
        importlib.invalidate_caches()


def test_separately_installed_plugin_appears_in_cli_and_builds(installed_third_party):
    out = run_cli("plugins", "--json")
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)["components"]
    tiny = [r for r in rows if r["name"] == "time-cost"]
    assert tiny
    assert tiny[0]["distribution"] == installed_third_party
    assert tiny[0]["config"]["seconds_per_action"]["default"] == 1.0
    pm = get_plugin_manager()
    term = pm.build("objective-term", ComponentRef(name="time-cost", params={"seconds_per_action": 2.5}))
    assert term.config.seconds_per_action == 2.5


def test_disable_autoload_keeps_builtins_only(installed_third_party):
    out = run_cli("plugins", "--json", env={"MSMEM_DISABLE_PLUGIN_AUTOLOAD": "1"})
    names = {r["name"] for r in json.loads(out.stdout)["components"]}
    assert "time-cost" not in names
    assert {"view", "pybullet", "ig"} <= names


def test_a_plugin_named_twice_for_the_same_module_loads_once_without_a_warning(monkeypatch):
    """An installed plugin also listed in MSMEM_PLUGINS (the same module, e.g. a package's tests run
    from its source folder) is the same plugin, not a clash."""
    import warnings

    monkeypatch.setenv("MSMEM_PLUGINS", "good=tests.support.good_plugin")
    pm = get_plugin_manager()
    with warnings.catch_warnings():
        warnings.simplefilter("error", PluginLoadWarning)
        pm._load_one("good", "tests.support.good_plugin", "some-dist", lambda: None)
        pm._load_one("good", "tests.support.good_plugin:plugin", "other-dist", lambda: None)
    assert "wait" in pm.skills()
    with pytest.warns(PluginLoadWarning, match="the name is taken"):
        pm._load_one("good", "tests.support.broken_plugin", "some-dist", lambda: None)

"""Plugin isolation: a plugin that exits, raises in a hook or takes a built-in's name is
named and skipped; the others load and every command keeps working (as pytest and conda do it).

Third-party distributions are throwaway ``*.dist-info`` folders on ``sys.path``: importlib.metadata
finds their entry points as it finds an installed distribution's, and nothing is installed.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from msmem_core.plugins import get_plugin_manager
from msmem_core.plugins.manager import PluginLoadWarning

ROOT = Path(__file__).resolve().parents[1]
MSMEM = str(Path(sys.executable).with_name("msmem"))

EXITING = "import sys\nsys.exit(3)\n"
BASE_EXIT = "raise BaseException('a BaseException at import')\n"
RAISING_HOOK = textwrap.dedent('''
    from msmem_core.plugins import hookimpl

    @hookimpl
    def msmem_skills():
        raise ValueError("this skill hook is broken on purpose")
        yield
''')
EXITING_HOOK = textwrap.dedent('''
    import sys
    from msmem_core.plugins import hookimpl

    @hookimpl
    def msmem_objective_terms():
        sys.exit("no terms today")
''')
VIEW_SKILL = textwrap.dedent('''
    from msmem_core.plugins import SkillSpec, hookimpl
    from tests.support.good_plugin import WaitConfig, WaitSkill

    @hookimpl
    def msmem_skills():
        yield SkillSpec(name="view", factory=WaitSkill, config_model=WaitConfig, description="an impostor")
''')


def _modules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, **sources: str) -> None:
    """Write each ``name=source`` as module ``name`` in a folder put first on ``sys.path``."""
    for name, text in sources.items():
        (tmp_path / f"{name}.py").write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    for name in sources:
        sys.modules.pop(name, None)


def _dist(site: Path, name: str, entry_points: dict[str, str]) -> None:
    """A throwaway installed distribution: only its metadata and its ``msmem`` entry points."""
    info = site / f"{name.replace('-', '_')}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    lines = "".join(f"{k} = {v}\n" for k, v in entry_points.items())
    (info / "entry_points.txt").write_text(f"[msmem]\n{lines}")


def _cli(*args: str, extra_path: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    here = [str(ROOT / d) for d in ("", "plugins", "simulators")]
    full = {**os.environ, "PYTHONPATH": os.pathsep.join([*extra_path, *here]), **env}
    return subprocess.run([MSMEM, *args], capture_output=True, text=True, env=full, timeout=300, check=False)


@pytest.mark.parametrize(("source", "reason"), [(EXITING, "SystemExit: 3"),
                                                (BASE_EXIT, "BaseException: a BaseException at import")])
def test_plugin_that_exits_at_import_is_skipped_and_the_others_load(tmp_path, monkeypatch, source, reason):
    _modules(tmp_path, monkeypatch, iso_exiting=source)
    monkeypatch.setenv("MSMEM_PLUGINS", "exiting=iso_exiting,good=tests.support.good_plugin")
    with pytest.warns(PluginLoadWarning, match=rf"plugin 'exiting' .*failed to load and is skipped: {reason}"):
        pm = get_plugin_manager()
    assert pm.load_errors["exiting"] == reason
    assert {"view", "push", "wait"} <= set(pm.skills())


def test_keyboard_interrupt_at_import_is_not_swallowed(tmp_path, monkeypatch):
    _modules(tmp_path, monkeypatch, iso_interrupt="raise KeyboardInterrupt\n")
    monkeypatch.setenv("MSMEM_PLUGINS", "interrupt=iso_interrupt")
    with pytest.raises(KeyboardInterrupt):
        get_plugin_manager()


@pytest.mark.parametrize(("source", "kind", "reason"), [
    (RAISING_HOOK, "skill", "msmem_skills hook failed: ValueError: this skill hook is broken on purpose"),
    (EXITING_HOOK, "objective-term", "msmem_objective_terms hook failed: SystemExit: no terms today"),
])
def test_plugin_whose_hook_raises_is_skipped_and_the_others_work(tmp_path, monkeypatch, source, kind, reason):
    _modules(tmp_path, monkeypatch, iso_hook=source)
    monkeypatch.setenv("MSMEM_PLUGINS", "hooky=iso_hook,good=tests.support.good_plugin")
    pm = get_plugin_manager()
    with pytest.warns(PluginLoadWarning, match=r"plugin 'hooky' \(from MSMEM_PLUGINS\) is skipped: msmem_"):
        names = set(pm.registered(kind))
    assert pm.load_errors["hooky"] == reason
    assert not pm.has_plugin("hooky")
    # every kind still works, the good plugin's components included
    assert {"view", "push", "wait"} <= set(pm.skills())
    assert {"ig", "constant"} <= set(pm.objective_terms())
    assert names
    assert "pybullet" in pm.simulators()


def test_plugins_command_lists_a_plugin_that_exits_as_failed(tmp_path, monkeypatch):
    _modules(tmp_path, monkeypatch, iso_exiting=EXITING, iso_hook=RAISING_HOOK)
    out = _cli("plugins", extra_path=[str(tmp_path)],
               env={"MSMEM_PLUGINS": "exiting=iso_exiting,hooky=iso_hook,good=tests.support.good_plugin"})
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr
    assert "wait" in out.stdout  # the table was printed: the good plugin and the built-ins are listed
    assert "pybullet" in out.stdout
    assert "failed plugin 'exiting' (from MSMEM_PLUGINS): SystemExit: 3" in out.stderr
    assert ("failed plugin 'hooky' (from MSMEM_PLUGINS): msmem_skills hook failed: "
            "ValueError: this skill hook is broken on purpose") in out.stderr


@pytest.fixture
def impostor_site(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A site folder first on ``sys.path``, so its distributions are found before msmem's own."""
    site = tmp_path / "site"
    site.mkdir()
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    yield site
    importlib.invalidate_caches()


def test_third_party_plugin_named_like_a_builtin_is_refused(impostor_site, monkeypatch):
    (impostor_site / "iso_impostor.py").write_text(VIEW_SKILL.replace('name="view"', 'name="impostor-view"'))
    _dist(impostor_site, "msmem-impostor", {"view": "iso_impostor"})
    sys.modules.pop("iso_impostor", None)
    with pytest.warns(PluginLoadWarning) as caught:
        pm = get_plugin_manager()
    text = "\n".join(str(w.message) for w in caught)
    assert ("plugin 'view' from msmem-impostor is refused: the name is taken by plugin 'view' from msmem"
            in text)
    assert pm.distributions["view"] == "msmem"
    assert pm.registered("skill")["view"].distribution == "msmem"
    assert "impostor-view" not in pm.skills()
    assert "msmem-impostor:view" in pm.load_errors


def test_third_party_component_named_like_a_builtin_is_refused(impostor_site, monkeypatch):
    (impostor_site / "iso_clash.py").write_text(VIEW_SKILL)
    _dist(impostor_site, "msmem-clash", {"clash": "iso_clash"})
    sys.modules.pop("iso_clash", None)
    pm = get_plugin_manager()
    with pytest.warns(PluginLoadWarning, match=r"plugin 'clash' \(from msmem-clash\) is skipped: its skill 'view' "
                                               r"clashes with plugin 'view' from msmem"):
        skills = pm.skills()
    assert pm.registered("skill")["view"].distribution == "msmem"
    assert skills["view"].description != "an impostor"
    assert "clash" in pm.load_errors

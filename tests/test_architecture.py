"""The core's import rules, checked on the source (docs/explanation/design.md, "Layers").

- ``msmem_core`` imports no plugin and no backend;
- a core module imports only from its own layer or the layers below it (listed bottom-up in
  ``LAYERS``), and there is no import cycle between core modules;
- plugins never build a backend directly: they reach physics through the plugin manager;
- a plugin's run time never imports its ``learn`` subpackage (data generation, training, evaluation):
  only its ``commands`` module does, inside the command bodies; and a plugin package has no import cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "msmem_core"
LAYERS = [  # bottom-up; a module may import from its own layer and the ones before it
    ("errors", "util", "presets", "suites"),
    ("world",),
    ("map",),
    ("interfaces",),
    ("plugins",),
    ("config",),
    ("msas",),
    ("sim",),
    ("run",),
    ("learn",),
    ("perf",),
    ("testing",),
    ("cli",),
]
RANK = {name: i for i, names in enumerate(LAYERS) for name in names}
PLUGIN_PACKAGES = sorted(p.name for d in ("plugins", "simulators") for p in (ROOT / d).glob("msmem_*") if p.is_dir())


def _module(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module named by an import statement in the file (including function-level imports)."""
    return _imports_in([ast.parse(path.read_text(), str(path))])


def _module_level_imports(path: Path) -> set[str]:
    """The modules imported at the top of the file (not inside a function or class body)."""
    tree = ast.parse(path.read_text(), str(path))
    return _imports_in([n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom | ast.If | ast.Try)])


def _imports_in(nodes: list[ast.AST]) -> set[str]:
    out: set[str] = set()
    for top in nodes:
        for node in ast.walk(top):
            if isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                out.add(node.module)
                out.update(f"{node.module}.{a.name}" for a in node.names)
    return out


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "msmem_core" else None


CORE_FILES = sorted(CORE.rglob("*.py"))


def test_every_core_module_has_a_layer() -> None:
    missing = {_layer(_module(f)) for f in CORE_FILES} - set(RANK) - {None}
    assert not missing, f"core modules outside every layer: {missing}; add them to LAYERS"


@pytest.mark.parametrize("path", CORE_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_core_imports_no_plugin_and_nothing_above_it(path: Path) -> None:
    me = _layer(_module(path))
    for name in _imports(path):
        top = name.split(".")[0]
        assert top not in PLUGIN_PACKAGES, f"{path.relative_to(ROOT)} imports plugin {name}"
        other = _layer(name)
        if me is None or other is None or other not in RANK:
            continue
        assert RANK[other] <= RANK[me], f"{path.relative_to(ROOT)} (layer {me}) imports {name} (layer {other})"


def _assert_no_import_cycle(files: list[Path], root: Path = ROOT) -> None:
    """No cycle among the modules of ``files`` (named relative to ``root``), function-level imports included."""
    modules = {_module(f, root): f for f in files}
    graph = {m: {n for n in _imports(f) if n in modules and n != m} for m, f in modules.items()}
    # parents import their subpackages' names: only module -> module edges of distinct files count
    state: dict[str, int] = {}

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycle = [*stack[stack.index(n):], n] if n in stack else [m, n]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n, [*stack, n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_no_import_cycle_between_core_modules() -> None:
    _assert_no_import_cycle(CORE_FILES)


@pytest.mark.parametrize("path", sorted((ROOT / "plugins").rglob("*.py")), ids=lambda p: str(p.relative_to(ROOT)))
def test_plugins_do_not_build_backends(path: Path) -> None:
    text = path.read_text()
    for banned in ("msmem_pybullet", "msmem_sapien", "PyBulletSimulator", "SapienSimulator"):
        assert banned not in text, f"{path.relative_to(ROOT)} names {banned}: get the simulator from the plugin manager"


@pytest.mark.parametrize("path", CORE_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_core_text_names_no_plugin_package(path: Path) -> None:
    """The issue's grep rule, on the whole text (docstrings and comments too): core is plugin-neutral."""
    text = path.read_text()
    for name in ("msmem_grasp", "msmem_push", "msmem_cnabu"):
        assert name not in text, f"{path.relative_to(ROOT)} names the plugin package {name}"


# plugins whose learning code lives in a ``learn`` subpackage, apart from what an episode imports
LEARNING_PLUGINS = ("msmem_grasp", "msmem_cnabu")


def _runtime_files(package: str) -> list[Path]:
    folder = ROOT / "plugins" / package
    return sorted(f for f in folder.rglob("*.py") if "learn" not in f.relative_to(folder).parts)


def test_learning_plugins_have_a_learn_subpackage() -> None:
    for package in LEARNING_PLUGINS:
        assert (ROOT / "plugins" / package / "learn" / "__init__.py").is_file(), f"{package} has no learn/"


@pytest.mark.parametrize("path", [f for p in LEARNING_PLUGINS for f in _runtime_files(p)],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_plugin_run_time_does_not_import_its_learn_subpackage(path: Path) -> None:
    """What an episode imports never pulls in training code; ``commands`` (the CLI's door into
    learning) may import ``learn`` inside its command bodies only, so importing it stays cheap."""
    package = path.relative_to(ROOT / "plugins").parts[0]
    learn = f"{package}.learn"
    names = _module_level_imports(path) if path.name == "commands.py" else _imports(path)
    bad = sorted(n for n in names if n == learn or n.startswith(learn + "."))
    assert not bad, f"{path.relative_to(ROOT)} imports {', '.join(bad)}: run time never imports {learn}"


@pytest.mark.parametrize("package", LEARNING_PLUGINS)
def test_no_import_cycle_in_a_learning_plugin(package: str) -> None:
    _assert_no_import_cycle(sorted((ROOT / "plugins" / package).rglob("*.py")), ROOT / "plugins")


BUILT_IN_SKILLS = ("view", "push", "grasp")
NOT_A_SKILL_NAME = "not a skill name"
"""The comment that marks a line whose string equal to a skill name means something else (a field, a label)."""
SKILL_NEUTRAL_FILES = [f for f in CORE_FILES if f.relative_to(CORE).parts[0] not in ("presets", "testing")]


def skill_names_in_code(source: str, names: tuple[str, ...] = BUILT_IN_SKILLS) -> list[tuple[int, str]]:
    """(line, name) of every string literal of ``source`` equal to one of ``names``, docstrings left out,
    and lines marked ``# ... not a skill name`` too."""
    tree = ast.parse(source)
    docstrings = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
    lines = source.splitlines()
    return sorted((n.lineno, n.value) for n in ast.walk(tree)
                  if isinstance(n, ast.Constant) and n.value in names and id(n) not in docstrings
                  and NOT_A_SKILL_NAME not in lines[n.lineno - 1])


def test_the_built_in_skill_names_are_the_registered_ones() -> None:
    from msmem_core.plugins import get_plugin_manager

    assert set(BUILT_IN_SKILLS) <= set(get_plugin_manager().skills())


def test_the_skill_name_check_finds_names_in_code_only() -> None:
    source = '''"""Pushes and grasps: "push" in a docstring is fine."""
def f(kinds, skill):
    """Counts "view"."""
    n = kinds.count("view")
    m = skill == "push"
    action.get("view")  # the field, not a skill name
    return {"grasps": n, "grasp": m}
'''
    assert skill_names_in_code(source) == [(4, "view"), (5, "push"), (7, "grasp")]


@pytest.mark.parametrize("path", SKILL_NEUTRAL_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_core_code_names_no_built_in_skill(path: Path) -> None:
    """Core counts and branches on a skill's ``category`` or the names in the run's config, never on a
    plugin's skill name, so an outside skill is treated as the built-in ones are. The defaults that
    name built-in skills live in ``msmem_core/presets``; a string that equals a skill name but means
    something else is marked on its line with the comment ``not a skill name``."""
    found = skill_names_in_code(path.read_text())
    assert not found, f"{path.relative_to(ROOT)} names built-in skills in code at " + ", ".join(
        f"line {line} ({name!r})" for line, name in found)


HOOKS = ("propose", "track", "execute", "score", "refine")
"""The methods of ``Skill`` and ``Term`` that MSAS calls with the step's ``DecisionContext``."""
HOOK_FILES = sorted(f for d in (CORE, ROOT / "plugins", ROOT / "examples" / "msmem-nudge" / "msmem_nudge")
                    for f in d.rglob("*.py") if not f.is_relative_to(CORE / "cli"))  # the CLI's ctx: a click context


def _ctx_annotations(source: str) -> list[tuple[int, str, str]]:
    """(line, function, annotation) of every parameter named ``ctx`` of a hook method or annotated ``Any``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            for arg in node.args.args + node.args.kwonlyargs:
                text = ast.unparse(arg.annotation) if arg.annotation is not None else ""
                if arg.arg == "ctx" and (node.name in HOOKS or text == "Any"):
                    out.append((node.lineno, node.name, text))
    return sorted(out)


@pytest.mark.parametrize("path", HOOK_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_hooks_type_their_context(path: Path) -> None:
    """Skills' and terms' hooks (and the helpers they hand the context to) take a ``DecisionContext``, not
    ``Any``: the type checker sees what a plugin reads of it."""
    wrong = [(line, name, text) for line, name, text in _ctx_annotations(path.read_text())
             if text != "DecisionContext"]
    assert not wrong, f"{path.relative_to(ROOT)}: " + ", ".join(
        f"{name} (line {line}) takes ctx: {text or 'unannotated'}" for line, name, text in wrong)


def test_the_context_check_finds_untyped_hooks_and_helpers() -> None:
    source = '''class S:
    def propose(self, ctx: Any) -> list: ...
    def track(self, ctx) -> None: ...
    def score(self, ctx: DecisionContext, batch) -> None: ...
def helper(ctx: Any) -> None: ...
def other(ctx: Tensor) -> None: ...
'''
    assert _ctx_annotations(source) == [(2, "propose", "Any"), (3, "track", ""), (4, "score", "DecisionContext"),
                                        (5, "helper", "Any")]


def test_the_cli_starts_without_the_heavy_libraries():
    """Registering every plugin and validating a config must not import what only running needs:
    scipy's statistics, image and spatial modules, trimesh, torch and open3d take 0.1-0.7 s
    each to import, and a command that refuses its input should not wait for them."""
    import subprocess
    import sys

    heavy = ("scipy.stats", "scipy.ndimage", "scipy.signal", "scipy.spatial", "trimesh", "torch", "open3d")
    code = ("import sys\n"
            "from msmem_core.config import load_config\n"
            "from msmem_core.plugins import get_plugin_manager\n"
            "from msmem_core.run.bench import summarise\n"
            "from msmem_core.run.runner import check_components\n"
            "check_components(load_config('ours', None, {}), get_plugin_manager())\n"
            f"print(' '.join(m for m in {heavy!r} if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.split() == []

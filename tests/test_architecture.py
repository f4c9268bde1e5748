"""The core's import rules, checked on the source (docs/explanation/design.md, "Layers").

- ``msmem_core`` imports no plugin and no backend;
- a core module imports only from its own layer or the layers below it (listed bottom-up in
  ``LAYERS``), and there is no import cycle between core modules;
- plugins never build a backend directly: they reach physics through the plugin manager.
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


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module named by an import statement in the file (including function-level imports)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
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


def test_no_import_cycle_between_core_modules() -> None:
    modules = {_module(f): f for f in CORE_FILES}
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

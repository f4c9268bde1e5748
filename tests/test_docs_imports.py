"""Every import line of msmem's own modules in the manual's Python blocks (the API reference, the
how-to guides and the tutorials) imports: a renamed module or name fails here, not in a reader's hands."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
API = ROOT / "docs" / "reference" / "api.md"
PAGES = [API, *sorted((ROOT / "docs" / "how-to").glob("*.md")), *sorted((ROOT / "docs" / "tutorials").glob("*.md"))]
OURS = ("msmem_core", "msmem_analytic", "msmem_cnabu", "msmem_grasp", "msmem_objectives", "msmem_push",
        "msmem_robots", "msmem_view", "msmem_pybullet")
BLOCK = re.compile(r"```python\n(.*?)```", re.S)


def import_statements(text: str) -> list[str]:
    """The ``import`` / ``from ... import`` statements of msmem's modules in the page's Python blocks."""
    out = []
    for block in BLOCK.findall(text):
        try:
            tree = ast.parse(block)
        except SyntaxError:  # a fragment (e.g. a signature): take its import lines one by one
            lines = [ln.strip() for ln in block.splitlines() if re.match(r"\s*(from \S+ import [^(]+$|import \S+)", ln)]
            tree = ast.parse("\n".join(lines)) if lines else ast.Module(body=[], type_ignores=[])
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in OURS:
                out.append(ast.unparse(node))
            elif isinstance(node, ast.Import) and any(a.name.split(".")[0] in OURS for a in node.names):
                out.append(ast.unparse(node))
    return out


DEFINED = re.compile(r"`(?:class|def) (\w+)[^`]*` in `((?:msmem_\w+)(?:\.\w+)*)`")


def reference_imports(text: str) -> list[str]:
    """The API reference's "`class Name(...)` in `module`" lines as ``from module import Name``."""
    return [f"from {module} import {name}" for name, module in DEFINED.findall(text)]


CASES = [(p, s) for p in PAGES for s in import_statements(p.read_text())]
CASES += [(API, s) for s in reference_imports(API.read_text())]


def test_the_manual_has_import_lines_to_check() -> None:
    assert len(CASES) >= 20
    assert {p.parent.name for p, _ in CASES} >= {"reference", "how-to"}


@pytest.mark.parametrize(("page", "statement"), CASES, ids=[f"{p.relative_to(ROOT)}: {s}" for p, s in CASES])
def test_import_line_imports(page: Path, statement: str) -> None:
    exec(compile(statement, str(page), "exec"), {})

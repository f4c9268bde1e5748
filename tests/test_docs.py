"""The docs stay true: generated references equal what the code generates, shell blocks marked
runnable run as written, and relative links point at files that exist."""

from __future__ import annotations

import difflib
import os
import re
import subprocess
from pathlib import Path

import pytest

from msmem_core.cli import build_app
from msmem_core.cli.docgen import api_reference, cli_reference, config_reference

ROOT = Path(__file__).resolve().parents[1]
DOCS = [*sorted((ROOT / "docs").rglob("*.md")), ROOT / "README.md", ROOT / "examples" / "msmem-nudge" / "README.md"]
FENCE = re.compile(r"^```bash runnable[^\n]*\n(.*?)^```", re.S | re.M)


def runnable_blocks() -> list[tuple[str, str]]:
    blocks = []
    for path in DOCS:
        text = path.read_text()
        for m in FENCE.finditer(text):
            line = text[: m.start()].count("\n") + 1
            blocks.append((f"{path.relative_to(ROOT)}:{line}", m.group(1)))
    return blocks


def _same(path: Path, generated: str, command: str) -> None:
    committed = path.read_text()
    if committed != generated:
        diff = "".join(list(difflib.unified_diff(committed.splitlines(True), generated.splitlines(True),
                                                 "committed", "generated"))[:60])
        pytest.fail(f"{path.relative_to(ROOT)} is stale: run `make docs` (or `{command}`)\n{diff}")


REFERENCE = ROOT / "docs" / "reference"


def test_config_reference_is_generated_from_the_models():
    _same(REFERENCE / "config.md", config_reference(), "msmem docs config > docs/reference/config.md")


def test_cli_reference_is_generated_from_the_commands():
    _same(REFERENCE / "cli.md", cli_reference(build_app(builtin_only=True)), "msmem docs cli > docs/reference/cli.md")


def test_api_reference_is_generated_from_the_docstrings():
    _same(REFERENCE / "api.md", api_reference(), "msmem docs api > docs/reference/api.md")


def test_results_page_is_generated_from_the_committed_result_folders():
    from msmem_core.run.results import results_page

    _same(ROOT / "docs" / "results.md", results_page(ROOT / "docs" / "results"),
          "msmem docs results > docs/results.md")


def test_the_docs_have_runnable_blocks():
    assert len(runnable_blocks()) >= 5


# each block runs msmem commands end to end (10-15 s each): the slow suite's, which CI runs
@pytest.mark.slow
@pytest.mark.parametrize(("where", "script"), runnable_blocks(), ids=[w for w, _ in runnable_blocks()])
def test_runnable_shell_blocks_run_as_written(where, script):
    if not (ROOT / ".venv" / "bin" / "msmem").exists():
        pytest.skip("the docs' commands use .venv/bin/...; create the venv with `make setup`")
    env = {k: v for k, v in os.environ.items() if k not in ("MSMEM_PLUGINS", "MSMEM_DISABLE_PLUGIN_AUTOLOAD")}
    out = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=ROOT, capture_output=True, text=True,
                         timeout=300, env=env, check=False)
    tail = f"{out.stdout[-2000:]}\n{out.stderr[-3000:]}"
    assert out.returncode == 0, f"{where} failed ({out.returncode}):\n{script}\n{tail}"


@pytest.mark.parametrize("path", DOCS, ids=[str(p.relative_to(ROOT)) for p in DOCS])
def test_relative_links_point_at_existing_files(path):
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    broken = [link for link in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
              if "://" not in link and not (path.parent / link).exists()]
    assert not broken, f"{path.relative_to(ROOT)} links to missing files: {broken}"


def test_every_name_the_api_reference_lists_under_the_testing_kit_imports_from_msmem_core_testing():
    import msmem_core.testing as kit

    text = (REFERENCE / "api.md").read_text()
    names = set()
    for section in text.split("\n## ")[1:]:
        if section.startswith("Testing kit"):
            names |= set(re.findall(r"^- \[`(\w+)`\]", section, re.M))
    assert len(names) >= 15
    missing = sorted(n for n in names if not hasattr(kit, n))
    assert not missing, f"api.md lists {missing} under the testing kit; msmem_core.testing does not export them"

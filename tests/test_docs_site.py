"""The manual builds as a website (``make docs-site``): ``mkdocs build --strict`` over ``mkdocs.yml``
fails on a broken link or anchor and on a page that is in neither the nav nor ``not_in_nav``. The build
needs the optional ``docs`` extra; without it that test is skipped, and the checks of the configuration
and of the link hook still run."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
HAVE_DOCS_EXTRA = all(importlib.util.find_spec(m) is not None
                      for m in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers"))


def _hooks():
    spec = importlib.util.spec_from_file_location("mkdocs_hooks", ROOT / "mkdocs_hooks.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _config() -> dict:
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text())


@pytest.mark.skipif(not HAVE_DOCS_EXTRA, reason="the `docs` extra (mkdocs, mkdocs-material, mkdocstrings) is not "
                                                "installed: pip install -e '.[docs]', or run `make docs-site`")
def test_the_site_builds_strict_with_no_broken_link_and_no_page_left_out_of_the_nav(tmp_path):
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=600, check=False,
                         env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    warnings = [line for line in out.stderr.splitlines() if "WARNING" in line or "ERROR" in line]
    assert out.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(warnings or out.stderr.splitlines()[-30:])
    assert (tmp_path / "site" / "reference" / "python" / "interfaces" / "index.html").is_file()


def test_broken_links_anchors_and_pages_missing_from_the_nav_fail_the_build():
    validation = _config()["validation"]
    assert validation["nav"]["omitted_files"] == "warn"
    assert validation["links"]["not_found"] == "warn"
    assert validation["links"]["anchors"] == "warn"
    assert _config()["strict"] is True, "warnings must fail the build"


def test_the_nav_holds_the_four_parts_and_every_page_it_names_exists():
    nav = _config()["nav"]
    titles = [next(iter(entry)) for entry in nav if isinstance(entry, dict)]
    assert {"Tutorials", "How-to guides", "Reference", "Explanation"} <= set(titles)

    def pages(entries):
        for entry in entries:
            value = entry if isinstance(entry, str) else next(iter(entry.values()))
            if isinstance(value, list):
                yield from pages(value)
            else:
                yield value

    missing = [p for p in pages(nav) if not (ROOT / "docs" / p).is_file()]
    assert not missing, f"the nav names pages that do not exist: {missing}"


def test_the_hook_turns_links_out_of_docs_into_text_and_leaves_broken_ones_for_the_build():
    hooks = _hooks()
    page = SimpleNamespace(file=SimpleNamespace(src_path="explanation/x.md"))
    config = {"docs_dir": str(ROOT / "docs"), "repo_url": ""}
    md = ("[card](../../plugins/msmem_cnabu/weights/MODEL_CARD_map.md) [in docs](push.md#falls) "
          "[gone](../../no/such/file.md)\n\n```text\n[card](../../CHANGELOG.md)\n```\n")
    out = hooks.on_page_markdown(md, page, config, None)
    assert "card (`plugins/msmem_cnabu/weights/MODEL_CARD_map.md`)" in out
    assert "[in docs](push.md#falls)" in out
    assert "[gone](../../no/such/file.md)" in out, "a broken link must stay for --strict to report"
    assert "[card](../../CHANGELOG.md)" in out, "code blocks are left as written"
    config["repo_url"] = "https://example.org/msmem"
    out = hooks.on_page_markdown("[log](../../CHANGELOG.md#2026)", page, config, None)
    assert out == "[log](https://example.org/msmem/blob/main/CHANGELOG.md#2026)"

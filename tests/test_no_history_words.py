"""The project speaks of what it is, not of how it was made: no "session N" or "issue N" in the README,
the docs, the examples, the code or the tests, and no pointer to a ``DESIGN.md`` that the repository
does not hold (the design is in docs/).

Dated studies in ``docs/lab/`` keep their history, and so do the generated data of result folders under
``docs/results/`` (episode files, results.json, table.md): only their hand-written README.md files are
read. A link into ``docs/lab/`` may name one of its archived anchors."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("README.md", "docs", "examples", "msmem_core", "plugins", "simulators", "tests")
SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".json", ".sh", ".txt", ".cfg", ".html", ".js", ".css"}
SKIPPED = ("docs/lab/", "tests/data/")
HISTORY = re.compile(r"\b(?:sessions?|issues?)[ -]\d+\b", re.I)
DESIGN = re.compile(r"\bDESIGN\.md\b")
# a link target inside docs/lab/ (an archived heading's anchor may carry its history)
LAB_LINK = re.compile(r"\S*lab/[^\s)#]*#[\w-]+")

# Lines left to files whose owners are rewriting them; each entry is cleared with its file. An empty
# tuple leaves the whole file.
ALLOW: dict[str, tuple[str, ...]] = {}
"""Files and the phrases in them the scan lets pass (none today)."""


def scanned_files() -> list[Path]:
    me = Path(__file__).resolve()
    files = []
    for top in SCANNED:
        path = ROOT / top
        candidates = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
        for p in candidates:
            rel = p.relative_to(ROOT).as_posix()
            if p.resolve() == me or p.suffix not in SUFFIXES or rel.startswith(SKIPPED) or "__pycache__" in rel:
                continue
            if rel.startswith("docs/results/") and p.name != "README.md":
                continue
            files.append(p)
    return files


def hits(path: Path) -> list[str]:
    rel = path.relative_to(ROOT).as_posix()
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return []
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        allowed = ALLOW.get(rel)
        if allowed is not None and (not allowed or any(phrase in line for phrase in allowed)):
            continue
        bare = LAB_LINK.sub("", line)
        for m in [*HISTORY.finditer(bare), *DESIGN.finditer(bare)]:
            found.append(f"{rel}:{number}: {m.group(0)!r} in {line.strip()[:160]}")
    return found


def test_the_scan_reads_every_part_of_the_project():
    tops = {p.relative_to(ROOT).parts[0] for p in scanned_files()}
    assert tops >= {"README.md", "docs", "examples", "msmem_core", "plugins", "simulators", "tests"}
    rels = {p.relative_to(ROOT).as_posix() for p in scanned_files()}
    assert "docs/results/falls/README.md" in rels
    assert not any(r.startswith(("docs/lab/", "tests/data/")) for r in rels)
    assert "tests/test_no_history_words.py" not in rels


def test_no_session_or_issue_numbers_and_no_design_md():
    found = [h for p in scanned_files() for h in hits(p)]
    assert not found, (
        "the project must say what it is, not when or in which session or issue it was made, and point to "
        "its own docs rather than a DESIGN.md; rewrite these lines:\n" + "\n".join(found))

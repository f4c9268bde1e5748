"""MkDocs hook for msmem's manual (``mkdocs.yml``: ``hooks``).

The pages link to files outside ``docs/`` (model cards next to the weights, the changelog, example
configs), which read well on GitHub but are not part of the site. Before a page is rendered, every such
link to a file that exists becomes a link into the repository when ``repo_url`` is set, and plain text
naming the file otherwise. A link to a file that does not exist is left alone, so that ``mkdocs build
--strict`` fails on it as on any broken link.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path
from typing import Any

LINK = re.compile(r"(?<!!)\[(?P<text>[^\]]+)\]\((?P<target>[^)\s#]+)(?P<anchor>#[^)\s]*)?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)


def _outside_link(match: re.Match[str], page_dir: Path, docs_dir: Path, repo_root: Path, repo_url: str) -> str:
    target = match.group("target")
    if "://" in target or target.startswith(("mailto:", "/")):
        return match.group(0)
    path = Path(posixpath.normpath((page_dir / target).as_posix()))
    try:
        path.relative_to(docs_dir)
        return match.group(0)  # inside docs/: MkDocs checks it
    except ValueError:
        pass
    if not path.exists():
        return match.group(0)  # broken: leave it for --strict to report
    rel = path.relative_to(repo_root).as_posix()
    if repo_url:
        kind = "tree" if path.is_dir() else "blob"
        return f"[{match.group('text')}]({repo_url.rstrip('/')}/{kind}/main/{rel}{match.group('anchor') or ''})"
    text = match.group("text")
    return text if text.strip("`") == rel else f"{text} (`{rel}`)"


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any, **_: Any) -> str:
    docs_dir = Path(config["docs_dir"]).resolve()
    repo_root = docs_dir.parent
    page_dir = (docs_dir / page.file.src_path).parent
    repo_url = config.get("repo_url") or ""
    out, last = [], 0
    for fence in FENCE.finditer(markdown):  # leave code blocks as written
        out.append(LINK.sub(lambda m: _outside_link(m, page_dir, docs_dir, repo_root, repo_url),
                            markdown[last:fence.start()]))
        out.append(fence.group(0))
        last = fence.end()
    out.append(LINK.sub(lambda m: _outside_link(m, page_dir, docs_dir, repo_root, repo_url), markdown[last:]))
    return "".join(out)

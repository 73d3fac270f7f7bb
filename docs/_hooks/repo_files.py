"""MkDocs hook: the repository files the docs link to are published with the site.

Why: the pages link to example specs (``examples/*.toml``), measured results (``benchmarks/results/*.json``,
``experiments/*/*.md``) and the README, which live outside ``docs/``. On GitHub those relative links
work; on the site they would be dead, and ``mkdocs build --strict`` rightly fails on a dead link. So
every file outside ``docs/`` that a page links to (and, for Markdown, that it links to in turn) is
added to the build under ``repo/``, and each link is rewritten to where its target is on the site:
a docs page where it is, a repository file under ``repo/``. A link to a file that does not exist is
left as it is, and the strict build names it.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

LINK = re.compile(r"(\]\()([^)\s#]+)(#[^)\s]*)?(\))")  # [text](target#anchor)
PREFIX = "repo"


def _repo_path(src_uri: str) -> str:
    """Where the page of the site's ``src_uri`` lives in the repository."""
    return src_uri[len(PREFIX) + 1 :] if src_uri.startswith(f"{PREFIX}/") else f"docs/{src_uri}"


def _site_uri(repo_path: str) -> str:
    return repo_path[len("docs/") :] if repo_path.startswith("docs/") else f"{PREFIX}/{repo_path}"


def _target(page_repo_path: str, target: str, root: Path) -> str | None:
    """The repository file ``target`` (a link on the page at ``page_repo_path``) names, or None."""
    if "://" in target or target.startswith(("/", "mailto:")):
        return None
    path = posixpath.normpath(posixpath.join(posixpath.dirname(page_repo_path), target))
    return path if not path.startswith("..") and (root / path).is_file() else None


def on_files(files: Files, config) -> Files:
    root = Path(config["docs_dir"]).parent
    seen: set[str] = set()
    todo = [f"docs/{md.relative_to(root / 'docs').as_posix()}" for md in sorted((root / "docs").rglob("*.md")) if "_hooks" not in md.parts]
    while todo:  # the docs' Markdown, then the outside Markdown they link to, and so on
        page = todo.pop()
        for match in LINK.finditer((root / page).read_text(encoding="utf-8")):
            path = _target(page, match.group(2), root)
            if path is None or path.startswith("docs/") or path in seen:
                continue
            seen.add(path)
            if path.endswith(".md"):
                todo.append(path)
    for path in sorted(seen):
        files.append(File.generated(config, _site_uri(path), abs_src_path=str(root / path)))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    root = Path(config["docs_dir"]).parent
    here = page.file.src_uri
    where = _repo_path(here)

    def rewrite(match: re.Match) -> str:
        path = _target(where, match.group(2), root)
        if path is None:
            return match.group(0)
        link = posixpath.relpath(_site_uri(path), posixpath.dirname(here) or ".")
        return f"{match.group(1)}{link}{match.group(3) or ''}{match.group(4)}"

    return LINK.sub(rewrite, markdown)

"""The site's build steps beyond mkdocs' own (``hooks:`` in mkdocs.yml).

- The Markdown files that live outside ``docs/`` are pages of the site, read where they are (no copies):
  README.md is the home page, ARCHITECTURE.md and CONTRIBUTING.md pages of their own, and ``reports/``
  (the benchmarks' own write-ups, plots and data) is mirrored under ``reports/``.
- Links are written as the repository holds the files (README's ``docs/live.md``, ARCHITECTURE's
  ``model/online/bounds.py``): a link to a page or a report becomes the site's link to it, a link to a
  source file becomes its path in code type (the site does not carry the source).
- ``{{ presets }}`` is the table of what the config presets set, read from ``model/config.py``.
- Benchmark figures (``{{ FILE KEY }}``, ``{{ results FILE }}``) are read from ``reports/`` by
  ``bench.pages``, which lists each page's sources (command, machine, date) at its end; a report's own
  page (``reports/*.md``) opens with its command, machine and date.
"""

from __future__ import annotations

import posixpath
import re
import sys
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
INCLUDED = {"README.md": "index.md", "ARCHITECTURE.md": "architecture.md",
            "CONTRIBUTING.md": "contributing.md"}
"""Repository Markdown outside docs/ -> its page in the site."""
REPORTS = "reports"
LINK = re.compile(r'(?P<bang>!?)\[(?P<text>[^\]]*)\]\((?P<target>[^)\s]+)(?P<title>\s+"[^"]*")?\)')
FENCE = re.compile(r"^\s*(```|~~~)")
PRESETS = re.compile(r"\{\{\s*presets\s*\}\}")

_origin: dict[str, str] = {}
"""The site's page (src_uri) -> the file it was read from, relative to the repository."""
_figures = None


def on_config(config):
    global _figures
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))  # bench/ is not installed
    from bench.pages import Figures

    _figures = Figures(ROOT / REPORTS)
    return config


def _reports() -> list[str]:
    """Every file of reports/ but the benchmarks' caches, relative to the repository."""
    out = []
    for path in sorted((ROOT / REPORTS).rglob("*")):
        rel = path.relative_to(ROOT).as_posix()
        if path.is_file() and "cache" not in path.relative_to(ROOT / REPORTS).parts:
            out.append(rel)
    return out


def on_files(files: Files, config) -> Files:
    _origin.clear()
    for file in files:
        if file.src_uri.endswith(".md"):
            _origin[file.src_uri] = f"docs/{file.src_uri}"
    sources = dict(INCLUDED) | {rel: rel for rel in _reports()}
    for repo, site in sources.items():
        if files.get_file_from_path(site) is not None:
            raise PluginError(f"docs/{site} would hide {repo}: the page is read from {repo}")
        files.append(File.generated(config, site, abs_src_path=str(ROOT / repo)))
        if site.endswith(".md"):
            _origin[site] = repo
    return files


def _site_path(repo: str) -> str | None:
    """The site's file for a repository path, where the site has one."""
    if repo in INCLUDED:
        return INCLUDED[repo]
    if repo.startswith("docs/"):
        return repo.removeprefix("docs/")
    if repo.startswith(f"{REPORTS}/") and (ROOT / repo).is_file() and "cache" not in repo.split("/"):
        return repo
    return None


def rewrite_links(markdown: str, origin: str, page: str) -> str:
    """``markdown``, read from the repository file ``origin`` and shown as the site's ``page``, with its
    relative links pointing into the site (a source file's link: its path in code type)."""

    def one(match: re.Match) -> str:
        target = match["target"]
        if re.match(r"^([a-z][a-z0-9+.-]*:|#|/)", target, re.I):
            return match[0]
        path, _, fragment = target.partition("#")
        repo = posixpath.normpath(posixpath.join(posixpath.dirname(origin), path))
        site = _site_path(repo.rstrip("/"))
        if site is not None:
            new = posixpath.relpath(site, posixpath.dirname(page) or ".")
            new += f"#{fragment}" if fragment else ""
            return f"{match['bang']}[{match['text']}]({new}{match['title'] or ''})"
        if match["bang"]:
            raise PluginError(f"{origin}: the image {target} is not in docs/ or reports/")
        text = match["text"]
        if text.strip("`") == repo or text.strip("`") == path:
            return f"`{repo}`"
        return f"{text} (`{repo}`)"

    out, fenced = [], False
    for line in markdown.splitlines(keepends=True):
        if FENCE.match(line):
            fenced = not fenced
        out.append(line if fenced else LINK.sub(one, line))
    return "".join(out)


def presets_table() -> str:
    """Every config field some preset sets apart from the defaults: its value in each, and its meaning."""
    from edmcgs.model.config import PRESETS, field_docs

    configs = {name: make().to_dict() for name, make in PRESETS.items()}
    docs = field_docs()
    names = list(configs)
    rows = [f"| key | {' | '.join(f'`{n}`' for n in names)} | meaning |", "|---" * (len(names) + 2) + "|"]
    for key in configs[names[0]]:
        values = [configs[n][key] for n in names]
        if any(v != values[0] for v in values):
            shown = " | ".join(f"`{v:.6g}`" if isinstance(v, float) else f"`{v}`" for v in values)
            rows.append(f"| `{key}` | {shown} | {docs.get(key, '').replace('|', '/')} |")
    return "\n".join(rows)


def on_page_markdown(markdown: str, page, config, files) -> str:
    src = page.file.src_uri
    origin = _origin.get(src, f"docs/{src}")
    try:
        markdown = rewrite_links(markdown, origin, src)
        if origin.startswith(f"{REPORTS}/"):  # under the report's title: who wrote it, where, when
            title, _, body = markdown.partition("\n") if markdown.startswith("# ") else ("", "", markdown)
            note = _figures.provenance(origin.removeprefix(f"{REPORTS}/"))
            markdown = f"{title}\n\n{note}{body}" if title else note + body
        if PRESETS.search(markdown):
            markdown = PRESETS.sub(lambda _: presets_table(), markdown)
        return _figures.render(markdown)
    except ValueError as exc:  # InvalidInputError: a figure or link the page names is not there
        raise PluginError(f"{origin}: {exc}") from exc


__all__ = ["on_config", "on_files", "on_page_markdown", "presets_table", "rewrite_links"]

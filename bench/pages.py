"""Benchmark figures in the docs, read from ``reports/`` when the site is built, never copied by hand.

A docs page names a figure by its data file and key; the site shows the value, linked to the file's
provenance (the command, the machine, the date), which the page lists at its end:

    {{ FILE KEY [FORMAT] }}     one figure: FILE relative to reports/, KEY a dotted path into its JSON
    {{ results FILE }}          a table of every numeric result of FILE, with its targets where it has them

KEY steps into dicts by name and lists by index, or picks the list item whose fields match:
``rows[width=346,gaussians=8000].median_ms``. A key holding spaces or dots is quoted as a whole
(``"stages_ms.anchor: deform"``). FORMAT is a format spec (``.2f``, ``,d``), optionally scaled:
``.1f/60`` (seconds as minutes), ``.0f*1000``. Placeholders in code (fenced or `spans`) are left alone.

Provenance: a file's own ``run`` block (``{"command", "machine", "date"}``: ``bench.results.write_json``
stamps every benchmark's JSON with it), else its entry in ``reports/sources.toml``, which holds the
first 12 hex digits of the file's SHA-256: a file changed since its entry was written has no provenance
until it is given one, and a page that shows it does not build. An entry ``same_as = "OTHER"`` gives a
file the provenance of the data file the same command wrote (``summary.md`` that of ``report.json``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import shlex
import tomllib
from dataclasses import dataclass
from pathlib import Path

from bench.results import meets, numeric
from edmcgs.errors import InvalidInputError

PLACEHOLDER = re.compile(r"\{\{\s*(.+?)\s*\}\}")
FENCE = re.compile(r"^\s*(```|~~~)")
CODE_SPAN = re.compile(r"(`+)(?:.+?)\1")
SELECT = re.compile(r"^(?P<name>[^\[\]]*)\[(?P<where>[^\[\]]+)\]$")
SCALE = re.compile(r"^(?P<spec>.*?)(?P<op>[/*])(?P<by>[0-9.e+-]+)$")
SOURCES = "sources.toml"


@dataclass(frozen=True)
class Source:
    """Where a data file's figures come from."""

    path: str
    """The file, relative to ``reports/``."""
    command: str
    """The command (or commands, one a line) that wrote it."""
    machine: str
    date: str
    note: str = ""

    @property
    def anchor(self) -> str:
        return "src-" + re.sub(r"[^a-z0-9]+", "-", self.path.lower()).strip("-")


def digest(path: Path) -> str:
    """The first 12 hex digits of the file's SHA-256: what a ``sources.toml`` entry is pinned to."""
    return hashlib.sha256(path.read_bytes()).hexdigest()[:12]


class Figures:
    """The figures of the data files under one ``reports/`` folder, and their provenance."""

    def __init__(self, reports: Path):
        self.reports = Path(reports)
        listed = self.reports / SOURCES
        self._listed = tomllib.loads(listed.read_text()) if listed.exists() else {}
        self._data: dict[str, object] = {}

    def _path(self, name: str) -> Path:
        path = self.reports / name
        if not path.is_file():
            raise InvalidInputError(f"figures: reports/{name} does not exist")
        return path

    def data(self, name: str):
        """The parsed JSON of ``reports/NAME``."""
        if name not in self._data:
            try:
                self._data[name] = json.loads(self._path(name).read_text())
            except json.JSONDecodeError as exc:
                raise InvalidInputError(f"figures: reports/{name} is not JSON: {exc}") from exc
        return self._data[name]

    def source(self, name: str) -> Source:
        """The provenance of ``reports/NAME``: its ``run`` block, else its pinned ``sources.toml`` entry."""
        path = self._path(name)
        if name.endswith(".json"):
            run = self.data(name).get("run") if isinstance(self.data(name), dict) else None
            if run is not None:
                return _source(name, run, "its run block")
        entry = self._listed.get(name)
        if entry is not None and "same_as" in entry:  # written together with a data file by one command
            return dataclasses.replace(self.source(entry["same_as"]), path=name)
        if entry is None:
            raise InvalidInputError(f"figures: reports/{name} states no command, machine and date: give it a "
                                    f"'run' block or an entry in reports/{SOURCES}")
        if entry.get("sha256") != digest(path):
            raise InvalidInputError(f"figures: reports/{name} changed since its reports/{SOURCES} entry "
                                    f"(sha256 {entry.get('sha256')}, now {digest(path)}): state its command, "
                                    "machine and date again")
        return _source(name, entry, f"reports/{SOURCES}")

    def value(self, name: str, key: str):
        """The value at the dotted ``key`` of ``reports/NAME``."""
        return lookup(self.data(name), key, name)

    def provenance(self, name: str) -> str:
        """A note for ``reports/NAME``'s own page: the command, the machine and the date that wrote it."""
        source = self.source(name)
        command = "\n".join("    " + line for line in source.command.strip().splitlines())
        return (f'!!! info "Written {source.date} on {source.machine}"\n\n'
                + (f"    {source.note}\n\n" if source.note else "")
                + f"    ```bash\n{command}\n    ```\n\n")

    def render(self, markdown: str) -> str:
        """``markdown`` with its placeholders replaced, and the sources of its figures listed at the end."""
        used: dict[str, Source] = {}
        out, fenced = [], False
        for line in markdown.splitlines(keepends=True):
            if FENCE.match(line):
                fenced = not fenced
            out.append(line if fenced else _outside_code(line, lambda m: self._expand(m.group(1), used)))
        text = "".join(out)
        return text + self._sources(used) if used else text

    def _expand(self, body: str, used: dict[str, Source]) -> str:
        try:
            words = shlex.split(body)
        except ValueError as exc:
            raise InvalidInputError(f"figures: {{{{ {body} }}}}: {exc}") from exc
        if words[:1] == ["results"] and len(words) == 2:
            return self._results(words[1], used)
        if len(words) not in (2, 3):
            raise InvalidInputError(f"figures: {{{{ {body} }}}}: expected FILE KEY [FORMAT] or results FILE")
        name, key, spec = words[0], words[1], words[2] if len(words) == 3 else ""
        source = used.setdefault(name, self.source(name))
        shown = _format(self.value(name, key), spec, f"reports/{name} {key}")
        return _link(shown, source)

    def _results(self, name: str, used: dict[str, Source]) -> str:
        source = used.setdefault(name, self.source(name))
        data = self.data(name)
        results = data.get("results", data) if isinstance(data, dict) else None
        if not isinstance(results, dict):
            raise InvalidInputError(f"figures: reports/{name} has no results to tabulate")
        targets = data.get("targets", {})
        rows = ["| result | value | target |", "|---|---:|---|"]
        for key, value in numeric(results):
            target = targets.get(key)
            mark = ""
            if target is not None:
                mark = f"{target[0]} {target[1]:g}: {'met' if meets(value, target) else '**missed**'}"
            rows.append(f"| `{key}` | {_link(_format(value, '', name), source)} | {mark} |")
        return "\n".join(rows)

    @staticmethod
    def _sources(used: dict[str, Source]) -> str:
        parts = ["\n\n## Where these figures come from { #sources }\n\nEach figure above links here: "
                 "the data file it was read from when this page was built, the command that wrote it, "
                 "the machine and the date.\n"]
        for source in sorted(used.values(), key=lambda s: s.path):
            parts.append(f"\n### `reports/{source.path}` {{ #{source.anchor} }}\n\n"
                         f"{source.date}, on {source.machine}."
                         + (f" {source.note}" if source.note else "")
                         + f"\n\n```bash\n{source.command.strip()}\n```\n")
        return "".join(parts)


def _outside_code(line: str, expand) -> str:
    """``line`` with its placeholders expanded, but not those inside `code spans`; a ``{{`` left open
    (a placeholder broken over two lines) is an error, not text on the page."""
    out, at = [], 0

    def fill(text: str) -> str:
        done = PLACEHOLDER.sub(expand, text)
        if "{{" in PLACEHOLDER.sub("", text):
            raise InvalidInputError(f"figures: a placeholder opens and closes on one line: {line.strip()!r}")
        return done

    for span in CODE_SPAN.finditer(line):
        out += [fill(line[at:span.start()]), span[0]]
        at = span.end()
    return "".join([*out, fill(line[at:])])


def _source(name: str, fields: dict, where: str) -> Source:
    missing = [k for k in ("command", "machine", "date") if not str(fields.get(k, "")).strip()]
    if missing:
        raise InvalidInputError(f"figures: reports/{name}: {where} lacks {', '.join(missing)}")
    return Source(name, str(fields["command"]), str(fields["machine"]), str(fields["date"]),
                  str(fields.get("note", "")))


def lookup(data, key: str, name: str = "?"):
    """The value at the dotted ``key`` of ``data`` (a JSON document; ``name``: its file, for errors), as
    the pages' placeholders read it: ``a.b``, ``runs.0``, ``runs[side=this,round=1].value``."""
    for part in _split(key):
        data = _step(data, part, name, key)
    return data


def _split(key: str) -> list[str]:
    """A dotted key's steps; dots inside a ``[...]`` selector do not split."""
    parts, depth, word = [], 0, ""
    for ch in key:
        depth += (ch == "[") - (ch == "]")
        if ch == "." and depth == 0:
            parts.append(word)
            word = ""
        else:
            word += ch
    parts.append(word)
    return parts


def _step(node, part: str, name: str, key: str):
    where = f"reports/{name}: key {key!r}"
    select = SELECT.match(part)
    if select:
        if select["name"]:
            node = _step(node, select["name"], name, key)
        if not isinstance(node, list):
            raise InvalidInputError(f"figures: {where}: [{select['where']}] selects from a list")
        want = dict(item.split("=", 1) for item in select["where"].split(","))
        hits = [item for item in node if isinstance(item, dict)
                and all(k in item and _equal(item[k], v) for k, v in want.items())]
        if len(hits) != 1:
            raise InvalidInputError(f"figures: {where}: [{select['where']}] matches {len(hits)} items, not 1")
        return hits[0]
    if isinstance(node, list):
        try:
            return node[int(part)]
        except (ValueError, IndexError) as exc:
            raise InvalidInputError(f"figures: {where}: no item {part!r}") from exc
    if not isinstance(node, dict) or part not in node:
        raise InvalidInputError(f"figures: {where}: no {part!r}")
    return node[part]


def _equal(value, text: str) -> bool:
    if isinstance(value, int | float) and not isinstance(value, bool):
        try:
            return float(value) == float(text)
        except ValueError:
            return False
    return str(value) == text


def _format(value, spec: str, what: str) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise InvalidInputError(f"figures: {what} is {type(value).__name__}, not a figure")
    scale = SCALE.match(spec)
    if scale:
        factor = float(scale["by"])
        value = value / factor if scale["op"] == "/" else value * factor
        spec = scale["spec"]
    try:
        return format(value, spec)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"figures: {what}: format {spec!r}: {exc}") from exc


def _link(shown: str, source: Source) -> str:
    # a title ends at a double quote, a table cell at a bar, and a link at an unbalanced parenthesis
    title = source.command.strip().splitlines()[0].replace('"', "'").replace("|", "/")
    title = title.replace("(", "&#40;").replace(")", "&#41;")
    return f'[{shown}](#{source.anchor} "{title}")'


__all__ = ["Figures", "Source", "digest"]

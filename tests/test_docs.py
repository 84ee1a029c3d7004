"""The front door and the docs site: README.md short and true to the Makefile, the benchmark figures read
from reports/ with their provenance (bench/pages.py), repository links made the site's (docs/hooks.py),
and the whole site built by mkdocs --strict without a request to anywhere."""

import importlib.util
import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from bench.pages import Figures, digest
from bench.results import write_json
from edmcgs.errors import InvalidInputError

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ------------------------------------------------------------------------------- the README

def test_readme_is_short():
    assert len(README.splitlines()) <= 150


def test_readme_commands_are_the_makefiles():
    targets = set(re.findall(r"^([a-z][a-z-]*):", (ROOT / "Makefile").read_text(), re.M))
    commands = re.findall(r"^make ([a-z-]+)\b", README, re.M)
    assert commands[:2] == ["serve", "test"]  # the two commands, first
    assert set(commands) <= targets
    assert re.search(r"^make test$", (ROOT / ".ci" / "run").read_text(), re.M)  # CI runs the README's


def test_readme_names_the_port():
    assert "--port" in README and "EDMCGS_PORT" in README


# ------------------------------------------------------------------------------- figures

def _reports(tmp_path: Path) -> Path:
    reports = tmp_path / "reports"
    write_json(reports / "bench" / "serve.json",
               {"render_p50_ms": 7.7498, "rows": [{"width": 173, "ms": 1.5}, {"width": 346, "ms": 4.65}],
                "results": {"slots_s": 5.14, "renders": 0}, "targets": {"slots_s": ["<=", 5.0]}})
    return reports


def test_a_figure_links_to_its_command_machine_and_date(tmp_path):
    figures = Figures(_reports(tmp_path))
    page = figures.render("p50 {{ bench/serve.json render_p50_ms .2f }} ms, "
                          "{{ bench/serve.json rows[width=346].ms }} ms\n")
    assert page.startswith('p50 [7.75](#src-bench-serve-json "python ')
    assert "[4.65](#src-bench-serve-json" in page
    sources = page.split("{ #sources }")[1]
    run = json.loads((tmp_path / "reports" / "bench" / "serve.json").read_text())["run"]
    assert "{ #src-bench-serve-json }" in sources and run["machine"] in sources and run["date"] in sources
    assert run["command"] in sources and run["command"].startswith("python ")


def test_write_json_keeps_a_run_block_it_is_given(tmp_path):
    write_json(tmp_path / "x.json", {"a": 1, "run": {"command": "c", "machine": "m", "date": "d"}})
    run = json.loads((tmp_path / "x.json").read_text())["run"]
    assert run == {"command": "c", "machine": "m", "date": "d"}


def test_formats_scale_and_fenced_code(tmp_path):
    figures = Figures(_reports(tmp_path))
    assert figures.render("{{ bench/serve.json render_p50_ms .1f*1000 }}").startswith("[7749.8](")
    fenced = "```text\n{{ bench/serve.json nothing }}\n```\nand `{{ bench/NAME.json KEY }}` too\n"
    assert figures.render(fenced) == fenced  # documentation of the syntax stays as written


def test_results_table_marks_targets(tmp_path):
    page = Figures(_reports(tmp_path)).render("{{ results bench/serve.json }}")
    link = r"\[5\.14\]\(#src-bench-serve-json .*\)"
    assert re.search(rf"\| `slots_s` \| {link} \| <= 5: \*\*missed\*\* \|", page)
    assert "| `renders` |" in page


@pytest.mark.parametrize(("body", "says"), [
    ("bench/serve.json render_p99_ms", "no 'render_p99_ms'"),
    ("bench/serve.json rows[width=999].ms", "matches 0 items"),
    ("bench/none.json x", "reports/bench/none.json does not exist"),
    ("bench/serve.json rows", "not a figure"),
    ("bench/serve.json", "expected FILE KEY"),
])
def test_a_wrong_reference_is_named(tmp_path, body, says):
    with pytest.raises(InvalidInputError, match=re.escape(says)):
        Figures(_reports(tmp_path)).render("{{ " + body + " }}")


def test_a_placeholder_broken_over_two_lines_is_refused(tmp_path):
    with pytest.raises(InvalidInputError, match="opens and closes on one line"):
        Figures(_reports(tmp_path)).render("p50 {{ bench/serve.json\nrender_p50_ms }} ms")


def test_a_file_without_provenance_is_refused(tmp_path):
    reports = tmp_path / "reports"
    reports.mkdir()
    (reports / "old.json").write_text('{"x": 1.5}')
    with pytest.raises(InvalidInputError, match=r"reports/old\.json states no command, machine and date"):
        Figures(reports).render("{{ old.json x }}")


def test_sources_toml_holds_while_the_file_is_unchanged(tmp_path):
    reports = tmp_path / "reports"
    reports.mkdir()
    (reports / "old.json").write_text('{"x": 1.5}')
    (reports / "old.md").write_text("# a report\n")
    (reports / "sources.toml").write_text(
        f'["old.json"]\ncommand = "python -m bench.old"\nmachine = "m"\ndate = "2026-11-23"\n'
        f'sha256 = "{digest(reports / "old.json")}"\n["old.md"]\nsame_as = "old.json"\n')
    assert "python -m bench.old" in Figures(reports).render("{{ old.json x }}")
    assert "python -m bench.old" in Figures(reports).provenance("old.md")
    (reports / "old.json").write_text('{"x": 2.5}')  # written again: the entry no longer describes it
    with pytest.raises(InvalidInputError,
                       match=r"reports/old\.json changed since its reports/sources\.toml entry"):
        Figures(reports).render("{{ old.json x }}")


def test_every_report_of_the_repository_states_its_provenance():
    figures = Figures(ROOT / "reports")
    for name in tomllib.loads((ROOT / "reports" / "sources.toml").read_text()):
        assert figures.source(name).date


# ------------------------------------------------------------------------------- links

@pytest.mark.parametrize(("text", "origin", "page", "want"), [
    ("[live](docs/live.md#cold-start)", "README.md", "index.md", "[live](live.md#cold-start)"),
    ("![v](docs/viewer_events.png)", "README.md", "index.md", "![v](viewer_events.png)"),
    ("[Architecture](ARCHITECTURE.md)", "README.md", "index.md", "[Architecture](architecture.md)"),
    ("[model/online/bounds.py](model/online/bounds.py)", "ARCHITECTURE.md", "architecture.md",
     "`model/online/bounds.py`"),
    ("[the bounds](../model/event_bounds.py)", "reports/online.md", "reports/online.md",
     "the bounds (`model/event_bounds.py`)"),
    ("![plot](online_jj8.png)", "reports/online.md", "reports/online.md", "![plot](online_jj8.png)"),
    ("[plot](../../reports/online_jj8.png)", "docs/benchmarks/live.md", "benchmarks/live.md",
     "[plot](../reports/online_jj8.png)"),
    ("[web](https://example.org/x.md) [here](#top)", "README.md", "index.md",
     "[web](https://example.org/x.md) [here](#top)"),
])
def test_repository_links_become_the_sites(text, origin, page, want):
    assert _hooks().rewrite_links(text, origin, page) == want


def test_presets_table_lists_what_the_presets_set():
    table = _hooks().presets_table()
    row = r"^\| `{}` \| `{}` \| `{}` \| `{}` \| `{}` \| {}"  # paper, demo, real, moving, meaning
    assert re.search(row.format("bg_layer", False, False, True, True, "A distant background"), table, re.M)
    assert re.search(row.format("static_set", False, False, False, True, "A static set"), table, re.M)
    assert "| `iterations` | `30000` | `1500` | `1500` | `1500` |" in table
    assert "`sh_degree`" not in table  # the same in every preset


# ------------------------------------------------------------------------------- the site

@pytest.mark.slow
def test_site_builds_strict_and_offline(tmp_path):
    """The whole site, as make docs builds it; every resource a page loads is the site's own."""
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                          cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    pages = list(site.rglob("*.html"))
    assert {"index.html", "architecture.html", "benchmarks/live.html", "reports/online.html"} <= {
        p.relative_to(site).as_posix() for p in pages}
    loads = re.compile(r"<(?:script|link|img|iframe|source)\b[^>]*\b(?:src|href)=\"((?:https?:)?//[^\"]*)\"")
    for page in pages:
        assert loads.findall(page.read_text()) == [], page
    for css in site.rglob("*.css"):
        assert not re.search(r"url\((['\"]?)(https?:)?//", css.read_text()), css
    home = (site / "index.html").read_text()
    assert 'href="getting-started.html"' in home and 'src="viewer_events.png"' in home
    assert 'href="#src-traffic-json"' in (site / "benchmarks" / "real.html").read_text()

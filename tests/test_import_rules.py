"""Every import rule of CONTRIBUTING.md, checked over the source (imports inside functions included)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"edmcgs": "edmcgs", "sensor": "edmcgs.sensor", "model": "edmcgs.model", "synth": "edmcgs.synth",
           "server": "edmcgs.server", "clients": "edmcgs.clients", "bench": "bench", "harness": "harness",
           "tests": "tests"}
BASE = ("edmcgs.errors", "edmcgs.atomic", "edmcgs.geometry", "edmcgs.luminance",
        "edmcgs.filekind")
"""Shared by every layer: the error tree, atomic file output, the camera / pose / quaternion maths and
what an event pixel sees of an image (luminance), and what a file is by its first bytes."""
PROTOCOL = "edmcgs.protocol"
APPLICATION = ("edmcgs.pipeline", "edmcgs.options", "edmcgs.poses", "edmcgs.cli", "edmcgs.train_cli",
               "edmcgs.eval_cli", "edmcgs.record_cli", "edmcgs.poses_cli", "edmcgs.export_ply_cli",
               "edmcgs.warmup_cli")
CLI_MODULES = ("edmcgs.cli", "edmcgs.train_cli", "edmcgs.eval_cli", "edmcgs.record_cli", "edmcgs.poses_cli",
               "edmcgs.export_ply_cli", "edmcgs.warmup_cli", "edmcgs.server.cli")
MODEL_ROOMS = ("render", "motion", "train", "eval", "online")
MODEL_CORE = ("edmcgs.model.dynamic", "edmcgs.model.motion", "edmcgs.model.render", "edmcgs.model.config",
              "edmcgs.model.data", "edmcgs.model.checkpoint")
"""The inference core and what it is built from: it never imports what trains, scores or extends it."""
RAY_ROOMS = ("edmcgs.server.ray_serve", "edmcgs.fanout", "edmcgs.data_parallel")
"""The only installed modules that import ``ray`` (the optional extra): the Serve application and the
training fan-out and data-parallel training."""
BENCH_ONLY = ("matplotlib",)
"""Third-party packages of the ``bench`` extra, which only ``bench/`` imports."""


def _modules():
    out = {}
    for folder, package in FOLDERS.items():
        for path in (ROOT / folder).rglob("*.py"):
            if ".venv" in path.parts:
                continue
            rel = path.relative_to(ROOT / folder).with_suffix("").parts
            if folder == "edmcgs" and rel and rel[0] in {"model", "sensor", "synth", "server", "clients"}:
                continue  # a symlinked or stray copy; the mapped folder is the source
            name = ".".join((package, *rel)).removesuffix(".__init__")
            out[name] = path
    return out


MODULES = _modules()


def _imports(path: Path) -> set[str]:
    """The project modules a file imports (``from pkg import module`` counts as importing the module)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            subs = {f"{node.module}.{a.name}" for a in node.names} & MODULES.keys()
            names.update(subs or {node.module})
    return {n for n in names if n.split(".")[0] in ("edmcgs", "bench", "harness", "tests")}


def _within(name: str, *prefixes: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _violations(importer: str, allowed: tuple[str, ...]) -> list[str]:
    """``importer IMPORTS imported`` for each project import of the modules under ``importer`` outside
    ``allowed`` (the package root ``edmcgs`` itself holds nothing and is always allowed)."""
    bad = []
    for name, path in MODULES.items():
        if _within(name, importer):
            bad += [f"{name} imports {i}" for i in sorted(_imports(path))
                    if i != "edmcgs" and not _within(i, *allowed)]
    return sorted(bad)


def test_the_scan_sees_the_project():
    assert {"edmcgs.model.dynamic", "edmcgs.sensor.buffer.ring", "edmcgs.protocol"} <= MODULES.keys()
    assert "tests.support" in MODULES
    assert "edmcgs.model.render.rasterize" in _imports(MODULES["edmcgs.model.dynamic"])


def test_the_shared_base_imports_nothing_above_it():
    assert _violations("edmcgs.errors", ()) == []
    assert _violations("edmcgs.atomic", ("edmcgs.errors",)) == []
    assert _violations("edmcgs.geometry", ("edmcgs.errors",)) == []
    assert _violations("edmcgs.luminance", ()) == []
    assert _violations("edmcgs.filekind", ("edmcgs.errors",)) == []
    assert _violations(PROTOCOL, ()) == [], "the wire protocol imports nothing of the project"


def test_sensor_and_model_import_neither_each_other_nor_anything_above():
    assert _violations("edmcgs.sensor", ("edmcgs.sensor", *BASE)) == []
    assert _violations("edmcgs.model", ("edmcgs.model", *BASE)) == []


def test_the_renderer_imports_no_other_room_of_the_model():
    assert _violations("edmcgs.model.render", ("edmcgs.model.render", *BASE)) == []


@pytest.mark.parametrize("room", MODEL_ROOMS)
def test_model_rooms_import_no_application_or_server(room):
    assert _violations(f"edmcgs.model.{room}", ("edmcgs.model", *BASE)) == []


def test_the_model_core_imports_no_training_evaluation_or_online_room():
    above = ("edmcgs.model.train", "edmcgs.model.eval", "edmcgs.model.online")
    bad = [v for core in MODEL_CORE for v in _violations(core, ("edmcgs.model", *BASE))
           if _within(v.split(" imports ")[1], *above)]
    assert bad == []


def test_evaluation_never_imports_training():
    assert [v for v in _violations("edmcgs.model.eval", ("edmcgs.model", *BASE))
            if _within(v.split(" imports ")[1], "edmcgs.model.train")] == []


def _cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the directed graph ``edges`` (as its nodes in order), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node):
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        state[node] = 2
        path.pop()
        return None

    for node in sorted(edges):
        if node not in state and (found := visit(node)):
            return found
    return None


def _sibling_edges(package: str) -> dict[str, set[str]]:
    """Imports between the direct children (modules and sub-packages) of ``package``."""
    depth = package.count(".") + 1

    def child(name):
        parts = name.split(".")
        return ".".join(parts[:depth + 1]) if _within(name, package) and len(parts) > depth else None

    edges: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        a = child(name)
        if a is None:
            continue
        for i in _imports(path):
            b = child(i)
            if b is not None and b != a:
                edges.setdefault(a, set()).add(b)
    return edges


PACKAGES = sorted({n for n, p in MODULES.items() if p.name == "__init__.py"})


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycle_between_the_rooms_of_a_package(package):
    assert _cycle(_sibling_edges(package)) is None


def test_a_cycle_is_found():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}}) is None


def test_synth_imports_sensor_and_model_only():
    assert _violations("edmcgs.synth", ("edmcgs.synth", "edmcgs.sensor", "edmcgs.model", *BASE)) == []


def test_server_imports_sensor_model_protocol_and_the_pipeline():
    allowed = ("edmcgs.server", "edmcgs.sensor", "edmcgs.model", PROTOCOL, "edmcgs.pipeline", *BASE)
    assert _violations("edmcgs.server", allowed) == []


def test_clients_import_only_the_wire_protocol():
    assert _violations("edmcgs.clients", ("edmcgs.clients", PROTOCOL, "edmcgs.errors", "edmcgs.atomic")) == []


def test_nothing_installed_imports_bench_or_tests():
    assert _violations("edmcgs", ("edmcgs",)) == []


def test_no_module_imports_a_cli_module():
    bad = []
    for name, path in MODULES.items():
        if name == "edmcgs.cli" or name.startswith("tests."):
            continue
        bad += [f"{name} imports {i}" for i in _imports(path) if i in CLI_MODULES]
    assert bad == []


def test_bench_imports_the_harness_never_tests():
    assert _violations("bench", ("bench", "edmcgs", "harness")) == []


def test_the_harness_imports_only_the_package():
    """What tests, benchmarks and scripts share imports none of them."""
    assert _violations("harness", ("harness", "edmcgs")) == []


def test_test_support_imports_no_test_module_and_no_bench():
    assert _violations("tests.support", ("tests.support", "harness", "edmcgs")) == []


def test_tests_import_support_never_each_other():
    bad = []
    for name, path in MODULES.items():
        if not name.startswith("tests.") or name.startswith("tests.support"):
            continue
        bad += [f"{name} imports {i}" for i in _imports(path)
                if i.startswith("tests.") and not _within(i, "tests.support")]
    assert bad == []


def _top_level_imports(path: Path) -> set[str]:
    """Every top-level package a file imports (third-party ones too)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_structure_from_motion_imports_only_the_base_and_alone_imports_pycolmap():
    """``edmcgs.poses`` (and ``edmcgs.inertial``, the IMU's refinement of its poses) work on plain arrays
    (the pipeline hands them a recording's frames and IMU samples), and pycolmap is imported inside its
    functions only, so no command's ``--help`` waits for it."""
    assert _violations("edmcgs.poses", (*BASE, "edmcgs.inertial")) == []
    assert _violations("edmcgs.inertial", BASE) == []
    bad = [name for name, path in MODULES.items()
           if _within(name, "edmcgs") and name != "edmcgs.poses" and "pycolmap" in _top_level_imports(path)]
    assert bad == []
    module = ast.parse(MODULES["edmcgs.poses"].read_text())
    top = {a.name.split(".")[0] for node in module.body if isinstance(node, ast.Import) for a in node.names}
    assert "pycolmap" not in top


def test_only_the_ray_rooms_import_ray():
    bad = [name for name, path in MODULES.items()
           if _within(name, "edmcgs") and not _within(name, *RAY_ROOMS) and "ray" in _top_level_imports(path)]
    assert bad == []


def test_nothing_installed_imports_a_bench_only_package():
    """matplotlib is the ``bench`` extra's: a plain install has none."""
    bad = [name for name, path in MODULES.items()
           if _within(name, "edmcgs") and _top_level_imports(path) & set(BENCH_ONLY)]
    assert bad == []


def test_the_serve_application_is_reached_only_by_its_command():
    """The default server never loads Ray: only ``edmcgs-serve --ray`` (a command) imports the package."""
    bad = [f"{name} imports {i}" for name, path in MODULES.items()
           if _within(name, "edmcgs") and not _within(name, "edmcgs.server.ray_serve", "edmcgs.server.cli")
           for i in _imports(path) if _within(i, "edmcgs.server.ray_serve")]
    assert bad == []


def test_a_violation_is_reported():
    assert "edmcgs.sensor.buffer.ring imports edmcgs.sensor.events" in _violations("edmcgs.sensor",
                                                                                  ("edmcgs.errors",))

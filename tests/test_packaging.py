"""The distribution ships every subpackage and maps the code folders under ``edmcgs``."""

import importlib
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"edmcgs": "edmcgs", "sensor": "edmcgs.sensor", "model": "edmcgs.model",
           "synth": "edmcgs.synth", "server": "edmcgs.server", "clients": "edmcgs.clients"}


def _config():
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_subpackage_is_listed():
    listed = set(_config()["packages"])
    on_disk = set()
    for folder, name in FOLDERS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            on_disk.add(".".join((name, *rel)))
    assert on_disk - listed == set(), "add these to [tool.setuptools] packages in pyproject.toml"


def test_no_top_level_model_or_server_module():
    mapping = _config()["package-dir"]
    assert all(name.startswith("edmcgs") for name in mapping)
    for name in FOLDERS.values():
        assert importlib.import_module(name).__name__ == name


def test_cli_rejects_unknown_command(capsys):
    import pytest

    from edmcgs.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_package_data_lies_in_listed_packages():
    """Each package-data pattern names files in its own package's folder: a data folder inside another
    package is a package of its own to setuptools, which warns at every install unless it is listed."""
    config = _config()
    for package, patterns in config["package-data"].items():
        assert package in config["packages"], f"{package} has package data but is not listed"
        assert all("/" not in p for p in patterns), f"{package}: list the data folder as its own package"


def test_bench_only_dependencies_are_an_extra():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    runtime = {d.split(">")[0].split("=")[0].split("[")[0].strip() for d in project["dependencies"]}
    assert "matplotlib" not in runtime
    assert any(d.startswith("matplotlib") for d in project["optional-dependencies"]["bench"])

"""bench.ab: the previous release imported from its own files, the sides alternated, the ratio of medians."""

import json
import subprocess
import sys

from bench import ab

WRITE = "import sys, json, edmcgs.model; json.dump({'at': {'path': edmcgs.model.__file__}, 'v': 2.0}, " \
        "open(sys.argv[sys.argv.index('--json') + 1], 'w'))"


def test_the_previous_release_imports_from_its_archive_and_the_sides_alternate(tmp_path, capsys):
    tree = ab.previous_tree("HEAD", tmp_path / "cache")
    assert ab.previous_tree("HEAD", tmp_path / "cache") == tree  # made once
    code = "import edmcgs.model.train.row_adam as m; print(m.__file__)"
    found = subprocess.run([sys.executable, "-c", code],
                           env={"PYTHONPATH": str(tree), "PYTHONSAFEPATH": "1"}, capture_output=True,
                           text=True, check=True).stdout.strip()
    assert found.startswith(str(tmp_path / "cache")) and found.endswith("model/train/row_adam.py")
    out = tmp_path / "ab.json"
    assert ab.main(["--previous", "HEAD", "--rounds", "2", "--key", "v", "--json", str(out),
                    "--cache", str(tmp_path / "cache"), "--", "-c", WRITE]) == 0
    result = json.loads(out.read_text())
    assert [(r["side"], r["round"]) for r in result["runs"]] == \
        [("previous", 1), ("this", 1), ("this", 2), ("previous", 2)]
    assert result["ratio"] == 1.0 and result["run"]["command"]
    seen = {r["side"]: json.loads((tmp_path / r["json"]).read_text())["at"]["path"] for r in result["runs"]}
    assert seen["previous"].startswith(str(tmp_path / "cache")) and not seen["this"].startswith(str(tmp_path))

"""A bench run against the previous release, alternately, in one session: the ratio a speed is quoted as.

    .venv/bin/python -m bench.ab --previous REV [--rounds 2] --key timed.median_ms --json OUT
        -- -m bench.train_step --recording REC --config real --timed 200 --steps 5

Runs the command after ``--`` with this Python, ``--json PATH`` appended, ``--rounds`` times for each
side: this checkout, and the release ``REV`` (``git archive`` of it, its ``edmcgs`` packages put ahead
of this checkout's on ``PYTHONPATH``, the working directory off it; the bench code and every dependency
stay this checkout's, so both sides are measured alike). The sides alternate, and swap which goes first
each round (previous first in round 1). Writes each run's ``--key`` (a dotted path into its JSON) and
JSON, the median per side and ``ratio`` (this over previous) to ``--json``.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import tarfile
import tomllib
from pathlib import Path

import numpy as np

from bench.pages import lookup
from bench.results import write_json

ROOT = Path(__file__).resolve().parents[1]


def previous_tree(rev: str, cache: Path) -> Path:
    """A folder to put on ``PYTHONPATH`` that imports ``edmcgs`` as release ``rev`` has it (made once)."""
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", f"{rev}^{{commit}}"],
                            check=True, capture_output=True, text=True).stdout.strip()
    tree = cache / commit[:12]
    if (tree / "path" / "edmcgs").exists():
        return tree / "path"
    source = tree / "source"
    source.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit], check=True, capture_output=True)
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(source, filter="data")
    package_dir = tomllib.loads((source / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    # The layout maps edmcgs.model to model/ and so on: edmcgs/ made of links to edmcgs/'s files and to
    # those folders, under the names their packages import by.
    staged = tree / "staging" / "edmcgs"
    staged.mkdir(parents=True, exist_ok=True)
    for entry in (source / package_dir["edmcgs"]).iterdir():
        (staged / entry.name).symlink_to(entry)
    for package, folder in package_dir.items():
        if package != "edmcgs":
            (staged / package.split(".", 1)[1]).symlink_to(source / folder)
    (tree / "staging").rename(tree / "path")  # complete, or not there
    return tree / "path"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, command = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    p = argparse.ArgumentParser(prog="python -m bench.ab", description=__doc__.split("\n\n")[0])
    p.add_argument("--previous", required=True, help="the release to compare with (a git revision)")
    p.add_argument("--rounds", type=int, default=2, help="runs per side (2)")
    p.add_argument("--key", required=True, help="the figure compared: a dotted path into the command's JSON "
                   "(as the docs' placeholders read it)")
    p.add_argument("--json", type=Path, required=True, help="where the runs and the ratio go")
    p.add_argument("--cache", type=Path, default=ROOT / "reports" / "cache" / "ab",
                   help="the previous releases' files")
    args = p.parse_args(ours)
    if not command:
        p.error("the command to run goes after --")
    if args.rounds < 1:
        p.error("--rounds must be >= 1")
    previous = previous_tree(args.previous, args.cache)
    runs = []
    for round_ in range(1, args.rounds + 1):
        for side in (("previous", "this") if round_ % 2 else ("this", "previous")):
            out = args.json.with_name(f"{args.json.stem}_{side}_{round_}.json")
            # No working directory on sys.path (PYTHONSAFEPATH): this checkout's edmcgs/ would shadow
            # the previous one; the bench code comes from ROOT on both sides.
            env = dict(os.environ, PYTHONSAFEPATH="1")
            path = [str(previous)] if side == "previous" else []
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [*path, str(ROOT), env.get("PYTHONPATH")]))
            print(f"round {round_}, {side}: {' '.join(command)}", file=sys.stderr, flush=True)
            subprocess.run([sys.executable, *command, "--json", str(out)], check=True, env=env)
            value = float(lookup(json.loads(out.read_text()), args.key, out.name))
            runs.append({"side": side, "round": round_, "value": value, "json": out.name})
            print(f"round {round_}, {side}: {args.key} = {value:.4g}", file=sys.stderr, flush=True)
    medians = {side: float(np.median([r["value"] for r in runs if r["side"] == side]))
               for side in ("previous", "this")}
    result = {"previous": args.previous, "key": args.key, "command": command, "runs": runs,
              "median": medians, "ratio": medians["this"] / medians["previous"]}
    write_json(args.json, result)
    print(f"{args.key}: this {medians['this']:.4g}, previous ({args.previous}) {medians['previous']:.4g}, "
          f"ratio {result['ratio']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

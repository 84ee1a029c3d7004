"""How every benchmark states its numbers: a table with each target marked ok / MISSED, and JSON."""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

from edmcgs.atomic import atomic_output


def meets(value: float, target: tuple[str, float]) -> bool:
    """Whether ``value`` satisfies ``target`` = ("<=" or ">=", bound)."""
    op, bound = target
    return value <= bound if op == "<=" else value >= bound


def pick_variants(text: str, variants: dict, prog: str) -> list[str]:
    """The names in the comma-separated ``text``, each one of ``variants`` (else a one-line exit)."""
    names = [v.strip() for v in text.split(",") if v.strip()]
    unknown = [v for v in names if v not in variants]
    if unknown or not names:
        raise SystemExit(f"{prog}: unknown variant(s) {unknown}; choose from {list(variants)}")
    return names


def variant_parser(name: str, doc: str, variants: dict, recording: str) -> argparse.ArgumentParser:
    """``python -m bench.NAME``'s options shared by the benchmarks that train variants of one scene:
    where the report and the cache go, which variants, their steps, another recording, a JSON copy."""
    p = argparse.ArgumentParser(prog=f"python -m bench.{name}", description=doc.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("reports"), help=f"where {name}.md/json/png go")
    p.add_argument("--cache", type=Path, default=Path(f"reports/cache/{name}"),
                   help="recordings and checkpoints")
    p.add_argument("--variants", default=",".join(variants), help=f"comma-separated, of {list(variants)}")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--recording", type=Path, default=None, help=recording)
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    return p


def numeric(results: dict):
    """(key, value) of the numeric entries of ``results`` (booleans are not numbers here)."""
    return ((k, v) for k, v in results.items() if isinstance(v, int | float) and not isinstance(v, bool))


def table(results: dict, targets: dict[str, tuple[str, float]]) -> str:
    """The numeric entries of ``results``, one per row, with their target and whether it is met."""
    rows = [f"{'metric':<30}{'value':>12}  target"]
    for key, value in numeric(results):
        target = targets.get(key)
        mark = ""
        if target is not None:
            mark = f"{target[0]} {target[1]:g}  {'ok' if meets(value, target) else 'MISSED'}"
        shown = f"{value:.2f}" if isinstance(value, float) else str(value)
        rows.append(f"{key:<30}{shown:>12}  {mark}")
    return "\n".join(rows)


def machine() -> str:
    """This machine in words: architecture, CPUs and their model, and the GPU where torch uses one."""
    model = ""
    try:
        with open("/proc/cpuinfo") as info:
            names = (line.split(":", 1)[1].strip() for line in info if line.startswith("model name"))
            model = next(names, "")
    except OSError:
        pass
    words = [f"{platform.machine()}, {os.cpu_count()} CPUs" + (f" ({model})" if model else "")]
    torch = sys.modules.get("torch")  # only where the benchmark already loaded it
    if torch is not None and torch.cuda.is_available():
        words.append(torch.cuda.get_device_name())
    return ", ".join(words)


def run_info() -> dict:
    """How this process ran, for its JSON's ``run`` block (what ``bench.pages`` shows beside each figure):
    the command as typed from the repository root, the machine, the date (UTC) and the load average."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None:
        head = ["python", "-m", spec.name.removesuffix(".__main__")]
    else:
        head = ["python", sys.argv[0]]
    return {"command": shlex.join(head + sys.argv[1:]), "machine": machine(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "load_average_1m": round(os.getloadavg()[0], 2)}


def write_json(path: Path | None, data) -> None:
    """Write ``data`` as indented JSON to ``path`` (parents created); nothing when ``path`` is None. A dict
    gets a ``run`` block (``run_info``) unless it has one."""
    if path is None:
        return
    if isinstance(data, dict) and "run" not in data:
        data = {**data, "run": run_info()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")

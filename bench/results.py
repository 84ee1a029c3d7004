"""How every benchmark states its numbers: a table with each target marked ok / MISSED, and JSON."""

from __future__ import annotations

import json
from pathlib import Path

from edmcgs.atomic import atomic_output


def meets(value: float, target: tuple[str, float]) -> bool:
    """Whether ``value`` satisfies ``target`` = ("<=" or ">=", bound)."""
    op, bound = target
    return value <= bound if op == "<=" else value >= bound


def table(results: dict, targets: dict[str, tuple[str, float]]) -> str:
    """The numeric entries of ``results``, one per row, with their target and whether it is met."""
    rows = [f"{'metric':<30}{'value':>12}  target"]
    for key, value in results.items():
        if isinstance(value, bool) or not isinstance(value, int | float):
            continue
        target = targets.get(key)
        mark = ""
        if target is not None:
            mark = f"{target[0]} {target[1]:g}  {'ok' if meets(value, target) else 'MISSED'}"
        shown = f"{value:.2f}" if isinstance(value, float) else str(value)
        rows.append(f"{key:<30}{shown:>12}  {mark}")
    return "\n".join(rows)


def write_json(path: Path | None, data) -> None:
    """Write ``data`` as indented JSON to ``path`` (parents created); nothing when ``path`` is None."""
    if path is None:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")

"""Where torch code reads tensors back to the host: on a GPU each such read waits for the device.

``HostReads`` counts, by the line of project code that asked, every ``item``, ``tolist``, ``bool``,
``float``, ``int``, ``cpu`` and ``numpy`` of a tensor inside its ``with`` block (a TorchFunctionMode, so it
sees the CPU path too, where such reads cost nothing, and tells which of them a GPU would wait on).
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path

from torch.overrides import TorchFunctionMode

READS = frozenset({"item", "tolist", "__bool__", "__float__", "__int__", "__index__", "cpu", "numpy"})
"""The Tensor methods that bring a value to the host."""
ROOT = Path(__file__).resolve().parents[1]


class HostReads(TorchFunctionMode):
    """``with HostReads() as reads: ...``; then ``reads.sites`` {"path:line": count}, by the innermost
    project frame (paths relative to the repository), ``reads.direct``: those read by project code itself
    (not by a library it called, such as torch's CPU optimizer), and ``reads.total``."""

    def __init__(self) -> None:
        super().__init__()
        self.sites: collections.Counter[str] = collections.Counter()
        self.direct: collections.Counter[str] = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if getattr(func, "__name__", "") in READS:
            caller = sys._getframe(1)
            site = self._site(caller)
            self.sites[site] += 1
            if _in_project(caller):
                self.direct[site] += 1
        return func(*args, **(kwargs or {}))

    @staticmethod
    def _site(frame) -> str:
        while frame is not None:
            if _in_project(frame):
                return f"{Path(frame.f_code.co_filename).relative_to(ROOT)}:{frame.f_lineno}"
            frame = frame.f_back
        return "(outside the project)"

    @property
    def total(self) -> int:
        return sum(self.sites.values())

    def by_file(self) -> dict[str, int]:
        """The counts summed per file."""
        out: collections.Counter[str] = collections.Counter()
        for site, n in self.sites.items():
            out[site.rsplit(":", 1)[0]] += n
        return dict(out)


def _in_project(frame) -> bool:
    path = Path(frame.f_code.co_filename)
    return path.is_relative_to(ROOT) and path != Path(__file__) and ".venv" not in path.parts

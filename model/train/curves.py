"""Training curves for TensorBoard (the optional ``tensorboard`` extra), beside the history CSV.

The trainer hands every step's loss terms, Gaussian count and step time (group ``train``) and every
held-out evaluation (group ``heldout``) to a ``Curves``; ``TensorBoardCurves`` writes them as scalars
``GROUP/NAME`` at the training step, readable by ``tensorboard --logdir DIR``.
"""

from __future__ import annotations

import math
import os
from typing import Protocol

from edmcgs.errors import InvalidInputError

INSTALL = "pip install 'edmcgs[tensorboard]'"
"""How to get the optional extra (``tensorboard``, which torch's SummaryWriter needs)."""


class Curves(Protocol):
    def scalars(self, step: int, group: str, values: dict[str, float]) -> None: ...

    def flush(self) -> None: ...


def tensorboard_missing() -> str | None:
    """None when TensorBoard logging works here, else a one-line reason naming the install command."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401  (fails without tensorboard)
    except ImportError as exc:
        return f"--tensorboard needs the tensorboard package ({exc}); install it with: {INSTALL}"
    return None


class TensorBoardCurves:
    """Scalars into an event file under ``log_dir`` (created). ``purge_step``: the first step this run
    logs; what an earlier run into the same folder logged from there on is dropped, so that the curves of
    a resumed run do not double back."""

    def __init__(self, log_dir: str | os.PathLike, *, purge_step: int | None = None):
        reason = tensorboard_missing()
        if reason is not None:
            raise InvalidInputError(reason)
        from torch.utils.tensorboard import SummaryWriter

        self.log_dir = os.fspath(log_dir)
        self.writer = SummaryWriter(self.log_dir, purge_step=purge_step or None)

    def scalars(self, step: int, group: str, values: dict[str, float]) -> None:
        for name, value in values.items():
            value = float(value)
            if math.isfinite(value):  # a skipped (non-finite) step leaves a gap, not a spike
                self.writer.add_scalar(f"{group}/{name}", value, int(step))

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()

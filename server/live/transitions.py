"""Which transition moves online anchors past the span: g_phi, the checkpoint's distilled one
(``model/online/distill.py``), or none, chosen by how well each predicted the recent frames.

Readers (renders, predictions) take ``module`` once per use; the fit thread replaces it whole and then
bumps ``version`` (the deform cache keys on it), so a reader never sees a half-made choice.
"""

from __future__ import annotations

from collections import deque

import numpy as np
import torch

from edmcgs.errors import InvalidInputError
from edmcgs.model.dynamic import EdMCGS

EVIDENCE = 8
"""Frames the transition is chosen by (the most recent)."""


class Transitions:
    """model: the checkpoint; mode: ``select`` (the candidate with the lowest mean loss over the last
    EVIDENCE frames) or one candidate's name, fixed (protocol.TRANSITIONS)."""

    def __init__(self, model: EdMCGS, mode: str = "select"):
        # the candidates, best first while there is no evidence (None: events move nothing)
        self.candidates: dict[str, torch.nn.Module | None] = {"none": None}
        if model.transition is not None:
            self.candidates = {"g_phi": model.transition, "none": None}
            if model.online_transition is not None:
                self.candidates = {"distilled": model.online_transition, **self.candidates}
        if mode != "select" and mode not in self.candidates:
            raise InvalidInputError(f"transition {mode!r}: the checkpoint has none "
                                    + ("(edmcgs distill makes one)" if mode == "distilled"
                                       else "(no event branch)"))
        self.select = mode == "select" and len(self.candidates) > 1
        """Whether the frames choose (False: one fixed, or the only one)."""
        self.kind = next(iter(self.candidates)) if mode == "select" else mode
        """The candidate moving the predictions and renders past the span now (/scene)."""
        self.module = self.candidates[self.kind]
        """Its module (None: none), or a copy fine-tuned on the corrections."""
        self.evidence: dict[str, deque[float]] = {n: deque(maxlen=EVIDENCE) for n in self.candidates}
        """Per candidate, the L1 of its prediction of each recent frame."""
        self.version = 0

    def record(self, losses: dict[str, float]) -> None:
        """Each candidate's loss on one more frame; the best over the evidence becomes the current one."""
        for name, loss in losses.items():
            self.evidence[name].append(loss)
        chosen = min(self.candidates, key=lambda n: float(np.mean(self.evidence[n])))
        if chosen != self.kind:
            self.module, self.kind = self.candidates[chosen], chosen
            self.version += 1  # after the module: see the module's docstring

    def replace(self, tuned: torch.nn.Module) -> None:
        """The current candidate replaced by a fine-tuned copy of it."""
        self.module = self.candidates[self.kind] = tuned
        self.version += 1

    def info(self) -> dict:
        """GET /scene's ``online.transition``."""
        return {"mode": "select" if self.select else self.kind, "current": self.kind,
                # a snapshot of each: the fit thread appends meanwhile
                "evidence": {name: float(np.mean(v)) if (v := list(losses)) else None
                             for name, losses in self.evidence.items()}}

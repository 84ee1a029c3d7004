"""The part of a network's first layer that depends only on the query points, kept between inference
calls: the deformation networks are always asked at the same control points, only time or the motion
codes change, so gamma(x) and its product with the layer's x-columns need not be recomputed."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch
from torch import Tensor, nn

T = TypeVar("T")


class PointTerms:
    """``get(module, x, build)`` = ``build(x)``, reused while gradients are off, ``module``'s parameters
    unchanged (identity and in-place version) and ``x`` equal to the last points. With gradients on it
    is always rebuilt, so training differentiates through it as before."""

    def __init__(self) -> None:
        self._last: tuple | None = None  # (key, points, terms): replaced whole, so threads never mix

    def get(self, module: nn.Module, x: Tensor, build: Callable[[Tensor], T]) -> T:
        if torch.is_grad_enabled():
            return build(x)
        key = (tuple((id(p), p._version) for p in module.parameters()), x.shape, x.dtype, x.device)
        last = self._last
        if last is not None and last[0] == key and torch.equal(last[1], x):
            return last[2]
        terms = build(x)
        self._last = (key, x.clone(), terms)
        return terms

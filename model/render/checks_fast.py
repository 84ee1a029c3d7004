"""The value checks of ``io.check_inputs`` for numpy inputs, compiled (no temporary arrays)."""

from __future__ import annotations

import numpy as np

from edmcgs.model.render.jit import njit_cached

PROBLEMS = ("means contains NaN or Inf", "quats contains NaN or Inf", "scales contains NaN or Inf",
            "opacities contains NaN or Inf", "colors contains NaN or Inf",
            "scales must be >= 0 (linear scales, not log-scales)",
            "opacities must lie in [0, 1] (activated, not logits)",
            "quats has a zero quaternion; it describes no rotation")
"""What ``first_problem`` finds, by index, in the order ``check_inputs`` reports them."""


@njit_cached(nogil=True, fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _nonfinite(values):
    """How many entries are NaN or Inf (x - x is 0 exactly when x is finite); an integer count, so
    that LLVM vectorises the loop."""
    n = 0
    for i in range(values.shape[0]):
        n += np.int32((values[i] - values[i]) != 0)
    return n


@njit_cached(nogil=True)
def _flags(means, quats, scales, opacities, colors):
    """One flag per entry of PROBLEMS (a plain tuple: no Python object is read inside the kernel).
    Every count is an integer sum, which LLVM vectorises."""
    flat = scales.reshape(-1)
    negative = 0
    for i in range(flat.shape[0]):
        negative += np.int32(flat[i] < 0)
    outside = 0
    for i in range(opacities.shape[0]):
        outside += np.int32((opacities[i] < 0) | (opacities[i] > 1))
    zero = 0
    for i in range(quats.shape[0]):
        zero += np.int32((quats[i, 0] == 0) & (quats[i, 1] == 0) & (quats[i, 2] == 0) & (quats[i, 3] == 0))
    return (_nonfinite(means.reshape(-1)) > 0, _nonfinite(quats.reshape(-1)) > 0,
            _nonfinite(scales.reshape(-1)) > 0, _nonfinite(opacities) > 0, _nonfinite(colors.reshape(-1)) > 0,
            negative > 0, outside > 0, zero > 0)


def first_problem(means, quats, scales, opacities, colors) -> str | None:
    """The message of the first failed check, or None; C-contiguous float arrays of checked shapes."""
    for problem, bad in zip(PROBLEMS, _flags(means, quats, scales, opacities, colors), strict=True):
        if bad:  # the first in PROBLEMS' order, as the torch path checks them
            return problem
    return None

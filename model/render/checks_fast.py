"""The value checks of ``io.check_inputs`` for numpy inputs in one numba pass (no temporaries)."""

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
    bad = np.zeros(len(PROBLEMS), np.bool_)
    flat = (means.reshape(-1), quats.reshape(-1), scales.reshape(-1), opacities, colors.reshape(-1))
    for k, values in enumerate(flat):
        bad[k] = _nonfinite(values) > 0
    negative = 0
    for v in scales.reshape(-1):
        negative += v < 0
    outside = 0
    for v in opacities:
        outside += (v < 0) | (v > 1)
    zero = 0
    for i in range(quats.shape[0]):
        zero += (quats[i, 0] == 0) & (quats[i, 1] == 0) & (quats[i, 2] == 0) & (quats[i, 3] == 0)
    bad[5], bad[6], bad[7] = negative > 0, outside > 0, zero > 0
    return bad


def first_problem(means, quats, scales, opacities, colors) -> str | None:
    """The message of the first failed check, or None; C-contiguous float arrays of checked shapes."""
    bad = _flags(means, quats, scales, opacities, colors)
    for i in range(len(PROBLEMS)):
        if bad[i]:
            # a NaN opacity fails both its checks: report it as non-finite, as the torch path does
            return PROBLEMS[i]
    return None

"""The vectorisable float32 exp and 2^x of ``simd_exp`` against float64 numpy, over their whole range."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from edmcgs.model.render.simd_exp import exp2_nonpositive, exp_nonpositive


@numba.njit
def _apply_exp(x, out):
    for i in range(x.shape[0]):
        out[i] = exp_nonpositive(x[i])


@numba.njit
def _apply_exp2(x, out):
    for i in range(x.shape[0]):
        out[i] = exp2_nonpositive(x[i])


def _run(kernel, x) -> np.ndarray:
    x = np.asarray(x, np.float32)
    out = np.full_like(x, np.nan)
    kernel(x, out)
    return out


@pytest.mark.parametrize("kernel, ref, low, tol", [(_apply_exp, np.exp, -87.0, 4e-7),
                                                   (_apply_exp2, np.exp2, -125.0, 3e-7)])
def test_relative_error_over_the_range(kernel, ref, low, tol):
    x = np.concatenate([np.linspace(low, 0, 1_000_001), -np.logspace(-8, 0, 1001)]).astype(np.float32)
    got = _run(kernel, x).astype(np.float64)
    rel = np.abs(got / ref(x.astype(np.float64)) - 1)
    assert rel.max() < tol, (rel.max(), x[rel.argmax()])


@pytest.mark.parametrize("kernel, low", [(_apply_exp, -87.0), (_apply_exp2, -125.0)])
def test_extremes_stay_finite_small_and_ordered(kernel, low):
    # rounding noise above 0 gives about 1; below the clamp, a tiny positive number, never NaN or Inf
    x = np.array([3e-7, 0.0, -0.0, low, low - 0.4, low - 50, -1e30, -np.inf], np.float32)
    got = _run(kernel, x)
    assert np.isfinite(got).all() and (got > 0).all()
    assert abs(got[0] - 1) < 1e-6 and got[1] == pytest.approx(1, abs=1e-7) and got[2] == got[1]
    assert (got[3:] < 1e-37).all() and (got >= np.finfo(np.float32).tiny).all()  # never subnormal
    assert (np.diff(got[3:]) <= 0).all()


"""SSIM in both conventions against an independent float64 reference: each window's weighted moments
summed explicitly (no convolution), on small images, border cases included."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from edmcgs.model.eval.metrics import ssim_score
from edmcgs.model.eval.ssim import ssim, ssim_map


def reference_ssim_map(a: np.ndarray, b: np.ndarray, *, padded: bool) -> np.ndarray:
    """float64 SSIM map of [H, W, C] images: 11x11 Gaussian (sigma 1.5) windows inside the image, or
    (``padded``) centred on every pixel of the image zero-padded by 5, as the 3DGS papers compute it."""
    x = np.arange(11, dtype=np.float64) - 5
    g = np.exp(-x ** 2 / (2 * 1.5 ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    out = []
    for ch in range(a.shape[2]):
        p, q = a[..., ch].astype(np.float64), b[..., ch].astype(np.float64)
        if padded:
            p, q = np.pad(p, 5), np.pad(q, 5)
        wp, wq = sliding_window_view(p, (11, 11)), sliding_window_view(q, (11, 11))
        mp, mq = (wp * w).sum((-2, -1)), (wq * w).sum((-2, -1))
        vp = (w * (wp - mp[..., None, None]) ** 2).sum((-2, -1))
        vq = (w * (wq - mq[..., None, None]) ** 2).sum((-2, -1))
        cov = (w * (wp - mp[..., None, None]) * (wq - mq[..., None, None])).sum((-2, -1))
        out.append((2 * mp * mq + c1) * (2 * cov + c2) / ((mp ** 2 + mq ** 2 + c1) * (vp + vq + c2)))
    return np.stack(out, -1)


def _pair(h: int, w: int, c: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.random((h, w, c))
    # b: a blurred, shifted and noisy copy, so SSIM is neither 1 nor near 0.
    b = np.clip(0.7 * np.roll(a, 1, axis=1) + 0.2 * rng.random((h, w, c)) + 0.05, 0, 1)
    return a.astype(np.float32), b.astype(np.float32)


@pytest.mark.parametrize(("h", "w", "c"), [(11, 11, 1), (17, 23, 3), (32, 48, 3), (13, 40, 1)])
@pytest.mark.parametrize("convention", ["valid", "3dgs"])
def test_matches_the_float64_reference(h, w, c, convention):
    a, b = _pair(h, w, c, seed=h * w + c)
    ref = reference_ssim_map(a, b, padded=convention == "3dgs")
    got = ssim_map(torch.from_numpy(a), torch.from_numpy(b), convention=convention).double().numpy()
    assert got.shape == ref.shape == ((h, w, c) if convention == "3dgs" else (h - 10, w - 10, c))
    np.testing.assert_allclose(got, ref, atol=2e-5)
    assert ssim_score(a, b, convention) == pytest.approx(float(ref.mean()), abs=1e-5)


def test_the_conventions_differ_at_the_border_only():
    a, b = _pair(32, 48, 3, seed=5)
    valid = ssim_map(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    padded = ssim_map(torch.from_numpy(a), torch.from_numpy(b), convention="3dgs").numpy()
    np.testing.assert_allclose(padded[5:-5, 5:-5], valid, atol=1e-6)  # same windows inside
    assert ssim_score(a, b, "3dgs") != pytest.approx(ssim_score(a, b, "valid"), abs=1e-4)
    for convention in ("valid", "3dgs"):
        assert float(ssim(torch.from_numpy(a), torch.from_numpy(a), convention=convention)) == \
            pytest.approx(1.0, abs=1e-5)
    with pytest.raises(ValueError, match="one of"):
        ssim_score(a, b, "inria")

"""Structural similarity (Wang et al. 2004): 11x11 Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2,
in two conventions that differ only at the image border:

- ``"valid"`` (ours, the default and the training loss's): only windows that lie wholly inside the image,
  so the border carries no zero-padding bias; the mean is over the (H - 10) x (W - 10) window centres.
- ``"3dgs"``: the convention of the 3DGS papers' numbers (Inria's ``utils/loss_utils.py``): the same window
  zero-padded by 5 pixels (``conv2d(..., padding=5)``), every pixel a centre, the mean over the full image.
  A border window then sees the same zeros in both images, which makes them look more alike: the scores
  are higher than ``"valid"``'s (by about 0.01 on our scenes), so a number set beside a paper's must be
  this one.

An image smaller than the window gets, in ``"valid"``, the largest odd window that fits, its sigma shrunk in
proportion, so that tiny renders (a low training scale) still have a defined SSIM.
"""

import torch
import torch.nn.functional as F
from torch import Tensor

_C1 = 0.01 ** 2
_C2 = 0.03 ** 2
CONVENTIONS = ("valid", "3dgs")
"""``ssim``'s conventions: windows inside the image only, or the 3DGS papers' zero-padded full image."""


def _window(size: int, sigma: float, dtype, device) -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-x.square() / (2 * sigma * sigma))
    return g / g.sum()


def ssim_map(a: Tensor, b: Tensor, *, size: int = 11, sigma: float = 1.5,
             convention: str = "valid") -> Tensor:
    """Per-pixel SSIM of two images.

    a, b: Tensor  # [H, W, C] in [0, 1]
    returns Tensor  # "valid": [H - size + 1, W - size + 1, C] (no padding bias at borders);
                    # "3dgs": [H, W, C] (zero-padded by size // 2, as the 3DGS papers compute it)
    """
    if convention not in CONVENTIONS:
        raise ValueError(f"SSIM convention {convention!r}: one of {CONVENTIONS}")
    pad = 0
    if convention == "3dgs":
        pad = size // 2
    else:
        fit = min(size, a.shape[0], a.shape[1])
        fit -= 1 - fit % 2
        if fit < size:
            size, sigma = fit, sigma * fit / size
    # The five maps blurred in one depthwise convolution, each image channel its own group: one call, not
    # four, and on the CPU a one-channel convolution's backward is several times slower than a depthwise
    # one's (the real preset's step on grey frames 176 / 159 -> 95 / 102 ms: docs/benchmarks/training.md).
    c, h, w = a.shape[-1], a.shape[0], a.shape[1]
    n = 5 * c
    x = torch.stack([a, b, a * a, b * b, a * b]).permute(0, 3, 1, 2).reshape(1, n, h, w)
    g = _window(size, sigma, x.dtype, x.device)
    kx = g.view(1, 1, 1, size).expand(n, 1, 1, size)
    ky = g.view(1, 1, size, 1).expand(n, 1, size, 1)
    # Separable: the same as one conv2d with the outer-product window (Inria's), zeros outside.
    blurred = F.conv2d(F.conv2d(x, kx, groups=n, padding=(0, pad)), ky, groups=n, padding=(pad, 0))
    mu_a, mu_b, aa, bb, ab = blurred.reshape(5, c, blurred.shape[-2], blurred.shape[-1])
    var_a = aa - mu_a.square()
    var_b = bb - mu_b.square()
    cov = ab - mu_a * mu_b
    num = (2 * mu_a * mu_b + _C1) * (2 * cov + _C2)
    den = (mu_a.square() + mu_b.square() + _C1) * (var_a + var_b + _C2)
    return (num / den).permute(1, 2, 0)


def ssim(a: Tensor, b: Tensor, *, convention: str = "valid") -> Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1] (a scalar tensor) in ``convention`` (``CONVENTIONS``)."""
    return ssim_map(a, b, convention=convention).mean()

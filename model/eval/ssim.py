"""Structural similarity (Wang et al. 2004): 11x11 Gaussian window, sigma 1.5, as in 3DGS.

An image smaller than the window gets the largest odd window that fits, its sigma shrunk in proportion,
so that tiny renders (a low training scale) still have a defined SSIM.
"""

import torch
import torch.nn.functional as F
from torch import Tensor

_C1 = 0.01 ** 2
_C2 = 0.03 ** 2


def _window(size: int, sigma: float, dtype, device) -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-x.square() / (2 * sigma * sigma))
    return g / g.sum()


def ssim_map(a: Tensor, b: Tensor, *, size: int = 11, sigma: float = 1.5) -> Tensor:
    """Per-pixel SSIM of two images.

    a, b: Tensor  # [H, W, C] in [0, 1]
    returns Tensor  # [H - size + 1, W - size + 1, C] ('valid' windows, no padding bias at borders)
    """
    fit = min(size, a.shape[0], a.shape[1])
    fit -= 1 - fit % 2
    if fit < size:
        size, sigma = fit, sigma * fit / size
    x = torch.stack([a, b]).permute(0, 3, 1, 2)  # [2, C, H, W]
    c = x.shape[1]
    g = _window(size, sigma, x.dtype, x.device)
    kx = g.view(1, 1, 1, size).expand(c, 1, 1, size)
    ky = g.view(1, 1, size, 1).expand(c, 1, size, 1)

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(t, kx, groups=c), ky, groups=c)

    mu = blur(x)
    mu_a, mu_b = mu[0], mu[1]
    var_a = blur(x[:1] * x[:1])[0] - mu_a.square()
    var_b = blur(x[1:] * x[1:])[0] - mu_b.square()
    cov = blur(x[:1] * x[1:])[0] - mu_a * mu_b
    num = (2 * mu_a * mu_b + _C1) * (2 * cov + _C2)
    den = (mu_a.square() + mu_b.square() + _C1) * (var_a + var_b + _C2)
    return (num / den).permute(1, 2, 0)


def ssim(a: Tensor, b: Tensor) -> Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1] (a scalar tensor)."""
    return ssim_map(a, b).mean()

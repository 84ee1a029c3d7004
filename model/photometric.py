"""The photometric loss at the RGB anchors: (1 - lambda_d) L1 + lambda_d D-SSIM."""

from edmcgs.model.ssim import ssim
from torch import Tensor


def photometric_loss(rendered: Tensor, target: Tensor, lambda_dssim: float) -> Tensor:
    """rendered, target: Tensor  # [H, W, C] in [0, 1]; D-SSIM = 1 - SSIM (as in 3DGS)."""
    l1 = (rendered - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(rendered, target))

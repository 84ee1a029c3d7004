"""Image-quality metrics on [H, W, C] float images in [0, 1]: PSNR and SSIM (LPIPS: ``lpips.py``)."""

import math

import numpy as np
import torch

from edmcgs.model.eval.ssim import ssim


def psnr(image: np.ndarray, target: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB (peak 1); capped at 100 dB for identical images."""
    mse = float(np.mean((np.asarray(image, np.float64) - np.asarray(target, np.float64)) ** 2))
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def ssim_score(image: np.ndarray, target: np.ndarray, convention: str = "valid") -> float:
    """Mean SSIM (11x11 Gaussian window, sigma 1.5) in ``convention``: "valid" (windows inside the image)
    or "3dgs" (the 3DGS papers' zero-padded full image; see ``ssim.py``)."""
    with torch.no_grad():
        return float(ssim(torch.as_tensor(np.asarray(image, np.float32)),
                          torch.as_tensor(np.asarray(target, np.float32)), convention=convention))

"""Evaluation: image metrics (PSNR, SSIM, LPIPS) and held-out evaluation through the inference API."""

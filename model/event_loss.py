"""The event loss from the event generation model: L(t_b) - L(t_a) = C * sum of polarities in [t_a, t_b]."""

import torch
import torch.nn.functional as F
from torch import Tensor

LUMA = (0.299, 0.587, 0.114)
"""Rec. 601 weights that turn a rendered RGB image into the luminance an event pixel sees."""


def log_luminance(image: Tensor, eps: float) -> Tensor:
    """log(I + eps) of a [H, W, C] image in [0, 1] (C = 1 grey, or 3 RGB reduced to luminance) -> [H, W]."""
    if image.shape[-1] == 3:
        lum = image @ torch.tensor(LUMA, dtype=image.dtype, device=image.device)
    else:
        lum = image[..., 0]
    return torch.log(lum.clamp_min(0.0) + eps)


def event_loss(render_a: Tensor, render_b: Tensor, event_sum: Tensor, contrast: float, eps: float, *,
               levels: int = 1) -> Tensor:
    """Mean L1 between the rendered log-luminance change and the events' prediction of it.

    render_a, render_b: Tensor  # [H, W, C] renders at t_a < t_b (render them with colours detached, so
                                #  that this loss moves geometry and motion, never the colours)
    event_sum: Tensor           # [H, W] signed polarity sum over [t_a, t_b) at the render's resolution
    levels: 1 compares pixels (the paper's loss); L > 1 averages it over a pyramid of L levels, each
            2x2 mean-pooled from the one before. A coarse level still sees an edge that moved further
            than a pixel's neighbourhood, so large motions get a gradient towards the events.
    """
    change = log_luminance(render_b, eps) - log_luminance(render_a, eps)
    residual = (change - contrast * event_sum)[None, None]
    total = residual.abs().mean()
    for _ in range(levels - 1):
        if min(residual.shape[-2:]) < 2:
            break
        residual = F.avg_pool2d(residual, 2)
        total = total + residual.abs().mean()
    return total / levels

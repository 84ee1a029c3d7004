"""The losses of training, each a pure function of tensors.

- photometric: (1 - lambda_d) L1 + lambda_d D-SSIM at the RGB anchors;
- event: the event generation model, L(t_b) - L(t_a) = C * sum of polarities in [t_a, t_b);
- regularisers on the control points: temporal local isometry (TLI) and KNN Laplacian smoothness.

A new loss is a function here, weighted by a config field and composed in ``trainer``.
"""

import torch
import torch.nn.functional as F
from torch import Tensor

from edmcgs.luminance import LUMA
from edmcgs.model.eval.ssim import ssim


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



def photometric_loss(rendered: Tensor, target: Tensor, lambda_dssim: float) -> Tensor:
    """rendered, target: Tensor  # [H, W, C] in [0, 1]; D-SSIM = 1 - SSIM (as in 3DGS)."""
    l1 = (rendered - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(rendered, target))


def pyramid_l1(rendered: Tensor, target: Tensor, levels: int) -> Tensor:
    """Mean L1 of [H, W, C] images at ``levels`` - 1 coarser levels (each 2x2 mean-pooled from the one
    before; 0 for levels <= 1). A small object displaced by more than its own size overlaps its target
    only at a coarse level: there the loss still pulls it the right way."""
    total = rendered.new_zeros(())
    a, b = rendered.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
    used = 0
    for _ in range(levels - 1):
        if min(a.shape[-2:]) < 2:
            break
        a, b = F.avg_pool2d(a, 2), F.avg_pool2d(b, 2)
        total = total + (a - b).abs().mean()
        used += 1
    return total / max(used, 1)


def tli_loss(points_t1: Tensor, points_t2: Tensor, graph: Tensor) -> Tensor:
    """Mean squared change of edge length between two nearby times.

    points_t1, points_t2: Tensor  # [M, 3] deformed control points at t - dt/2 and t + dt/2
    graph: Tensor                 # [R, K] int64 neighbours of the first R <= M points (edges
                                  #  (j, graph[j, k]); R < M: one anchor window's own points)
    Zero for any rigid motion between the two times; positive for a stretch or shear; zero without
    edges (a window with no points of its own: the moving preset's before its lift).
    """
    r = graph.shape[0]
    len1 = (points_t1[:r, None, :] - points_t1[graph]).norm(dim=-1)
    len2 = (points_t2[:r, None, :] - points_t2[graph]).norm(dim=-1)
    return _mean((len1 - len2).square())


def _mean(x: Tensor) -> Tensor:
    """The mean of ``x``; 0 when it is empty (torch's is NaN)."""
    return x.sum() / max(x.numel(), 1)


def laplacian_smoothness(values: Tensor, graph: Tensor) -> Tensor:
    """Mean squared difference of each point's value from the mean of its graph neighbours.

    values: Tensor  # [M, D] (g_phi's displacement per control point)
    graph: Tensor   # [R, K] int64 neighbours of the first R <= M points (as ``tli_loss``; none: 0)
    """
    return _mean((values[:graph.shape[0]] - values[graph].mean(1)).square().sum(-1))

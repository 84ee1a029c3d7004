"""EWA splatting of 3D Gaussians to the screen (the 3DGS math), shared by both rasterizers.

Conventions: pixel centres at integer coordinates; a Gaussian covers the 16x16 tiles that hold a pixel
centre within its 3-sigma screen radius (3DGS's ``getRect`` drops the last tile when mean + radius lies
in its first pixel's unit, though that row's alpha may still reach alpha_min; gsplat keeps it); inside
those, a pixel takes it when
alpha = min(0.99, opacity * exp(-q/2)) >= alpha_min. ``screen_rect`` returns the pixel rectangle
where that can happen: the tile rectangle clipped to the ellipse q <= 2 ln(opacity / alpha_min)
(a little enlarged against rounding). Clipping only drops pixels whose alpha is below alpha_min,
so it changes no pixel's value; it only saves the work of evaluating them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from edmcgs.geometry import Intrinsics, quat_to_rotmat

TILE = 16
"""Tile edge in pixels: a Gaussian is considered for every pixel of every tile its radius touches."""
LOWPASS = 0.3
"""Screen-space low-pass filter (px^2) added to the diagonal of every 2D covariance."""
SIGMAS = 3.0
"""Screen radius in standard deviations of the major axis."""
ALPHA_MAX = 0.99
"""Per-Gaussian alpha is clamped here, so no single splat makes a pixel fully opaque."""
ALPHA_MIN = 1.0 / 255.0
"""A splat contributes to a pixel only where its alpha reaches this."""
T_MIN = 1e-4
"""A pixel stops taking splats once blending the next would leave less transmittance than this."""
NEAR = 0.01
"""Gaussians at camera z <= NEAR are culled (``rasterize``'s default)."""
FRUSTUM_SLACK = 0.3
"""The Jacobian's x/z, y/z are clamped to the view frustum widened by this fraction of tan(fov/2)."""


@dataclass
class Splats:
    """Gaussians on the screen, one row per input Gaussian.

    mean2d: Tensor  # [N, 2] pixel coordinates (u, v)
    cov2d: Tensor   # [N, 3] (a, b, c) of the dilated covariance [[a, b], [b, c]], px^2
    conic: Tensor   # [N, 3] (A, B, C) of its inverse
    depth: Tensor   # [N] camera z
    """

    mean2d: Tensor
    cov2d: Tensor
    conic: Tensor
    depth: Tensor


def ewa_project(means: Tensor, quats: Tensor, scales: Tensor, w2c: Tensor, intrinsics: Intrinsics,
                near: float) -> Splats:
    """Project Gaussians with the local affine (EWA) approximation of the perspective map.

    means: Tensor   # [N, 3] world
    quats: Tensor   # [N, 4] (w, x, y, z), non-zero (normalised here)
    scales: Tensor  # [N, 3] linear, >= 0
    w2c: Tensor     # [4, 4] world-to-camera, same dtype/device as means
    Differentiable. Rows with depth <= near come out finite but meaningless (the Jacobian uses
    depth clamped to ``near``); callers cull them.
    """
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    rot = w2c[:3, :3]
    cam = means @ rot.T + w2c[:3, 3]
    x, y, z = cam.unbind(-1)
    inv_z = 1.0 / z.clamp_min(near)
    mean2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], dim=-1)

    tan_x, tan_y = 0.5 * intrinsics.width / fx, 0.5 * intrinsics.height / fy
    slack_x, slack_y = FRUSTUM_SLACK * tan_x, FRUSTUM_SLACK * tan_y
    xz = (x * inv_z).clamp(-(cx / fx + slack_x), (intrinsics.width - cx) / fx + slack_x)
    yz = (y * inv_z).clamp(-(cy / fy + slack_y), (intrinsics.height - cy) / fy + slack_y)
    zeros = torch.zeros_like(inv_z)
    jac = torch.stack([torch.stack([fx * inv_z, zeros, -fx * xz * inv_z], -1),
                       torch.stack([zeros, fy * inv_z, -fy * yz * inv_z], -1)], dim=-2)  # [N, 2, 3]

    rotg = quat_to_rotmat(quats / quats.norm(dim=-1, keepdim=True))
    m = (jac @ rot) @ rotg * scales[:, None, :]  # [N, 2, 3]; cov2d = m m^T
    m0, m1 = m[:, 0], m[:, 1]
    a0, b, c0 = (m0 * m0).sum(-1), (m0 * m1).sum(-1), (m1 * m1).sum(-1)
    # det(m m^T) as a sum of squared 2x2 minors (Cauchy-Binet): never negative, even for needles
    # whose a0 * c0 - b^2 would cancel catastrophically in float32.
    minors = torch.stack([m0[:, 0] * m1[:, 1] - m0[:, 1] * m1[:, 0],
                          m0[:, 0] * m1[:, 2] - m0[:, 2] * m1[:, 0],
                          m0[:, 1] * m1[:, 2] - m0[:, 2] * m1[:, 1]], -1)
    det = (minors * minors).sum(-1) + LOWPASS * (a0 + c0) + LOWPASS * LOWPASS
    a, c = a0 + LOWPASS, c0 + LOWPASS
    conic = torch.stack([c / det, -b / det, a / det], dim=-1)
    return Splats(mean2d, torch.stack([a, b, c], -1), conic, z)


def screen_rect(splats: Splats, opacities: Tensor, width: int, height: int, near: float,
                alpha_min: float = ALPHA_MIN) -> Tensor:
    """Half-open pixel rectangle [x0, x1) x [y0, y1) where each splat can reach alpha_min.

    returns Tensor  # [N, 4] int64 (x0, y0, x1, y1); empty (x0 >= x1 or y0 >= y1) for culled splats:
    depth <= near, non-finite screen covariance (overflow), opacity < alpha_min, or off-screen.
    Not differentiable.
    """
    with torch.no_grad():
        a, b, c = splats.cov2d.unbind(-1)
        mx, my = splats.mean2d.unbind(-1)
        grid_x, grid_y = -(-width // TILE), -(-height // TILE)
        # 3DGS: radius = ceil(3 sqrt(lambda_max)), lambda_max = mid + sqrt(max(0.1, mid^2 - det));
        # mid^2 - det is written as ((a - c) / 2)^2 + b^2, which cannot cancel.
        lam = 0.5 * (a + c) + torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp_min(0.1))
        radius = torch.ceil(SIGMAS * torch.sqrt(lam))
        tx0 = torch.floor((mx - radius) / TILE).clamp(0, grid_x)
        tx1 = (torch.floor((mx + radius) / TILE) + 1).clamp(0, grid_x)
        ty0 = torch.floor((my - radius) / TILE).clamp(0, grid_y)
        ty1 = (torch.floor((my + radius) / TILE) + 1).clamp(0, grid_y)
        # Ellipse where opacity * exp(-q/2) >= alpha_min: q <= tau; its bounding box is
        # mean +- sqrt(tau * a), mean +- sqrt(tau * c). 0.1% + 1e-3 of slack covers float32 rounding.
        if alpha_min > 0:
            tau = 2.0 * torch.log(opacities.clamp_min(1e-30) / alpha_min) * 1.001 + 1e-3
            ex, ey = torch.sqrt(tau.clamp_min(0) * a), torch.sqrt(tau.clamp_min(0) * c)
        else:
            ex = ey = torch.full_like(a, math.inf)
        x0 = torch.maximum(tx0 * TILE, torch.ceil(mx - ex)).clamp(0, width)
        x1 = torch.minimum((tx1 * TILE).clamp_max(width), torch.floor(mx + ex) + 1).clamp(0, width)
        y0 = torch.maximum(ty0 * TILE, torch.ceil(my - ey)).clamp(0, height)
        y1 = torch.minimum((ty1 * TILE).clamp_max(height), torch.floor(my + ey) + 1).clamp(0, height)
        finite = (torch.isfinite(splats.cov2d).all(-1) & torch.isfinite(splats.conic).all(-1)
                  & torch.isfinite(splats.mean2d).all(-1))
        ok = finite & (splats.depth > near) & (opacities >= alpha_min) & (x0 < x1) & (y0 < y1)
        rect = torch.stack([x0, y0, x1, y1], -1)
        rect = torch.where(ok[:, None] & torch.isfinite(rect), rect, torch.zeros_like(rect))
        return rect.long()


_REACH_SIGMAS = max(SIGMAS, math.sqrt(2.002 * math.log(1 / ALPHA_MIN) + 1e-3))
"""How far from its mean ``screen_rect`` can place a splat, in standard deviations: the tiles' 3-sigma
radius, or the alpha_min ellipse of an opaque splat where that reaches farther."""


def may_draw(means: Tensor, max_scales: Tensor, w2c: Tensor, intrinsics: Intrinsics, near: float, *,
             reach: float = 0.0, growth: float = 1.0) -> Tensor:
    """[N] bool: False only for Gaussians that ``screen_rect`` cannot place on this view's screen, even
    after each moved by up to ``reach`` (world units, any direction) and its scales grown by ``growth``.

    means: Tensor       # [N, 3] world positions
    max_scales: Tensor  # [N] each Gaussian's largest standard deviation (any rotation)
    w2c: Tensor         # [4, 4] on the means' device
    The screen radius is bounded through the Jacobian's Frobenius norm, its clamped x/z and y/z at their
    largest (lambda_max <= |J|^2 s^2 + the low-pass and screen_rect's 0.1 floor), and the mean's shift by
    the largest gradient of the projection over the ball of radius ``reach``. A Gaussian that may cross
    the near plane is kept."""
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    width, height = intrinsics.width, intrinsics.height
    with torch.no_grad():
        cam = means @ w2c[:3, :3].T + w2c[:3, 3]
        x, y, z = cam.unbind(-1)
        zc = (z - reach).clamp_min(near)  # the nearest the ball comes, where every bound is largest
        tx = max(cx, width - cx) / fx + FRUSTUM_SLACK * 0.5 * width / fx
        ty = max(cy, height - cy) / fy + FRUSTUM_SLACK * 0.5 * height / fy
        jac = math.sqrt(fx * fx * (1 + tx * tx) + fy * fy * (1 + ty * ty)) / zc
        spread = (jac * max_scales * growth).square() + LOWPASS + math.sqrt(0.1)
        radius = _REACH_SIGMAS * torch.sqrt(spread) + 2
        inv_z = 1.0 / z.clamp_min(near)
        u, v = fx * x * inv_z + cx, fy * y * inv_z + cy
        if reach > 0:  # |grad u| <= (fx / z) (1 + |x| / z) over the ball, at its nearest z (v alike)
            radius = radius + reach * (fx + fy) / zc * (1 + (x.abs() + y.abs() + reach) / zc)
        on_screen = (u + radius >= 0) & (u - radius < width) & (v + radius >= 0) & (v - radius < height)
        crossing = (z - reach <= near) & (z + reach > near)
        return ((z > near) & on_screen) | crossing

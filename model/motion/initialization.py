"""Initial canonical Gaussians: scene centre and extent, back-projected pixels, 3D points.

Without a point cloud the anchors' pixels are lifted to the depth of the scene centre (with a little
depth jitter) in their own colours. The centre is where the anchors' optical axes meet (least
squares); when they do not meet (a static or translating camera) it is ``init_depth`` in front of the
mean camera. With structure from motion's points (``--poses auto``), the static set starts on them
(``point_gaussians``), as 3DGS starts, and a pixel lifted later can take its depth from a render
(``backproject_anchors``' ``depth``).
"""

from __future__ import annotations

import numpy as np
import torch

from edmcgs.geometry import Intrinsics
from edmcgs.model.motion.neighbors import knn

POINT_OPACITY = 0.1
"""Opacity of the Gaussians started on 3D points (3DGS's)."""


def scene_center_and_extent(poses: np.ndarray, intrinsics: Intrinsics,
                            init_depth: float) -> tuple[np.ndarray, float]:
    """Centre of attention of the cameras and the half-width of the view there.

    poses: np.ndarray  # [F, 4, 4] float64 camera-to-world (OpenCV)
    returns (center [3] float64, extent float > 0)
    """
    origins = poses[:, :3, 3]
    axes = poses[:, :3, 2] / np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True)
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # [F, 3, 3] off-axis projectors
    a = proj.sum(0)
    b = (proj @ origins[:, :, None]).sum(0)[:, 0]
    eig = np.linalg.eigvalsh(a)
    center = None
    if eig[0] > 1e-3 * eig[-1]:
        candidate = np.linalg.solve(a, b)
        depths = ((candidate - origins) * axes).sum(1)
        if np.all(depths > 0):
            center = candidate
    if center is None:
        center = origins.mean(0) + init_depth * axes.mean(0) / np.linalg.norm(axes.mean(0))
    depth = float(np.mean(np.linalg.norm(center - origins, axis=1)))
    half_fov = max(intrinsics.width / (2 * intrinsics.fx), intrinsics.height / (2 * intrinsics.fy))
    return center, max(depth * half_fov, 1e-6)


def backproject_anchors(images: np.ndarray, poses: np.ndarray, intrinsics: Intrinsics, center: np.ndarray,
                        extent: float, n: int, rng: np.random.Generator, background: np.ndarray,
                        jitter: float = 0.05, threshold: float = 2.0 / 255.0, return_views: bool = False,
                        depth: np.ndarray | None = None, candidates: np.ndarray | None = None):
    """``n`` Gaussians on random anchor pixels at the centre's depth (one on every candidate pixel when
    there are at most ``n``).

    images: np.ndarray      # [F, H, W, C] uint8
    poses: np.ndarray       # [F, 4, 4] float64 c2w
    background: np.ndarray  # [C] in [0, 1], or [F, H, W, C] per anchor pixel (a background layer's
                            #  views): pixels within ``threshold`` of it are already explained by the
                            #  background and get no Gaussian (unless every pixel is such)
    depth: np.ndarray       # [F, H, W] each pixel's depth (camera z) where known (> 0), e.g. a render's;
                            #  elsewhere the centre's
    candidates: np.ndarray  # [F, H, W] bool: the pixels to lift (instead of those that differ from
                            #  ``background``)
    returns (points [n, 3], colors [n, C] in [0, 1], scales [n]) float32 tensors, and with
    ``return_views`` the [n] int64 anchor index each point was lifted from
    """
    f, h, w, _ = images.shape
    differs = candidates if candidates is not None else \
        np.abs(images.astype(np.float32) / 255.0 - background).max(-1) > threshold
    candidates = np.flatnonzero(differs) if differs.any() else np.arange(differs.size)
    # As many as there are candidates: one on each (a background layer leaves few: the movers).
    picked = candidates if n >= candidates.size else rng.choice(candidates, n)
    n = picked.size
    view, v, u = np.unravel_index(picked, (f, h, w))
    c2w = poses[view]
    depth_center = ((center - c2w[:, :3, 3]) * c2w[:, :3, 2]).sum(1)
    z = np.maximum(depth_center + rng.uniform(-jitter, jitter, n) * extent, 1e-3 * depth_center)
    if depth is not None:
        known = depth[view, v, u]
        z = np.where(known > 0, known, z)
    cam = np.stack([(u - intrinsics.cx) / intrinsics.fx * z, (v - intrinsics.cy) / intrinsics.fy * z, z], 1)
    world = (c2w[:, :3, :3] @ cam[:, :, None])[:, :, 0] + c2w[:, :3, 3]
    colors = images[view, v, u].astype(np.float32) / 255.0
    points = torch.from_numpy(world.astype(np.float32))
    # Half the mean spacing of the samples on the image plane (n / f of them over each view's
    # candidate pixels), lifted to each point's depth: neighbouring splats overlap a little.
    spacing_px = np.sqrt(candidates.size / n)
    scales = torch.from_numpy((0.5 * spacing_px * z / intrinsics.fx).astype(np.float32))
    out = points, torch.from_numpy(colors), scales.clamp(1e-4 * extent, 0.05 * extent)
    return (*out, torch.from_numpy(view.astype(np.int64))) if return_views else out


def point_gaussians(xyz: np.ndarray, colors: np.ndarray, extent: float) -> tuple[torch.Tensor, torch.Tensor,
                                                                                 torch.Tensor]:
    """Gaussians on 3D points, as 3DGS starts them: each as wide as the root mean square distance to
    its 3 nearest neighbours (bounded to [1e-4, 0.05] of the extent).

    xyz: np.ndarray     # [P, 3] float64, P >= 2
    colors: np.ndarray  # [P, C] uint8
    returns (points [P, 3], colors [P, C] in [0, 1], scales [P]) float32 tensors
    """
    points = torch.from_numpy(np.asarray(xyz, dtype=np.float32))
    d2, _ = knn(points, points, min(3, len(points) - 1), exclude_self=True)
    scales = d2.mean(1).sqrt().clamp(1e-4 * extent, 0.05 * extent)
    return points, torch.from_numpy(np.asarray(colors, dtype=np.float32) / 255.0), scales


def median_depth(xyz: np.ndarray, poses: np.ndarray) -> float | None:
    """The median depth (camera z) of points ``xyz`` [P, 3] in front of the cameras ``poses`` [F, 4, 4]
    (c2w); None when none is in front."""
    rel = np.asarray(xyz, dtype=np.float64)[None] - poses[:, None, :3, 3]
    z = np.einsum("fpj,fj->fp", rel, poses[:, :3, 2])
    z = z[z > 0]
    return float(np.median(z)) if z.size else None

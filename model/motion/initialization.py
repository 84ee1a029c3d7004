"""Initial canonical Gaussians from the anchor frames: scene centre and extent, back-projected pixels.

There is no SfM point cloud for an event camera's sparse frames, so the anchors' pixels are lifted to
the depth of the scene centre (with a little depth jitter) in their own colours. The centre is where
the anchors' optical axes meet (least squares); when they do not meet (a static or translating
camera) it is ``init_depth`` in front of the mean camera.
"""

from __future__ import annotations

import numpy as np
import torch

from edmcgs.geometry import Intrinsics


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
                        jitter: float = 0.05, threshold: float = 2.0 / 255.0, return_views: bool = False):
    """``n`` Gaussians on random anchor pixels at the centre's depth (one on every candidate pixel when
    there are at most ``n``).

    images: np.ndarray      # [F, H, W, C] uint8
    poses: np.ndarray       # [F, 4, 4] float64 c2w
    background: np.ndarray  # [C] in [0, 1], or [F, H, W, C] per anchor pixel (a background layer's
                            #  views): pixels within ``threshold`` of it are already explained by the
                            #  background and get no Gaussian (unless every pixel is such)
    returns (points [n, 3], colors [n, C] in [0, 1], scales [n]) float32 tensors, and with
    ``return_views`` the [n] int64 anchor index each point was lifted from
    """
    f, h, w, _ = images.shape
    differs = np.abs(images.astype(np.float32) / 255.0 - background).max(-1) > threshold
    candidates = np.flatnonzero(differs) if differs.any() else np.arange(differs.size)
    # As many as there are candidates: one on each (a background layer leaves few: the movers).
    picked = candidates if n >= candidates.size else rng.choice(candidates, n)
    n = picked.size
    view, v, u = np.unravel_index(picked, (f, h, w))
    c2w = poses[view]
    depth_center = ((center - c2w[:, :3, 3]) * c2w[:, :3, 2]).sum(1)
    z = np.maximum(depth_center + rng.uniform(-jitter, jitter, n) * extent, 1e-3 * depth_center)
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

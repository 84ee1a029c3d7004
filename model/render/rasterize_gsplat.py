"""The compositing of ``rasterize`` on CUDA by gsplat (the optional ``cuda`` extra: ``edmcgs[cuda]``).

gsplat's ``rasterization`` is the field's maintained CUDA rasterizer of the same 3DGS math: EWA
projection with the 0.3 px^2 low-pass, the Jacobian clamped to the frustum widened by 0.3 tan(fov/2),
16x16 tiles, depth-sorted front-to-back blending, alpha < 1/255 skipped, a pixel stopping where its
transmittance would fall to 1e-4. What it is handed here:

- the camera: ``viewmats`` is our world-to-camera (OpenCV axes, as ours), ``Ks`` our intrinsics with
  the principal point moved by +0.5 px: gsplat's pixel centres lie at i + 0.5, ours at integers;
- the Gaussians as they are (quaternions (w, x, y, z), normalised by gsplat as by us; linear scales;
  activated opacities);
- colours already evaluated (``sh_degree=None``): ``rasterize`` turns SH into colours with the torch
  code of the other paths, so every path has one colour convention, grey included; the camera depth
  rides along as one more channel when a depth map is asked for;
- no background: ``rasterize`` composites it under the splats from the returned transmittance, as for
  the other compositors.

Where gsplat's contract differs from ours (``projection``'s): a single splat's alpha is clamped at
0.999 rather than 0.99, and a Gaussian covers the tiles of its 3.33-sigma box per axis (or less, where
its opacity cannot reach 1/255 that far) rather than those of its 3-sigma radius. Both only matter for
opacities above about 0.35 (beyond 3 sigma a splat's alpha is below 1/255 otherwise) and change a pixel
by at most about 1% of a splat's colour; below that the two agree to float32 rounding, values and
gradients (``tests/raster/test_rasterize_gsplat.py``).
"""

from __future__ import annotations

import functools
import importlib.util
import logging
import math

import torch
from torch import Tensor

from edmcgs.errors import RenderError
from edmcgs.geometry import Intrinsics
from edmcgs.model.render.io import to_device
from edmcgs.model.render.projection import LOWPASS, TILE

PACKAGE = "gsplat"
"""The distribution that brings it (``pip install edmcgs[cuda]``)."""


log = logging.getLogger(__name__)


@functools.cache
def available() -> bool:
    """Whether gsplat is installed (imported only when a CUDA render first needs it)."""
    return importlib.util.find_spec(PACKAGE) is not None


@functools.cache
def extension_error() -> str | None:
    """Why gsplat's CUDA extension cannot be used (None: it loads). The first call compiles it when
    gsplat's build cache does not hold it yet (minutes; nvcc needed), later calls are instant."""
    if not available():
        return "gsplat is not installed (pip install 'edmcgs[cuda]')"
    try:
        from gsplat.cuda import _backend
    except Exception as exc:  # a failed build raises anything from an OSError to a CalledProcessError
        return f"gsplat's CUDA extension failed to build or load: {type(exc).__name__}: {exc}"
    if getattr(_backend, "_C", None) is None:
        return "gsplat's CUDA extension could not be built (is nvcc, the CUDA compiler, on the PATH?)"
    return None


def usable() -> bool:
    """Whether gsplat renders here (``extension_error`` is None); logs why not, once."""
    error = extension_error()
    if error is not None and available():
        _warn_once(error)
    return error is None


@functools.cache
def _warn_once(error: str) -> None:
    log.warning("%s: CUDA renders use the torch rasterizer", error)


def camera(w2c: Tensor, intrinsics: Intrinsics) -> tuple[Tensor, Tensor]:
    """(viewmats [1, 4, 4], Ks [1, 3, 3]) of our camera in gsplat's conventions, on w2c's device and dtype."""
    return w2c[None].contiguous(), _ks(intrinsics, w2c.dtype, w2c.device)


@functools.lru_cache(maxsize=16)
def _ks(intrinsics: Intrinsics, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[1, 3, 3] intrinsics matrix, principal point at gsplat's pixel centres: made once per camera and
    device (a training step renders a few cameras thousands of times; gsplat only reads it)."""
    return to_device(torch.tensor([[[intrinsics.fx, 0.0, intrinsics.cx + 0.5],
                                    [0.0, intrinsics.fy, intrinsics.cy + 0.5],
                                    [0.0, 0.0, 1.0]]], dtype=dtype), device)


def composite_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, feat: Tensor,
                     w2c: Tensor, intrinsics: Intrinsics, near: float) -> tuple[Tensor, Tensor]:
    """Blend the Gaussians into one view on CUDA.

    means, quats, scales, opacities: as ``rasterize`` takes them (float32, CUDA)
    feat: Tensor  # [N, F] per-Gaussian features (colour channels, optionally camera z)
    returns (acc [H, W, F] = sum_i w_i f_i, transmittance [H, W]); differentiable in every input.
    """
    width, height = intrinsics.width, intrinsics.height
    if means.shape[0] == 0:
        return feat.new_zeros(height, width, feat.shape[1]), feat.new_ones(height, width)
    error = extension_error()
    if error is not None:
        raise RenderError(f"{error} (EDMCGS_RASTERIZER=torch renders without it)")
    from gsplat import rasterization

    viewmats, ks = camera(w2c, intrinsics)
    acc, alpha, _ = rasterization(means.contiguous(), quats.contiguous(), scales.contiguous(),
                                  opacities.contiguous(), feat.contiguous(), viewmats, ks, width, height,
                                  near_plane=near, far_plane=math.inf, eps2d=LOWPASS, sh_degree=None,
                                  packed=False, tile_size=TILE, render_mode="RGB", rasterize_mode="classic")
    return acc[0], 1.0 - alpha[0, ..., 0]

"""Differentiable 3D Gaussian splatting in PyTorch (any device): the training rasterizer.

The standard 3DGS pipeline: EWA projection with the 0.3 px^2 low-pass (``projection``), colour
from spherical harmonics seen from the camera centre (``sh``) or a plain colour, 16x16-tile
culling with a 3-sigma radius, and front-to-back blending of depth-sorted splats with alpha
clamped at 0.99, alpha < 1/255 skipped and a pixel stopping below transmittance 1e-4
(``composite``). Gaussians at depth <= ``near`` are culled.

Implementations of one contract: on the CPU numba kernels with analytic backwards (``project_fast``
for the projection and SH colour, ``composite_fast`` for the blending); on CUDA gsplat's kernels where
the ``cuda`` extra is installed (``rasterize_gsplat``, float32; its two small departures from the
contract are listed there); elsewhere torch (``projection``, ``sh``, ``composite``), which is also the
reference for the others. ``backend`` (or the ``EDMCGS_RASTERIZER`` environment variable: auto, torch,
numba, gsplat) forces one.
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import Tensor

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics
from edmcgs.model.render.composite import composite, make_plan
from edmcgs.model.render.composite_fast import KERNELS as _COMPOSITE_KERNELS
from edmcgs.model.render.composite_fast import composite_fast
from edmcgs.model.render.io import RenderOutput, check_inputs
from edmcgs.model.render.project_fast import KERNELS as _PROJECT_KERNELS
from edmcgs.model.render.project_fast import project_fast, sh_color_fast
from edmcgs.model.render.projection import NEAR, Splats, ewa_project, screen_rect
from edmcgs.model.render.rasterize_gsplat import available as gsplat_available
from edmcgs.model.render.rasterize_gsplat import composite_gsplat
from edmcgs.model.render.rasterize_gsplat import usable as gsplat_usable
from edmcgs.model.render.sh import sh_to_color

__all__ = ["BACKENDS", "RenderOutput", "rasterize"]

BACKENDS = ("auto", "torch", "numba", "gsplat")
"""Implementations: auto = numba for float32 / float64 on the CPU, gsplat for float32 on CUDA where it is
installed and its extension builds (else a logged warning, once), torch otherwise."""
BACKEND_ENV = "EDMCGS_RASTERIZER"


def backend_of(backend: str | None, means: Tensor) -> str:
    """The compositor to use: the argument, else the environment variable, else auto."""
    source = "backend"
    if backend is None:
        backend, source = os.environ.get(BACKEND_ENV, "auto").strip().lower() or "auto", BACKEND_ENV
    if backend not in BACKENDS:
        raise InvalidInputError(f"{source} must be one of {', '.join(BACKENDS)}, got {backend!r}")
    numba_ok = means.device.type == "cpu" and means.dtype in (torch.float32, torch.float64)
    gsplat_ok = means.device.type == "cuda" and means.dtype == torch.float32
    if backend == "auto":
        return "numba" if numba_ok else "gsplat" if gsplat_ok and gsplat_usable() else "torch"
    if backend == "numba" and not numba_ok:
        raise InvalidInputError(f"{source}=numba renders float32 or float64 tensors on the CPU, got "
                                f"{means.dtype} on {means.device}")
    if backend == "gsplat" and not (gsplat_ok and gsplat_available()):
        why = "gsplat is not installed (pip install 'edmcgs[cuda]')" if not gsplat_available() else \
            f"it renders float32 tensors on CUDA, got {means.dtype} on {means.device}"
        raise InvalidInputError(f"{source}=gsplat: {why}")
    return backend


def _colors(colors: Tensor, means: Tensor, w2c: Tensor) -> Tensor:
    """[M, C] colours: plain colours as given, SH evaluated towards each Gaussian."""
    if colors.ndim == 2:
        return colors
    centre = -(w2c[:3, :3].T @ w2c[:3, 3])
    return sh_to_color(colors, F.normalize(means - centre, dim=-1, eps=1e-12))


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, w2c,
              intrinsics: Intrinsics, *, background=None, near: float = NEAR, return_depth: bool = False,
              return_alpha: bool = False, backend: str | None = None) -> RenderOutput:
    """Render Gaussians into one view; differentiable w.r.t. means, quats, scales, opacities, colors.

    means: Tensor      # [N, 3] world positions
    quats: Tensor      # [N, 4] (w, x, y, z), any non-zero norm
    scales: Tensor     # [N, 3] linear standard deviations, >= 0
    opacities: Tensor  # [N] in [0, 1]
    colors: Tensor     # [N, C] plain colour (C = 3 RGB or 1 grey), or SH [N, K, C], K = (deg + 1)^2
    w2c: [4, 4] world-to-camera rigid transform (numpy or torch; not differentiated)
    intrinsics: the camera; the image is [intrinsics.height, intrinsics.width]
    background: None (black), a number, or C numbers; composited under the splats
    near: Gaussians with camera z <= near are culled
    backend: the compositor, one of BACKENDS (default: the EDMCGS_RASTERIZER variable, else auto)
    returns RenderOutput with torch tensors on the means' device: image [H, W, C], and
    alpha [H, W] / depth [H, W] (expected z) when asked for.
    All tensors share one float dtype and device. Raises InvalidInputError (naming the argument)
    on bad shapes, NaN/Inf, negative scales, opacities outside [0, 1] or a zero quaternion.
    """
    if not isinstance(means, torch.Tensor):
        raise InvalidInputError(f"means must be a torch.Tensor, got {type(means).__name__} "
                                "(rasterize_fast takes numpy arrays)")
    chk = check_inputs(means, quats, scales, opacities, colors, w2c, intrinsics, background, near)
    width, height = intrinsics.width, intrinsics.height
    backend = backend_of(backend, chk.means)
    if backend == "gsplat":
        return _rasterize_gsplat(chk, intrinsics, near, return_depth, return_alpha)
    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (chk.means, chk.quats, chk.scales, chk.opacities, chk.colors))

    if backend == "numba":  # one projection of every Gaussian; the culled ones get zero gradients
        w2c64 = chk.w2c.double().numpy()
        splats = Splats(*project_fast(chk.means, chk.quats, chk.scales, w2c64, intrinsics, near))
        with torch.no_grad():
            rect = screen_rect(splats, chk.opacities, width, height, near)
            visible = ((rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])).nonzero().squeeze(1)
    else:
        with torch.no_grad():  # cull on every Gaussian, then differentiate only the visible ones
            splats = ewa_project(chk.means, chk.quats, chk.scales, chk.w2c, intrinsics, near)
            rect = screen_rect(splats, chk.opacities, width, height, near)
            visible = ((rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])).nonzero().squeeze(1)

    def pick(t: Tensor) -> Tensor:  # index_select: far faster than boolean/advanced indexing on CPU
        return t.index_select(0, visible)

    rect, depth_key = pick(rect), pick(splats.depth).detach()
    v_means, v_opac = pick(chk.means), pick(chk.opacities)
    if backend == "numba":
        mean2d, conic, z = pick(splats.mean2d), pick(splats.conic), pick(splats.depth)
        colors = pick(chk.colors)
        feat = sh_color_fast(colors, v_means, w2c64) if colors.ndim == 3 else colors
    else:
        if need_grad:
            splats = ewa_project(v_means, pick(chk.quats), pick(chk.scales), chk.w2c, intrinsics, near)
            mean2d, conic, z = splats.mean2d, splats.conic, splats.depth
        else:
            mean2d, conic, z = pick(splats.mean2d), pick(splats.conic), depth_key
        feat = _colors(pick(chk.colors), v_means, chk.w2c)
    if return_depth:
        feat = torch.cat([feat, z[:, None]], dim=-1)

    attrs = torch.cat([mean2d, conic, v_opac[:, None]], dim=-1)
    if backend == "numba":
        acc, trans = composite_fast(attrs, feat, rect, depth_key, width, height)
    else:
        acc, trans = composite(attrs, feat, make_plan(rect, depth_key, width, height, dtype=means.dtype))

    return _output(chk, acc, trans, return_depth, return_alpha)


def _rasterize_gsplat(chk, intrinsics: Intrinsics, near: float, return_depth: bool,
                      return_alpha: bool) -> RenderOutput:
    """gsplat's compositing of every Gaussian (it culls on the device; its tile lists read one count back)."""
    feat = _colors(chk.colors, chk.means, chk.w2c)
    if return_depth:
        z = chk.means @ chk.w2c[2, :3] + chk.w2c[2, 3]
        feat = torch.cat([feat, z[:, None]], dim=-1)
    acc, trans = composite_gsplat(chk.means, chk.quats, chk.scales, chk.opacities, feat, chk.w2c, intrinsics,
                                  near)
    return _output(chk, acc, trans, return_depth, return_alpha)


def _output(chk, acc: Tensor, trans: Tensor, return_depth: bool, return_alpha: bool) -> RenderOutput:
    """The image over the background, alpha and depth from a compositor's (acc [H, W, F], T [H, W])."""
    c = chk.channels
    image = acc[..., :c] + trans[..., None] * chk.background
    alpha = 1.0 - trans
    depth = None
    if return_depth:
        covered = alpha > 0
        depth = torch.where(covered, acc[..., c] / torch.where(covered, alpha, torch.ones_like(alpha)),
                            torch.zeros_like(alpha))
    return RenderOutput(image=image, alpha=alpha if return_alpha else None, depth=depth)


KERNELS = _PROJECT_KERNELS + _COMPOSITE_KERNELS
"""The numba kernels of the differentiable path on the CPU (training, online corrections)."""
COMPILE_S = 30
"""About how long numba compiles ``KERNELS`` on a first run (2 shared cores: 30 to 33 s); ``edmcgs
warm-up`` (run by setup) compiles them into numba's cache beforehand."""

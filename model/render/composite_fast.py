"""Differentiable compositing on the CPU (numba): the forward and analytic backward of ``composite``.

The same contract as ``composite.composite``: (attrs [M, 6] = mean x, mean y, conic A, B, C,
opacity; feat [M, F]) -> (acc [H, W, F] = sum_i w_i f_i, T [H, W] = prod (1 - alpha_i)), with the
same splat lists (each splat on the pixels of its ``screen_rect``, depth order, ties by index), the
same alpha (min(ALPHA_MAX, opacity exp(power)), skipped below ALPHA_MIN) and the same stop rule
(a pixel stops before a splat that would leave it less than T_MIN), so its gradients are those of
the torch path.

Both kernels run over 16x16 tiles in parallel (``numba.prange``) and visit each splat's rectangle
in runs of 8 pixels with branch-free bodies that LLVM vectorises (all per-pixel state of a tile in
one array: with separate arrays LLVM cannot rule out aliasing and keeps the bodies scalar). The
forward keeps per pixel the feature sums, the final transmittance and how many list entries it went
through (the last taken one + 1, like gsplat's ``last_ids``). The backward replays the lists front
to back up to that count, so it takes exactly the splats the forward took (no stop decision is
re-made), and with w_i = alpha_i T_i, prefix_i = sum_{j <= i} w_j (g . f_j) and the incoming
gradients g of acc and g_T of T_N:
    dL / d f_i     = w_i g
    dL / d alpha_i = T_i (g . f_i) - (g . acc - prefix_i + g_T T_N) / (1 - alpha_i)
This is gsplat's back-to-front recurrence read forwards (the formula ``composite`` differentiates):
no division recovers T_i, the forward's acc stands in for the suffix sums. Per (tile, splat) the
pixel sums of dL/dpower times (1, dx, dy, dx^2, dx dy, dy^2) give the mean and conic gradients;
they are written to the splat's slot in the tile lists and summed per splat in float64 afterwards
(no atomics).

float32 inputs use ``simd_exp``; float64 inputs run the same kernels in float64 with ``math.exp``
(gradcheck and the exact comparison with the reference).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F
from numba.core import types
from numba.extending import overload
from torch import Tensor

from edmcgs.errors import InvalidInputError
from edmcgs.model.render.jit import in_torch_threads, njit_cached
from edmcgs.model.render.projection import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from edmcgs.model.render.simd_exp import exp_nonpositive
from edmcgs.model.render.tiles import all_stopped, bin_tiles, depth_order

__all__ = ["composite_fast"]

_PIX = TILE * TILE
_MOMENTS = 7
"""Per (tile, splat) sums: dL/dpower times 1, dx, dy, dx^2, dx dy, dy^2, and dL/dalpha exp(power)."""


def _exp_le0(x):
    """exp(min(x, 0)); numba picks the float32 SIMD version or math.exp by the argument's type."""
    return math.exp(min(x, 0.0))


@overload(_exp_le0, inline="always")
def _exp_le0_impl(x):
    if x == types.float32:
        return lambda x: exp_nonpositive(x)
    return lambda x: math.exp(min(x, 0.0))


@njit_cached(inline="always")
def _span(rect, g, ox, oy, tw, th):
    """The splat's rectangle in tile-local pixels, clipped to the tile, and the first x of its runs
    of 8: one run anywhere in the row when the span fits in it, else the two halves (pixels of a
    run outside the span are outside the ellipse where alpha can reach ALPHA_MIN: skipped)."""
    x0 = max(rect[g, 0] - ox, 0)
    x1 = min(rect[g, 2] - ox, tw)
    y0 = max(rect[g, 1] - oy, 0)
    y1 = min(rect[g, 3] - oy, th)
    first = min(x0, TILE - 8) if x1 - x0 <= 8 else 0
    return first, x1, y0, y1


@njit_cached(inline="always")
def _splat(attrs, feat, g, ox, oy, dt):
    """Splat g as both kernels read it: its mean in tile-local pixels, the exponent's coefficients
    (power = ca dx^2 + cb dx dy + cc dy^2), its opacity and its 4 features."""
    mx, my = dt(attrs[g, 0] - ox), dt(attrs[g, 1] - oy)
    ca, cb, cc = dt(-0.5) * attrs[g, 2], -attrs[g, 3], dt(-0.5) * attrs[g, 4]
    return mx, my, ca, cb, cc, attrs[g, 5], feat[g, 0], feat[g, 1], feat[g, 2], feat[g, 3]


# Per-tile state: one array per work item, so that LLVM sees no aliasing between the pixel rows
# the bodies read and write and vectorises them (separate arrays keep them scalar).
_CNT, _TOT, _PRE, _G = _PIX, 2 * _PIX, 3 * _PIX, 4 * _PIX  # backward rows after T; _G: 4 of them
_ROWS = 8 * _PIX
FEATURES = 4
"""Feature channels the kernels carry (colour 1 or 3, plus camera z); fewer are padded with 0."""


@njit_cached(parallel=True, nogil=True, fastmath={"contract"})
def _forward(start, ids, attrs, feat, rect, width, height, grid_x, dt, alpha_min, alpha_max, t_min,
             acc, trans, count):
    """Blend every tile's list front to back. Writes acc [H, W, 4], trans [H, W] and count [H, W]
    (int32: list entries of the pixel's tile it went through, up to its last taken one).
    State rows: transmittance (negative once the pixel stopped), count, then the 4 feature sums."""
    n_tiles = grid_x * ((height + TILE - 1) // TILE)
    one, zero = dt(1.0), dt(0.0)
    # one tile per work item, in raster order, handed out one at a time (as in ``rasterize_fast``)
    for t in numba.prange(n_tiles):
        st = np.empty(6 * _PIX, attrs.dtype)
        ox = (t % grid_x) * TILE
        oy = (t // grid_x) * TILE
        tw = min(TILE, width - ox)
        th = min(TILE, height - oy)
        st[:] = zero
        for p in range(_PIX):  # pixels outside the image start stopped
            st[p] = one if (p % TILE < tw and p // TILE < th) else -one
        for k in range(start[t], start[t + 1]):
            g = ids[k]
            first, x1, y0, y1 = _span(rect, g, ox, oy, tw, th)
            mx, my, ca, cb, cc, o, f0, f1, f2, f3 = _splat(attrs, feat, g, ox, oy, dt)
            seen = dt(k - start[t] + 1)
            for ly in range(y0, y1):
                dy = dt(ly) - my
                rowb, rowc = cb * dy, cc * dy * dy
                for hx in range(first, x1, 8):
                    p0 = np.uint64(ly * TILE + hx)
                    dx0 = dt(hx) - mx
                    for j in range(8):
                        p = p0 + np.uint64(j)
                        dx = dx0 + dt(j)
                        alpha = min(o * _exp_le0(dx * (ca * dx + rowb) + rowc), alpha_max)
                        tv = st[p]
                        t_next = tv * (one - alpha)
                        live = (alpha >= alpha_min) & (tv > zero)
                        take = live & (t_next >= t_min)
                        w = alpha * tv if take else zero
                        st[p] = t_next if take else (-tv if live else tv)
                        st[np.uint64(_PIX) + p] = seen if take else st[np.uint64(_PIX) + p]
                        st[np.uint64(2 * _PIX) + p] += w * f0
                        st[np.uint64(3 * _PIX) + p] += w * f1
                        st[np.uint64(4 * _PIX) + p] += w * f2
                        st[np.uint64(5 * _PIX) + p] += w * f3
            if (k - start[t]) % 16 == 15:  # every 16 splats: has every pixel stopped?
                if all_stopped(st):
                    break
        for ly in range(th):
            for lx in range(tw):
                p = ly * TILE + lx
                trans[oy + ly, ox + lx] = abs(st[p])
                count[oy + ly, ox + lx] = np.int32(st[_PIX + p])
                for ch in range(FEATURES):
                    acc[oy + ly, ox + lx, ch] = st[(2 + ch) * _PIX + p]


# reassoc: the per-splat sums over a run of 8 pixels become vector reductions
@njit_cached(parallel=True, nogil=True, fastmath={"contract", "reassoc"})
def _backward(start, ids, attrs, feat, rect, width, height, grid_x, dt, alpha_min, alpha_max,
              count, trans, acc, g_acc, g_trans, out):
    """Replay every tile's list front to back up to each pixel's count. Writes out [K, 6 + 4]: per
    list slot the gradient of the slot's splat's attrs (6) and features (4) from that tile's pixels.
    State rows: replayed transmittance, count, g . acc + g_T T_N, prefix, the 4 rows of g."""
    n_tiles = grid_x * ((height + TILE - 1) // TILE)
    one, zero = dt(1.0), dt(0.0)
    nsum = _MOMENTS + FEATURES
    u = np.uint64
    for t in numba.prange(n_tiles):
        st = np.empty(_ROWS, attrs.dtype)
        sums = np.empty(nsum, np.float64)
        ox = (t % grid_x) * TILE
        oy = (t // grid_x) * TILE
        tw = min(TILE, width - ox)
        th = min(TILE, height - oy)
        st[:] = zero
        st[:_CNT] = one
        last = 0
        for ly in range(th):
            for lx in range(tw):
                p = ly * TILE + lx
                y, x = oy + ly, ox + lx
                st[_CNT + p] = count[y, x]
                last = max(last, count[y, x])
                s = g_trans[y, x] * trans[y, x]
                for ch in range(FEATURES):
                    st[_G + ch * _PIX + p] = g_acc[y, x, ch]
                    s += g_acc[y, x, ch] * acc[y, x, ch]
                st[_TOT + p] = s
        for k in range(start[t] + last, start[t + 1]):  # entries no pixel of the tile took
            out[k, :] = 0.0
        for k in range(start[t], start[t] + last):
            g = ids[k]
            first, x1, y0, y1 = _span(rect, g, ox, oy, tw, th)
            mx, my, ca, cb, cc, o, f0, f1, f2, f3 = _splat(attrs, feat, g, ox, oy, dt)
            seen = dt(k - start[t])
            a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = zero
            for ly in range(y0, y1):
                dy = dt(ly) - my
                rowb, rowc = cb * dy, cc * dy * dy
                for hx in range(first, x1, 8):
                    p0 = u(ly * TILE + hx)
                    dx0 = dt(hx) - mx
                    for j in range(8):
                        p = p0 + u(j)
                        dx = dx0 + dt(j)
                        e = _exp_le0(dx * (ca * dx + rowb) + rowc)
                        raw = o * e
                        alpha = min(raw, alpha_max)
                        take = (alpha >= alpha_min) & (seen < st[u(_CNT) + p])
                        tv = st[p]
                        g0, g1 = st[u(_G) + p], st[u(_G + _PIX) + p]
                        g2, g3 = st[u(_G + 2 * _PIX) + p], st[u(_G + 3 * _PIX) + p]
                        gf = g0 * f0 + g1 * f1 + g2 * f2 + g3 * f3
                        w = alpha * tv if take else zero
                        pre = st[u(_PRE) + p] + w * gf
                        d_alpha = tv * gf - (st[u(_TOT) + p] - pre) / (one - alpha) if take else zero
                        d_raw = d_alpha if raw < alpha_max else zero  # no gradient through the clamp
                        d_pow = d_raw * alpha
                        st[p] = tv * (one - alpha) if take else tv
                        st[u(_PRE) + p] = pre
                        a0 += d_pow
                        a1 += d_pow * dx
                        a2 += d_pow * dy
                        a3 += d_pow * dx * dx
                        a4 += d_pow * dx * dy
                        a5 += d_pow * dy * dy
                        a6 += d_raw * e
                        a7 += w * g0
                        a8 += w * g1
                        a9 += w * g2
                        a10 += w * g3
            sums[0], sums[1], sums[2], sums[3], sums[4], sums[5] = a0, a1, a2, a3, a4, a5
            sums[6], sums[7], sums[8], sums[9], sums[10] = a6, a7, a8, a9, a10
            # power = -(A dx^2 + 2 B dx dy + C dy^2) / 2 with dx = pixel x - mean x
            a, b, c = attrs[g, 2], attrs[g, 3], attrs[g, 4]
            out[k, 0] = a * sums[1] + b * sums[2]
            out[k, 1] = c * sums[2] + b * sums[1]
            out[k, 2] = -0.5 * sums[3]
            out[k, 3] = -sums[4]
            out[k, 4] = -0.5 * sums[5]
            out[k, 5] = sums[6]
            for ch in range(FEATURES):
                out[k, 6 + ch] = sums[_MOMENTS + ch]


@njit_cached(nogil=True)
def _gather(ids, slots, splats):
    """Sum the per-slot gradients [K, D] of each splat -> [splats, D] (float64)."""
    grad = np.zeros((splats, slots.shape[1]), np.float64)
    for k in range(ids.shape[0]):
        g = ids[k]
        for d in range(slots.shape[1]):
            grad[g, d] += slots[k, d]
    return grad


class _Tiles:
    """The tile lists of one render and what both kernels take besides the tensors."""

    def __init__(self, rect: Tensor, depth: Tensor, width: int, height: int, dtype: torch.dtype):
        self.width, self.height = width, height
        self.grid_x = -(-width // TILE)
        grid_y = -(-height // TILE)
        self.rect = np.ascontiguousarray(rect.numpy())
        if depth.dtype == torch.float32:  # the radix sort of the float32 bits: the same order, faster
            order = depth_order(self.rect, depth.detach().contiguous().numpy().view(np.uint32))
        else:
            order = torch.sort(depth.detach(), stable=True).indices.numpy()
        self.start, self.ids = bin_tiles(self.rect, order, self.grid_x, grid_y)
        self.dt = np.float64 if dtype == torch.float64 else np.float32
        # the thresholds as the torch path compares them: in the tensors' dtype
        self.alpha_min, self.alpha_max = self.dt(ALPHA_MIN), self.dt(ALPHA_MAX)
        self.t_min = self.dt(T_MIN)


class CompositeFast(torch.autograd.Function):
    """(attrs [M, 6], feat [M, F], tiles) -> (acc [H, W, F], T [H, W]); see the module docstring."""

    @staticmethod
    def forward(ctx, attrs: Tensor, feat: Tensor, tiles: _Tiles):
        nf = feat.shape[1]
        a = attrs.detach().contiguous().numpy()
        f = F.pad(feat.detach(), (0, FEATURES - nf)).contiguous().numpy()
        h, w = tiles.height, tiles.width
        acc = np.zeros((h, w, FEATURES), a.dtype)
        trans = np.ones((h, w), a.dtype)
        count = np.zeros((h, w), np.int32)
        in_torch_threads(_forward, tiles.start, tiles.ids, a, f, tiles.rect, w, h, tiles.grid_x, tiles.dt,
                         tiles.alpha_min, tiles.alpha_max, tiles.t_min, acc, trans, count, chunksize=1)
        acc_t, trans_t = torch.from_numpy(acc), torch.from_numpy(trans)
        ctx.save_for_backward(attrs, feat, acc_t, trans_t, torch.from_numpy(count))
        ctx.tiles = tiles
        return acc_t[..., :nf].clone(), trans_t.clone()

    @staticmethod
    def backward(ctx, g_acc: Tensor, g_trans: Tensor):
        attrs, feat, acc, trans, count = ctx.saved_tensors
        tiles = ctx.tiles
        nf = feat.shape[1]
        a = attrs.detach().contiguous().numpy()
        f = F.pad(feat.detach(), (0, FEATURES - nf)).contiguous().numpy()
        g_acc = F.pad(g_acc.to(attrs.dtype), (0, FEATURES - nf)).contiguous().numpy()
        slots = np.empty((tiles.ids.shape[0], 6 + FEATURES), a.dtype)
        in_torch_threads(_backward, tiles.start, tiles.ids, a, f, tiles.rect, tiles.width, tiles.height,
                         tiles.grid_x, tiles.dt, tiles.alpha_min, tiles.alpha_max, count.numpy(),
                         trans.numpy(), acc.numpy(), g_acc, g_trans.to(attrs.dtype).contiguous().numpy(),
                         slots, chunksize=1)
        grad = torch.from_numpy(_gather(tiles.ids, slots, a.shape[0])).to(attrs.dtype)
        return grad[:, :6], grad[:, 6:6 + nf], None


def composite_fast(attrs: Tensor, feat: Tensor, rect: Tensor, depth: Tensor, width: int,
                   height: int) -> tuple[Tensor, Tensor]:
    """Blend splats front to back on the CPU; differentiable w.r.t. attrs and feat.

    attrs: Tensor  # [M, 6] (mean x, mean y, conic A, B, C, opacity), float32 or float64, CPU
    feat: Tensor   # [M, F] per-splat features, same dtype
    rect: Tensor   # [M, 4] int64 pixel rectangles (x0, y0, x1, y1) from ``screen_rect``
    depth: Tensor  # [M] the sort key (camera z); ties keep index order
    returns (acc [H, W, F], transmittance [H, W]) like ``composite.composite``.
    """
    if feat.ndim != 2 or feat.shape[1] > FEATURES:
        raise InvalidInputError(f"feat must be [M, F] with F <= {FEATURES}, got {tuple(feat.shape)}")
    tiles = _Tiles(rect, depth, width, height, attrs.dtype)
    return CompositeFast.apply(attrs, feat, tiles)


KERNELS = (_forward, _backward)
"""The compositor's kernels a training step compiles on first use (``jit.compiled``)."""

"""Differentiable compositing on the CPU (numba): the forward and analytic backward of ``composite``.

The same contract as ``composite.composite``: (attrs [M, 6] = mean x, mean y, conic A, B, C,
opacity; feat [M, F]) -> (acc [H, W, F] = sum_i w_i f_i, T [H, W] = prod (1 - alpha_i)), with the
same splat lists (each splat on the pixels of its ``screen_rect``, depth order, ties by index), the
same alpha (min(ALPHA_MAX, opacity exp(power)), skipped below ALPHA_MIN) and the same stop rule
(a pixel stops before a splat that would leave it less than T_MIN), so its gradients are those of
the torch path.

Both kernels run over 16x16 tiles in parallel (``numba.prange``) and visit each splat's rectangle
in runs of 8 pixels with branch-free bodies that LLVM vectorises. The forward keeps per pixel the
float64 colour sum, the final transmittance and how many list entries it went through (the last
taken one + 1, like gsplat's ``last_ids``). The backward replays the lists front to back up to that
count, so it takes exactly the splats the forward took (no stop decision is re-made), and with
w_i = alpha_i T_i, prefix_i = sum_{j <= i} w_j (g . f_j) (float64) and the incoming gradients
g of acc and g_T of T_N:
    dL / d f_i     = w_i g
    dL / d alpha_i = T_i (g . f_i) - (g . acc - prefix_i + g_T T_N) / (1 - alpha_i)
This is gsplat's back-to-front recurrence read forwards: it needs no division to recover T_i (the
forward's float64 acc stands in for the suffix sums). Per (tile, splat) the pixel sums of
dL/dpower times (1, dx, dy, dx^2, dx dy, dy^2) give the mean and conic gradients; they are written
to the splat's slot in the tile lists and summed per splat afterwards (no atomics).

float32 inputs use ``simd_exp``; float64 inputs run the same kernels in float64 with ``math.exp``
(gradcheck and the exact comparison with the reference).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba.core import types
from numba.extending import overload
from torch import Tensor

from edmcgs.model.render.jit import njit_cached
from edmcgs.model.render.projection import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from edmcgs.model.render.simd_exp import exp_nonpositive

__all__ = ["composite_fast"]

_PIX = TILE * TILE
_WORK_ITEMS = 128
"""Tiles are dealt round-robin to this many parallel work items, handed to threads one at a time
(as in ``rasterize_fast``): busy regions are shared and a preempted thread holds up one item only."""
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


@njit_cached()
def _bin(rect, order, grid_x, grid_y):
    """Tile lists: ids[start[t]:start[t + 1]] are the splats (taken in ``order``) whose rectangle
    touches tile t."""
    start = np.zeros(grid_x * grid_y + 1, np.int64)
    for g in order:
        if rect[g, 2] <= rect[g, 0] or rect[g, 3] <= rect[g, 1]:
            continue
        for ty in range(rect[g, 1] // TILE, (rect[g, 3] - 1) // TILE + 1):
            for tx in range(rect[g, 0] // TILE, (rect[g, 2] - 1) // TILE + 1):
                start[ty * grid_x + tx + 1] += 1
    for t in range(grid_x * grid_y):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    ids = np.empty(start[-1], np.int32)
    for g in order:
        if rect[g, 2] <= rect[g, 0] or rect[g, 3] <= rect[g, 1]:
            continue
        for ty in range(rect[g, 1] // TILE, (rect[g, 3] - 1) // TILE + 1):
            for tx in range(rect[g, 0] // TILE, (rect[g, 2] - 1) // TILE + 1):
                t = ty * grid_x + tx
                ids[fill[t]] = g
                fill[t] += 1
    return start, ids


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


@njit_cached(parallel=True, fastmath={"contract"})
def _forward(start, ids, attrs, feat, rect, width, height, grid_x, dt, alpha_min, alpha_max, t_min,
             acc, trans, count):
    """Blend every tile's list front to back. Writes acc [H, W, F] (float64), trans [H, W] and
    count [H, W] (int32: list entries of the pixel's tile it went through, up to its last taken)."""
    nf = feat.shape[1]
    n_tiles = grid_x * ((height + TILE - 1) // TILE)
    one, zero = dt(1.0), dt(0.0)
    for item in numba.prange(_WORK_ITEMS):
        tr = np.empty(_PIX, attrs.dtype)    # transmittance; negative once the pixel stopped
        sums = np.empty(nf * _PIX, np.float64)
        cnt = np.empty(_PIX, np.int32)
        w = np.empty(8, attrs.dtype)
        coord = np.empty(TILE, attrs.dtype)
        for i in range(TILE):
            coord[i] = i
        for t in range(item, n_tiles, _WORK_ITEMS):
            ox = (t % grid_x) * TILE
            oy = (t // grid_x) * TILE
            tw = min(TILE, width - ox)
            th = min(TILE, height - oy)
            sums[:] = 0.0
            cnt[:] = 0
            for p in range(_PIX):  # pixels outside the image start stopped
                tr[p] = one if (p % TILE < tw and p // TILE < th) else -one
            for k in range(start[t], start[t + 1]):
                g = ids[k]
                first, x1, y0, y1 = _span(rect, g, ox, oy, tw, th)
                mx, my = dt(attrs[g, 0] - ox), dt(attrs[g, 1] - oy)
                ca, cb, cc = dt(-0.5) * attrs[g, 2], -attrs[g, 3], dt(-0.5) * attrs[g, 4]
                o = attrs[g, 5]
                seen = np.int32(k - start[t] + 1)
                for ly in range(y0, y1):
                    dy = coord[ly] - my
                    rowb, rowc = cb * dy, cc * dy * dy
                    for hx in range(first, x1, 8):
                        p0 = np.uint64(ly * TILE + hx)
                        for j in range(8):
                            p = p0 + np.uint64(j)
                            dx = coord[hx + j] - mx
                            alpha = min(o * _exp_le0(dx * (ca * dx + rowb) + rowc), alpha_max)
                            tv = tr[p]
                            t_next = tv * (one - alpha)
                            live = (alpha >= alpha_min) & (tv > zero)
                            take = live & (t_next >= t_min)
                            w[j] = alpha * tv if take else zero
                            tr[p] = t_next if take else (-tv if live else tv)
                            cnt[p] = seen if take else cnt[p]
                        for ch in range(nf):
                            f = np.float64(feat[g, ch])
                            base = np.uint64(ch * _PIX) + p0
                            for j in range(8):
                                sums[base + np.uint64(j)] += w[j] * f
                if (k - start[t]) % 16 == 15:  # every 16 splats: has every pixel stopped?
                    most = -one
                    for p in range(_PIX):
                        most = max(most, tr[p])
                    if most <= zero:
                        break
            for ly in range(th):
                for lx in range(tw):
                    p = ly * TILE + lx
                    trans[oy + ly, ox + lx] = abs(tr[p])
                    count[oy + ly, ox + lx] = cnt[p]
                    for ch in range(nf):
                        acc[oy + ly, ox + lx, ch] = sums[ch * _PIX + p]


@njit_cached(parallel=True, fastmath={"contract"})
def _backward(start, ids, attrs, feat, rect, width, height, grid_x, dt, alpha_min, alpha_max,
              count, trans, acc, g_acc, g_trans, out):
    """Replay every tile's list front to back up to each pixel's count. Writes out [K, 6 + F]: per
    list slot the gradient of the slot's splat's attrs (6) and feat (F) from that tile's pixels."""
    nf = feat.shape[1]
    n_tiles = grid_x * ((height + TILE - 1) // TILE)
    one, zero = dt(1.0), dt(0.0)
    for item in numba.prange(_WORK_ITEMS):
        tr = np.empty(_PIX, attrs.dtype)
        prefix = np.empty(_PIX, np.float64)
        total = np.empty(_PIX, np.float64)  # g . acc + g_T T_N
        cnt = np.empty(_PIX, np.int32)
        gg = np.empty(nf * _PIX, attrs.dtype)
        lanes = np.empty((_MOMENTS + nf) * 8, attrs.dtype)
        gf = np.empty(8, attrs.dtype)
        wb = np.empty(8, attrs.dtype)
        sums = np.empty(_MOMENTS + nf, np.float64)
        coord = np.empty(TILE, attrs.dtype)
        for i in range(TILE):
            coord[i] = i
        for t in range(item, n_tiles, _WORK_ITEMS):
            ox = (t % grid_x) * TILE
            oy = (t // grid_x) * TILE
            tw = min(TILE, width - ox)
            th = min(TILE, height - oy)
            tr[:] = one
            prefix[:] = 0.0
            total[:] = 0.0
            cnt[:] = 0
            gg[:] = zero
            last = 0
            for ly in range(th):
                for lx in range(tw):
                    p = ly * TILE + lx
                    y, x = oy + ly, ox + lx
                    cnt[p] = count[y, x]
                    last = max(last, count[y, x])
                    s = np.float64(g_trans[y, x]) * np.float64(trans[y, x])
                    for ch in range(nf):
                        gg[ch * _PIX + p] = g_acc[y, x, ch]
                        s += np.float64(g_acc[y, x, ch]) * acc[y, x, ch]
                    total[p] = s
            for k in range(start[t] + last, start[t + 1]):  # entries no pixel of the tile took
                out[k, :] = 0.0
            for k in range(start[t], start[t] + last):
                g = ids[k]
                first, x1, y0, y1 = _span(rect, g, ox, oy, tw, th)
                mx, my = dt(attrs[g, 0] - ox), dt(attrs[g, 1] - oy)
                ca, cb, cc = dt(-0.5) * attrs[g, 2], -attrs[g, 3], dt(-0.5) * attrs[g, 4]
                o = attrs[g, 5]
                seen = np.int32(k - start[t])
                lanes[:] = zero
                for ly in range(y0, y1):
                    dy = coord[ly] - my
                    rowb, rowc = cb * dy, cc * dy * dy
                    for hx in range(first, x1, 8):
                        p0 = np.uint64(ly * TILE + hx)
                        for j in range(8):
                            gf[j] = zero
                        for ch in range(nf):
                            f = feat[g, ch]
                            base = np.uint64(ch * _PIX) + p0
                            for j in range(8):
                                gf[j] += gg[base + np.uint64(j)] * f
                        for j in range(8):
                            p = p0 + np.uint64(j)
                            dx = coord[hx + j] - mx
                            e = _exp_le0(dx * (ca * dx + rowb) + rowc)
                            raw = o * e
                            alpha = min(raw, alpha_max)
                            take = (alpha >= alpha_min) & (seen < cnt[p])
                            tv = tr[p]
                            w = alpha * tv if take else zero
                            pre = prefix[p] + np.float64(w * gf[j])
                            after = dt(total[p] - pre)
                            d_alpha = tv * gf[j] - after / (one - alpha) if take else zero
                            d_raw = d_alpha if raw < alpha_max else zero  # no gradient through the clamp
                            d_pow = d_raw * alpha
                            tr[p] = tv * (one - alpha) if take else tv
                            prefix[p] = pre
                            wb[j] = w
                            lanes[j] += d_pow
                            lanes[8 + j] += d_pow * dx
                            lanes[16 + j] += d_pow * dy
                            lanes[24 + j] += d_pow * dx * dx
                            lanes[32 + j] += d_pow * dx * dy
                            lanes[40 + j] += d_pow * dy * dy
                            lanes[48 + j] += d_raw * e
                        for ch in range(nf):
                            base = np.uint64(ch * _PIX) + p0
                            lane = np.uint64((_MOMENTS + ch) * 8)
                            for j in range(8):
                                lanes[lane + np.uint64(j)] += wb[j] * gg[base + np.uint64(j)]
                sums[:] = 0.0
                for m in range(_MOMENTS + nf):
                    for j in range(8):
                        sums[m] += lanes[m * 8 + j]
                # power = -(A dx^2 + 2 B dx dy + C dy^2) / 2 with dx = pixel x - mean x
                a, b, c = attrs[g, 2], attrs[g, 3], attrs[g, 4]
                out[k, 0] = a * sums[1] + b * sums[2]
                out[k, 1] = c * sums[2] + b * sums[1]
                out[k, 2] = -0.5 * sums[3]
                out[k, 3] = -sums[4]
                out[k, 4] = -0.5 * sums[5]
                out[k, 5] = sums[6]
                for ch in range(nf):
                    out[k, 6 + ch] = sums[_MOMENTS + ch]


@njit_cached()
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
        order = torch.sort(depth.detach(), stable=True).indices.numpy()
        self.rect = np.ascontiguousarray(rect.numpy())
        self.start, self.ids = _bin(self.rect, order, self.grid_x, grid_y)
        self.dt = np.float64 if dtype == torch.float64 else np.float32
        # the thresholds as the torch path compares them: in the tensors' dtype
        self.alpha_min, self.alpha_max = self.dt(ALPHA_MIN), self.dt(ALPHA_MAX)
        self.t_min = self.dt(T_MIN)


def _in_threads(kernel, *args):
    """Run a parallel kernel on torch's thread count (the trainer's ``--threads``), one work item at
    a time; numba's OpenMP layer shares the process-wide OpenMP thread count with torch, so torch's
    is put back afterwards."""
    threads = torch.get_num_threads()
    previous_chunk = numba.set_parallel_chunksize(1)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
        kernel(*args)
    finally:
        numba.set_parallel_chunksize(previous_chunk)
        numba.set_num_threads(previous)
        torch.set_num_threads(threads)


class CompositeFast(torch.autograd.Function):
    """(attrs [M, 6], feat [M, F], tiles) -> (acc [H, W, F], T [H, W]); see the module docstring."""

    @staticmethod
    def forward(ctx, attrs: Tensor, feat: Tensor, tiles: _Tiles):
        a = attrs.detach().contiguous().numpy()
        f = feat.detach().contiguous().numpy()
        h, w, nf = tiles.height, tiles.width, f.shape[1]
        acc = np.zeros((h, w, nf), np.float64)
        trans = np.ones((h, w), a.dtype)
        count = np.zeros((h, w), np.int32)
        _in_threads(_forward, tiles.start, tiles.ids, a, f, tiles.rect, w, h, tiles.grid_x, tiles.dt,
                    tiles.alpha_min, tiles.alpha_max, tiles.t_min, acc, trans, count)
        acc64 = torch.from_numpy(acc)
        trans_t = torch.from_numpy(trans)
        ctx.save_for_backward(attrs, feat, acc64, trans_t, torch.from_numpy(count))
        ctx.tiles = tiles
        return acc64.to(attrs.dtype), trans_t.clone()

    @staticmethod
    def backward(ctx, g_acc: Tensor, g_trans: Tensor):
        attrs, feat, acc64, trans, count = ctx.saved_tensors
        tiles = ctx.tiles
        a, f = attrs.detach().contiguous().numpy(), feat.detach().contiguous().numpy()
        nf = f.shape[1]
        slots = np.empty((tiles.ids.shape[0], 6 + nf), a.dtype)
        _in_threads(_backward, tiles.start, tiles.ids, a, f, tiles.rect, tiles.width, tiles.height,
                    tiles.grid_x, tiles.dt, tiles.alpha_min, tiles.alpha_max, count.numpy(), trans.numpy(),
                    acc64.numpy(), g_acc.to(attrs.dtype).contiguous().numpy(),
                    g_trans.to(attrs.dtype).contiguous().numpy(), slots)
        grad = torch.from_numpy(_gather(tiles.ids, slots, a.shape[0])).to(attrs.dtype)
        return grad[:, :6], grad[:, 6:], None


def composite_fast(attrs: Tensor, feat: Tensor, rect: Tensor, depth: Tensor, width: int,
                   height: int) -> tuple[Tensor, Tensor]:
    """Blend splats front to back on the CPU; differentiable w.r.t. attrs and feat.

    attrs: Tensor  # [M, 6] (mean x, mean y, conic A, B, C, opacity), float32 or float64, CPU
    feat: Tensor   # [M, F] per-splat features, same dtype
    rect: Tensor   # [M, 4] int64 pixel rectangles (x0, y0, x1, y1) from ``screen_rect``
    depth: Tensor  # [M] the sort key (camera z); ties keep index order
    returns (acc [H, W, F], transmittance [H, W]) like ``composite.composite``.
    """
    tiles = _Tiles(rect, depth, width, height, attrs.dtype)
    return CompositeFast.apply(attrs, feat, tiles)

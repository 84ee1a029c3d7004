"""Differentiable front-to-back alpha compositing of screen-space Gaussians, in torch ops only.

The image is cut into small square pixel blocks; each block gets the depth-sorted list of splats
whose pixel rectangle (``projection.screen_rect``) touches it. Blocks are grouped with blocks of
similar list length and consumed in rounds: a round evaluates the next ``C`` splats of each block
of a group densely as [blocks, pixels, C] tensors and carries every pixel's transmittance to the
next round. Rounds hold at most ROUND_ELEMENTS elements: memory stays bounded and the tensors stay
in cache.

Per (block, splat) pair the Gaussian exponent is a quadratic in the block-local pixel coordinates,
so it is one small matmul with the basis (1, x, y, x^2, xy, y^2); the backward reduces over pixels
with the same basis (moments), and masks are built from float ops (threshold, sign), which torch
runs far faster on the CPU than boolean ones.

``Composite`` is an autograd Function with an analytic backward: the forward keeps only per-pixel
results, the backward replays the same rounds (same ops, so the same skip and stop decisions).
With w_i = alpha_i T_i, acc = sum w_i f_i and T_N = prod (1 - alpha_i) over the splats a pixel took:
    d acc / d f_i = w_i
    dL / d alpha_i = T_i (g . f_i) - (g . (acc - prefix_i) + g_T T_N) / (1 - alpha_i)
where prefix_i = sum_{j <= i} w_j f_j and g, g_T are the incoming gradients of acc and T_N.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from edmcgs.model.render.projection import ALPHA_MAX, ALPHA_MIN, T_MIN

BLOCK = 4
"""Compositing block edge (px). Any size gives the same image (the splat lists come from the
16x16-tile rule); small blocks keep the dense work close to the splats' real footprints."""
ROUND_ELEMENTS = 1 << 16
"""Upper bound of blocks x pixels x splats evaluated at once: bounds memory (~20 such tensors
live in the backward) and keeps them in the CPU's L2 cache."""


@dataclass
class Plan:
    """Which splats every block takes, in depth order, and how the lists are cut into rounds.

    Blocks with splats are processed in ``order`` (longest list first), so a round's blocks are the
    contiguous rows [row, row + rows) of the per-block state, and its (block, splat) slots the
    contiguous range [slot, slot + rows * chunk) of the slot arrays: no gathers inside the loop.
    """

    width: int
    height: int
    block: int
    splats: int         # M, the number of splats
    order: Tensor       # [B'] int64 the blocks that have splats, in processing order
    slot_gid: Tensor    # [S] int64 splat in each slot; M for padding
    slot_centre: Tensor  # [S, 2] pixel coordinates of the centre of each slot's block
    rounds: list        # [(row, rows, slot, chunk)]
    basis: Tensor       # [block^2, 6] (1, x, y, x^2, xy, y^2) of the pixels about the block centre
    blocks: int         # B, blocks in the image

    @property
    def blocks_x(self) -> int:
        return -(-self.width // self.block)

    @property
    def blocks_y(self) -> int:
        return -(-self.height // self.block)

    @property
    def pixels(self) -> int:
        return self.block * self.block


def _schedule(start: Tensor, count: Tensor, pixels: int):
    """Order blocks by list length, group similar ones and cut each group's lists into rounds of at
    most ROUND_ELEMENTS elements. Returns (order, slot_pair, rounds) as described in Plan."""
    counts = count.cpu()
    order = torch.sort(counts, descending=True, stable=True).indices
    order = order[counts[order] > 0]
    starts = start.cpu()[order]
    lengths = counts[order]
    total = int(counts.sum())
    rounds, slots = [], []
    row, slot = 0, 0
    n_rows = order.numel()
    while row < n_rows:
        longest = int(lengths[row])
        chunk = max(1, min(longest, ROUND_ELEMENTS // pixels))
        size = min(max(1, ROUND_ELEMENTS // (pixels * chunk)), n_rows - row)
        first = starts[row:row + size, None]
        end = first + lengths[row:row + size, None]
        for offset in range(0, longest, chunk):
            rows = int((lengths[row:row + size] > offset).sum())  # sorted: the active ones lead
            pos = first[:rows] + offset + torch.arange(chunk)
            slots.append(torch.where(pos < end[:rows], pos, total).reshape(-1))
            rounds.append((row, rows, slot, chunk))
            slot += rows * chunk
        row += size
    slot_pair = torch.cat(slots) if slots else torch.zeros(0, dtype=torch.long)
    return order.to(count.device), slot_pair.to(count.device), rounds


def make_plan(rect: Tensor, depth: Tensor, width: int, height: int, block: int | None = None,
              dtype: torch.dtype = torch.float32) -> Plan:
    """Bin splats into blocks.

    rect: Tensor   # [M, 4] int64 pixel rectangles (x0, y0, x1, y1), half-open; may be empty
    depth: Tensor  # [M] camera z; lists are sorted by it, ties by index (stable)
    """
    block = BLOCK if block is None else block
    device = rect.device
    bx_n, by_n = -(-width // block), -(-height // block)
    with torch.no_grad():
        x0, y0, x1, y1 = rect.unbind(-1)
        bx0, by0 = x0 // block, y0 // block
        nx = ((x1 + block - 1) // block - bx0).clamp_min(0) * (x1 > x0)
        ny = ((y1 + block - 1) // block - by0).clamp_min(0) * (y1 > y0)
        order = torch.sort(depth, stable=True).indices
        per = (nx * ny)[order]
        total = int(per.sum())
        gid = torch.repeat_interleave(order, per, output_size=total)
        first = torch.cumsum(per, 0) - per
        local = torch.arange(total, device=device) - torch.repeat_interleave(first, per, output_size=total)
        nxg = nx[gid]
        block_id = (by0[gid] + local // nxg) * bx_n + bx0[gid] + local % nxg
        block_id, perm = torch.sort(block_id, stable=True)
        gid = gid[perm]
        count = torch.bincount(block_id, minlength=bx_n * by_n)
        start = torch.cumsum(count, 0) - count
        half = (block - 1) / 2.0
        iy, ix = torch.meshgrid(torch.arange(block, device=device, dtype=dtype) - half,
                                torch.arange(block, device=device, dtype=dtype) - half, indexing="ij")
        ix, iy = ix.reshape(-1), iy.reshape(-1)
        basis = torch.stack([torch.ones_like(ix), ix, iy, ix * ix, ix * iy, iy * iy], dim=-1)
        order, slot_pair, rounds = _schedule(start, count, block * block)
        pad = torch.tensor([rect.shape[0]], device=device)
        slot_gid = torch.cat([gid, pad]).index_select(0, slot_pair)
        slot_block = torch.cat([block_id, pad * 0]).index_select(0, slot_pair)
        slot_centre = torch.stack([(slot_block % bx_n) * block + half, (slot_block // bx_n) * block + half],
                                  dim=-1).to(dtype)
    return Plan(width, height, block, rect.shape[0], order, slot_gid, slot_centre, rounds, basis, bx_n * by_n)


def _below(value: float, dtype: torch.dtype) -> float:
    """The largest number of ``dtype`` below ``value``: F.threshold keeps x > it, i.e. x >= value."""
    v = torch.tensor(value, dtype=dtype)
    return float(torch.nextafter(v, torch.zeros_like(v)))


class _Round:
    """The dense tensors of one round, shared by the forward and its replay in the backward.

    coef: [rows, C, 6] exponent coefficients; op: [rows, C] opacities; t_in: [rows, P, 1] incoming
    transmittance (0 for pixels that have stopped).
    """

    def __init__(self, basis: Tensor, coef: Tensor, op: Tensor, t_in: Tensor, thresholds):
        alpha_min, t_min = thresholds
        raw = torch.matmul(basis, coef.transpose(1, 2)).exp_().mul_(op[:, None, :])  # [rows, P, C]
        self.alpha = F.threshold(raw.clamp_max_(ALPHA_MAX), alpha_min, 0.0)  # skip alpha < ALPHA_MIN
        self.one_minus = 1.0 - self.alpha
        cp = torch.cumprod(self.one_minus, dim=-1)
        # keep: the pixel still takes the splat (T after it >= T_MIN); 1.0 / 0.0
        self.keep = F.threshold(cp * t_in, t_min, 0.0).sign_()
        self.t_before = torch.cat([torch.ones_like(cp[..., :1]), cp[..., :-1]], dim=-1).mul_(t_in)
        self.w = self.alpha * self.keep * self.t_before
        self.t_last = cp[..., -1] * t_in[..., 0]


def _slot_terms(plan: Plan, attrs: Tensor, feat: Tensor):
    """Exponent coefficients [S, 6], opacities [S] and features [S, F] slot by slot (padding gets
    opacity 0, so alpha 0 and skipped), and each slot's mean relative to its block centre [S, 2]."""
    a = torch.cat([attrs, attrs.new_zeros(1, 6)]).index_select(0, plan.slot_gid)
    rel = a[:, :2] - plan.slot_centre
    rx, ry = rel.unbind(-1)
    ca, cb, cc = a[:, 2], a[:, 3], a[:, 4]
    k1 = ca * rx + cb * ry
    k2 = cc * ry + cb * rx
    k0 = -0.5 * (rx * k1 + ry * k2)
    coef = torch.stack([k0, k1, k2, -0.5 * ca, -cb, -0.5 * cc], dim=-1)
    sfeat = torch.cat([feat, feat.new_zeros(1, feat.shape[1])]).index_select(0, plan.slot_gid)
    return coef, a[:, 5].contiguous(), sfeat, rel, a


def _thresholds(dtype: torch.dtype):
    return _below(ALPHA_MIN, dtype), _below(T_MIN, dtype)


def _forward(plan: Plan, attrs: Tensor, feat: Tensor):
    rows_all = plan.order.numel()
    thresholds = _thresholds(attrs.dtype)
    coef, op, pfeat, _, _ = _slot_terms(plan, attrs, feat)
    acc = feat.new_zeros(rows_all, plan.pixels, feat.shape[1])
    trans = feat.new_ones(rows_all, plan.pixels)
    alive = feat.new_ones(rows_all, plan.pixels)
    for row, rows, slot, chunk in plan.rounds:
        sl, ss = slice(row, row + rows), slice(slot, slot + rows * chunk)
        r = _Round(plan.basis, coef[ss].view(rows, chunk, 6), op[ss].view(rows, chunk),
                   (trans[sl] * alive[sl])[..., None], thresholds)
        acc[sl] += torch.bmm(r.w, pfeat[ss].view(rows, chunk, -1))
        trans[sl] -= r.w.sum(-1)
        alive[sl] = (r.t_last >= T_MIN).to(alive.dtype)
    acc_all = feat.new_zeros(plan.blocks, plan.pixels, feat.shape[1]).index_copy_(0, plan.order, acc)
    trans_all = feat.new_ones(plan.blocks, plan.pixels).index_copy_(0, plan.order, trans)
    return acc_all, trans_all


def _backward(plan: Plan, attrs: Tensor, feat: Tensor, acc: Tensor, trans: Tensor, g_acc: Tensor,
              g_trans: Tensor):
    rows_all, nslots = plan.order.numel(), plan.slot_gid.numel()
    thresholds = _thresholds(attrs.dtype)
    clamp_edge = -float(torch.tensor(ALPHA_MAX, dtype=attrs.dtype))  # -alpha > it <=> alpha < ALPHA_MAX
    coef, op, sfeat, rel, sattrs = _slot_terms(plan, attrs, feat)
    g_acc = g_acc.index_select(0, plan.order)
    total = ((g_acc * acc.index_select(0, plan.order)).sum(-1)        # g . acc + g_T T_N
             + (g_trans * trans).index_select(0, plan.order))
    moments = attrs.new_empty(nslots, 6)                  # per slot: sum_p dL/dpower * basis
    g_sfeat = feat.new_empty(nslots, feat.shape[1])
    run_t = feat.new_ones(rows_all, plan.pixels)
    alive = feat.new_ones(rows_all, plan.pixels)
    prefix = feat.new_zeros(rows_all, plan.pixels)        # sum_{j <= i} w_j (g . f_j), carried
    for row, rows, slot, chunk in plan.rounds:
        sl, ss = slice(row, row + rows), slice(slot, slot + rows * chunk)
        t_in = (run_t[sl] * alive[sl])[..., None]
        r = _Round(plan.basis, coef[ss].view(rows, chunk, 6), op[ss].view(rows, chunk), t_in, thresholds)
        g = g_acc[sl]                                       # [rows, P, F]
        gf = torch.bmm(g, sfeat[ss].view(rows, chunk, -1).transpose(1, 2))  # [rows, P, C]  g . f_i
        pre = torch.cumsum(r.w * gf, dim=-1).add_(prefix[sl][..., None])
        after = total[sl][..., None] - pre                  # g . (acc - prefix_i) + g_T T_N
        d_alpha = (r.t_before * gf).sub_(after.div_(r.one_minus)).mul_(r.keep)
        # dL/dpower = dL/dalpha * alpha where alpha is neither clamped at ALPHA_MAX nor skipped (0)
        d_pow = d_alpha.mul_(F.threshold(-r.alpha, clamp_edge, 0.0)).neg_()
        npix = d_pow.shape[1]
        torch.mm(d_pow.transpose(0, 1).reshape(npix, rows * chunk).T, plan.basis, out=moments[ss])
        torch.bmm(r.w.transpose(1, 2), g, out=g_sfeat[ss].view(rows, chunk, -1))
        prefix[sl] = pre[..., -1]
        run_t[sl] -= r.w.sum(-1)
        alive[sl] = (r.t_last >= T_MIN).to(alive.dtype)

    # moments (S0, Sx, Sy, Sxx, Sxy, Syy) about the block centre -> sums of dL/dpower times
    # (dx, dy, dx^2, dx dy, dy^2), dx = pixel x - mean x -> chain rule through the exponent.
    s0, sx, sy, sxx, sxy, syy = moments.unbind(-1)
    rx, ry = rel.unbind(-1)
    ca, cb, cc, opg = sattrs[:, 2], sattrs[:, 3], sattrs[:, 4], sattrs[:, 5]
    sdx, sdy = sx - rx * s0, sy - ry * s0
    sdxx = sxx - 2 * rx * sx + rx * rx * s0
    sdxy = sxy - rx * sy - ry * sx + rx * ry * s0
    sdyy = syy - 2 * ry * sy + ry * ry * s0
    # alpha = opacity exp(power) where not clamped: d alpha / d opacity = (d alpha / d power) / opacity
    d_op = s0 / torch.where(opg > 0, opg, torch.ones_like(opg))
    slot_grads = torch.stack([ca * sdx + cb * sdy, cc * sdy + cb * sdx, -0.5 * sdxx, -sdxy, -0.5 * sdyy,
                              d_op])
    # accumulate along dim 1 of [channels, M + 1] (much faster than rows on the CPU); column M: padding
    g_attrs = attrs.new_zeros(6, plan.splats + 1).index_add_(1, plan.slot_gid, slot_grads)
    g_feat = feat.new_zeros(feat.shape[1], plan.splats + 1).index_add_(1, plan.slot_gid, g_sfeat.T)
    return g_attrs[:, :-1].T, g_feat[:, :-1].T


class Composite(torch.autograd.Function):
    """(attrs [M, 6] = mean x, mean y, conic A, B, C, opacity; feat [M, F]) -> per-block
    (acc [B, block^2, F], T [B, block^2])."""

    @staticmethod
    def forward(ctx, attrs: Tensor, feat: Tensor, plan: Plan):
        acc, trans = _forward(plan, attrs, feat)
        ctx.save_for_backward(attrs, feat, acc, trans)
        ctx.plan = plan
        return acc, trans

    @staticmethod
    def backward(ctx, g_acc: Tensor, g_trans: Tensor):
        attrs, feat, acc, trans = ctx.saved_tensors
        g_attrs, g_feat = _backward(ctx.plan, attrs, feat, acc, trans, g_acc.contiguous(),
                                    g_trans.contiguous())
        return g_attrs, g_feat, None


def blocks_to_image(x: Tensor, plan: Plan) -> Tensor:
    """[B, block^2, ...] per-block values -> [H, W, ...] image (differentiable)."""
    b = plan.block
    rest = x.shape[2:]
    img = x.reshape(plan.blocks_y, plan.blocks_x, b, b, *rest).transpose(1, 2)
    return img.reshape(plan.blocks_y * b, plan.blocks_x * b, *rest)[: plan.height, : plan.width]


def composite(attrs: Tensor, feat: Tensor, plan: Plan) -> tuple[Tensor, Tensor]:
    """Blend the planned splats front to back.

    attrs: Tensor  # [M, 6] (mean x, mean y, conic A, B, C, opacity)
    feat: Tensor   # [M, F] per-splat features (colour channels, optionally camera z)
    returns (acc [H, W, F] = sum_i w_i f_i, transmittance [H, W] = prod (1 - alpha_i)); differentiable.
    """
    acc, trans = Composite.apply(attrs, feat, plan)
    return blocks_to_image(acc, plan), blocks_to_image(trans, plan)

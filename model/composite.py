"""Differentiable front-to-back alpha compositing of screen-space Gaussians, in torch ops only.

The image is cut into square pixel blocks; each block gets the depth-sorted list of splats whose
pixel rectangle (``projection.screen_rect``) touches it. Lists are consumed in rounds: a round
takes the next ``C`` splats of every block that still has some and evaluates them densely as
[blocks, pixels, C] tensors, carrying each pixel's transmittance to the next round. Rounds are
sized to a fixed element budget, so memory stays bounded whatever the scene.

``Composite`` is an autograd Function with an analytic backward: the forward keeps only the
per-pixel results, the backward replays the same rounds (same ops, so the same skip and stop
decisions) and turns the per-pixel gradients into per-splat ones. With w_i = alpha_i T_i,
acc = sum w_i f_i and T_N = prod (1 - alpha_i) over the splats a pixel took:
    d acc / d f_i = w_i
    dL / d alpha_i = T_i (g . f_i) - (g . (acc - prefix_i) + g_T T_N) / (1 - alpha_i)
where prefix_i = sum_{j <= i} w_j f_j and g, g_T are the incoming gradients of acc and T_N.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from edmcgs.model.projection import ALPHA_MAX, ALPHA_MIN, T_MIN
from torch import Tensor

BLOCK = 8
"""Compositing block edge (px). Any size gives the same image (the splat lists come from the
16x16-tile rule); 8 keeps the dense [pixels, splats] work close to the splats' real footprints."""
ROUND_ELEMENTS = 1 << 21
"""Upper bound of blocks x pixels x splats evaluated at once (bounds memory: ~20 such tensors)."""
ROUND_OVERHEAD = 1 << 16
"""A round's fixed cost in evaluated elements; used to trade padding against more rounds."""


@dataclass
class Plan:
    """Which splats every block takes, in depth order, and how the lists are cut into rounds."""

    width: int
    height: int
    block: int
    gid: Tensor        # [P] int64 splat index of each (block, splat) pair, grouped by block, front first
    start: Tensor      # [B] int64 first pair of each block
    count: Tensor      # [B] int64 pairs of each block
    rounds: list       # [(offset, length, active block ids [Ba] int64)]
    px: Tensor         # [B, block^2] pixel x of each block's pixels (float, splat dtype)
    py: Tensor         # [B, block^2] pixel y

    @property
    def blocks_x(self) -> int:
        return -(-self.width // self.block)

    @property
    def blocks_y(self) -> int:
        return -(-self.height // self.block)


def _schedule(count: Tensor, pixels: int) -> list:
    """Cut the per-block lists into rounds, choosing each round's length to minimise padded work
    plus per-round overhead, with at most ROUND_ELEMENTS evaluated elements per round."""
    rounds = []
    offset = 0
    counts = count.cpu()
    while True:
        active = (counts > offset).nonzero().squeeze(1)
        if active.numel() == 0:
            return rounds
        rem = (counts[active] - offset).sort().values
        n = rem.numel()
        cap = max(1, ROUND_ELEMENTS // (n * pixels))
        longest = int(rem[-1])
        best_len, best_cost = None, None
        length = 8
        while True:
            length = min(length, longest, cap)
            left = n - int(torch.searchsorted(rem, length, right=True))
            cost = n * pixels * length + ROUND_OVERHEAD
            if left:  # assume what is left goes in one more round
                cost += left * pixels * (longest - length) + ROUND_OVERHEAD
            if best_cost is None or cost < best_cost:
                best_len, best_cost = length, cost
            if length >= min(longest, cap):
                break
            length *= 2
        rounds.append((offset, best_len, active.to(count.device)))
        offset += best_len


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
        iy, ix = torch.meshgrid(torch.arange(block, device=device), torch.arange(block, device=device),
                                indexing="ij")
        b = torch.arange(bx_n * by_n, device=device)
        px = ((b % bx_n)[:, None] * block + ix.reshape(1, -1)).to(dtype)
        py = ((b // bx_n)[:, None] * block + iy.reshape(1, -1)).to(dtype)
    return Plan(width, height, block, gid, start, count, _schedule(count, block * block), px, py)


def _gather_round(plan: Plan, offset: int, length: int, blocks: Tensor, attrs: Tensor, feat: Tensor):
    """The round's splats per active block: ids [Ba, C], a validity mask, attributes and features."""
    pos = plan.start[blocks, None] + offset + torch.arange(length, device=blocks.device)
    valid = pos < (plan.start + plan.count)[blocks, None]
    ids = plan.gid[pos.clamp_max(plan.gid.numel() - 1)]
    a = attrs[ids] * valid[..., None]  # padding gets opacity 0: alpha 0, skipped
    f = feat[ids] * valid[..., None]
    return ids, valid, a, f


def _round_alpha(plan: Plan, blocks: Tensor, a: Tensor):
    """Dense per-(pixel, splat) terms of one round: [Ba, P, C] tensors."""
    px, py = plan.px[blocks, :, None], plan.py[blocks, :, None]
    mx, my, ca, cb, cc, op = (t[:, None, :] for t in a.unbind(-1))
    dx, dy = px - mx, py - my
    power = (-0.5 * ca) * dx * dx + (-0.5 * cc) * dy * dy - cb * dx * dy
    gauss = torch.exp(power)
    raw = op * gauss
    alpha = raw.clamp_max(ALPHA_MAX)
    alpha = alpha * (alpha >= ALPHA_MIN)
    return dx, dy, gauss, raw, alpha


def _round_weights(alpha: Tensor, t_in: Tensor):
    """Blending weights of one round given each pixel's incoming transmittance (0 once stopped).

    returns (w, excl, keep, t_after_last): w = alpha * T_before * keep, where keep is whether the
    pixel still takes the splat (T after it >= T_MIN, as 3DGS stops the pixel otherwise).
    """
    cp = torch.cumprod(1.0 - alpha, dim=-1)
    keep = (cp * t_in) >= T_MIN
    excl = torch.cat([torch.ones_like(cp[..., :1]), cp[..., :-1]], dim=-1)
    w = alpha * excl * t_in * keep
    return w, excl, keep, cp[..., -1:] * t_in


def _forward(plan: Plan, attrs: Tensor, feat: Tensor):
    nb, npix = plan.px.shape
    acc = feat.new_zeros(nb, npix, feat.shape[1])
    trans = feat.new_ones(nb, npix)
    alive = feat.new_ones(nb, npix)
    for offset, length, blocks in plan.rounds:
        _, _, a, f = _gather_round(plan, offset, length, blocks, attrs, feat)
        alpha = _round_alpha(plan, blocks, a)[-1]
        t_in = (trans[blocks] * alive[blocks])[..., None]
        w, _, _, t_last = _round_weights(alpha, t_in)
        acc[blocks] += torch.bmm(w, f)
        trans[blocks] -= w.sum(-1)
        alive[blocks] = (t_last[..., 0] >= T_MIN).to(alive.dtype)
    return acc, trans


def _backward(plan: Plan, attrs: Tensor, feat: Tensor, acc: Tensor, trans: Tensor, g_acc: Tensor,
              g_trans: Tensor):
    nb, npix = plan.px.shape
    g_attrs = torch.zeros_like(attrs)
    g_feat = torch.zeros_like(feat)
    run_t = feat.new_ones(nb, npix)
    alive = feat.new_ones(nb, npix)
    prefix = feat.new_zeros(nb, npix)  # sum_{j <= i} w_j (g . f_j), carried across rounds
    # The part of dL/dalpha_i's second term that does not depend on i: g . acc + g_T T_N.
    total = (g_acc * acc).sum(-1) + g_trans * trans
    for offset, length, blocks in plan.rounds:
        ids, valid, a, f = _gather_round(plan, offset, length, blocks, attrs, feat)
        dx, dy, gauss, raw, alpha = _round_alpha(plan, blocks, a)
        t_in = (run_t[blocks] * alive[blocks])[..., None]
        w, excl, keep, t_last = _round_weights(alpha, t_in)
        g = g_acc[blocks]                                   # [Ba, P, F]
        gf = torch.bmm(g, f.transpose(1, 2))                # [Ba, P, C]  g . f_i
        pre = prefix[blocks][..., None] + torch.cumsum(w * gf, dim=-1)
        after = total[blocks][..., None] - pre              # g . (acc - prefix_i) + g_T T_N
        d_alpha = keep * (excl * t_in * gf - after / (1.0 - alpha))
        # d alpha / d raw is 1 where alpha is neither skipped (< ALPHA_MIN) nor clamped (ALPHA_MAX).
        d_raw = d_alpha * ((alpha > 0) & (raw < ALPHA_MAX))
        d_pow = d_raw * raw
        t1, t2 = d_pow * dx, d_pow * dy
        ca, cb, cc = a[..., 2], a[..., 3], a[..., 4]
        s_dx, s_dy = t1.sum(1), t2.sum(1)
        grads = torch.stack([
            ca * s_dx + cb * s_dy,                          # d mean x  (dx = px - mx)
            cc * s_dy + cb * s_dx,                          # d mean y
            -0.5 * (t1 * dx).sum(1),                        # d conic A
            -(t1 * dy).sum(1),                              # d conic B
            -0.5 * (t2 * dy).sum(1),                        # d conic C
            (d_raw * gauss).sum(1),                         # d opacity
        ], dim=-1)                                          # [Ba, C, 6]
        g_f = torch.bmm(w.transpose(1, 2), g)               # [Ba, C, F]
        flat = valid.reshape(-1)
        idx = ids.reshape(-1)[flat]
        g_attrs.index_add_(0, idx, grads.reshape(-1, 6)[flat])
        g_feat.index_add_(0, idx, g_f.reshape(-1, g_f.shape[-1])[flat])
        prefix[blocks] = pre[..., -1]
        run_t[blocks] -= w.sum(-1)
        alive[blocks] = (t_last[..., 0] >= T_MIN).to(alive.dtype)
    return g_attrs, g_feat


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

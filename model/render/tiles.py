"""Depth order and tile lists: which splats touch which TILE x TILE tile, front to back, and the
early stop of a tile's blending (both numba rasterizers)."""

from __future__ import annotations

import numba
import numpy as np

from edmcgs.model.render.jit import njit_cached
from edmcgs.model.render.projection import TILE

SHIFT = TILE.bit_length() - 1
"""Pixel -> tile index by a shift (pixels are >= 0): numba's signed floor division costs branches."""
assert 1 << SHIFT == TILE


@njit_cached(nogil=True)
def depth_order(rect, depth_bits):
    """The splats with a non-empty rectangle, sorted by depth, ties by index: an LSD radix sort
    (stable) of the float32 depths' bit patterns, which order like the depths as these are > 0."""
    order = np.nonzero((rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1]))[0]
    spare = np.empty_like(order)
    for shift in (0, 11, 22):
        count = np.zeros(2049, np.int64)
        for g in order:
            count[((depth_bits[g] >> shift) & 2047) + 1] += 1
        for d in range(2048):
            count[d + 1] += count[d]
        for g in order:
            d = (depth_bits[g] >> shift) & 2047
            spare[count[d]] = g
            count[d] += 1
        order, spare = spare, order
    return order


@njit_cached(nogil=True)
def bin_tiles(rect, order, grid_x, grid_y):
    """Tile lists: ids[start[t]:start[t + 1]] are the splats (taken in ``order``) whose rectangle
    touches tile t. ``order`` holds every splat with a non-empty rectangle (empty ones are skipped)."""
    start = np.zeros(grid_x * grid_y + 1, np.int64)
    for g in range(rect.shape[0]):  # counting needs no order: memory order is faster
        x0, y0, x1, y1 = rect[g, 0], rect[g, 1], rect[g, 2], rect[g, 3]
        if x1 <= x0 or y1 <= y0:
            continue
        for ty in range(y0 >> SHIFT, ((y1 - 1) >> SHIFT) + 1):
            for tx in range(x0 >> SHIFT, ((x1 - 1) >> SHIFT) + 1):
                start[ty * grid_x + tx + 1] += 1
    for t in range(grid_x * grid_y):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    ids = np.empty(start[-1], np.int32)
    for g in order:
        x0, y0, x1, y1 = rect[g, 0], rect[g, 1], rect[g, 2], rect[g, 3]
        if x1 <= x0 or y1 <= y0:
            continue
        for ty in range(y0 >> SHIFT, ((y1 - 1) >> SHIFT) + 1):
            for tx in range(x0 >> SHIFT, ((x1 - 1) >> SHIFT) + 1):
                t = ty * grid_x + tx
                ids[fill[t]] = g
                fill[t] += 1
    return start, ids


@numba.njit(inline="always")
def all_stopped(st) -> bool:
    """Whether every pixel of a tile has stopped: no transmittance st[:TILE * TILE] is positive (a
    stopped pixel's is negative). Counted in integers, which LLVM vectorises; a float max would run
    one lane at a time."""
    live = 0
    for p in range(TILE * TILE):
        live += np.int32(st[p] > 0)
    return live == 0

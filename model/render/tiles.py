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
    touches tile t. ``order`` holds every splat with a non-empty rectangle.

    Most splats touch at most 2 x 2 tiles: those take a branch-free path (the four candidate tiles,
    counted with 0 or 1; an absent one's entry goes to a spare slot) instead of loops whose trip counts
    the CPU cannot predict; wider ones loop."""
    n_tiles = grid_x * grid_y
    # counts at start[t + 1]; room past the last tile for the zero counts of absent neighbours
    start = np.zeros(n_tiles + grid_x + 3, np.int64)
    for g in order:
        tx0, ty0, nx, ny = _tile_span(rect, g)
        if nx <= 2 and ny <= 2:
            a = ty0 * grid_x + tx0 + 1
            two_x, two_y = np.int64(nx == 2), np.int64(ny == 2)
            start[a] += 1
            start[a + 1] += two_x
            start[a + grid_x] += two_y
            start[a + grid_x + 1] += two_x * two_y
        else:
            for ty in range(ty0, ty0 + ny):
                for tx in range(tx0, tx0 + nx):
                    start[ty * grid_x + tx + 1] += 1
    for t in range(n_tiles):
        start[t + 1] += start[t]
    total = start[n_tiles]
    fill = start[:n_tiles + grid_x + 2].copy()
    ids = np.empty(total + 1, np.int32)  # ids[total]: the spare slot
    for g in order:
        tx0, ty0, nx, ny = _tile_span(rect, g)
        if nx <= 2 and ny <= 2:
            a = ty0 * grid_x + tx0
            two_x, two_y = np.int64(nx == 2), np.int64(ny == 2)
            both = two_x * two_y
            ids[fill[a]] = g
            fill[a] += 1
            ids[fill[a + 1] if two_x else total] = g
            fill[a + 1] += two_x
            ids[fill[a + grid_x] if two_y else total] = g
            fill[a + grid_x] += two_y
            ids[fill[a + grid_x + 1] if both else total] = g
            fill[a + grid_x + 1] += both
        else:
            for ty in range(ty0, ty0 + ny):
                for tx in range(tx0, tx0 + nx):
                    t = ty * grid_x + tx
                    ids[fill[t]] = g
                    fill[t] += 1
    return start[:n_tiles + 1], ids[:total]


@numba.njit(inline="always")
def _tile_span(rect, g):
    """(first tile column, first tile row, columns, rows) of splat g's rectangle."""
    tx0, ty0 = rect[g, 0] >> SHIFT, rect[g, 1] >> SHIFT
    return tx0, ty0, ((rect[g, 2] - 1) >> SHIFT) - tx0 + 1, ((rect[g, 3] - 1) >> SHIFT) - ty0 + 1

@numba.njit(inline="always")
def all_stopped(st) -> bool:
    """Whether every pixel of a tile has stopped: no transmittance st[:TILE * TILE] is positive (a
    stopped pixel's is negative). Counted in integers, which LLVM vectorises; a float max would run
    one lane at a time."""
    live = 0
    for p in range(TILE * TILE):
        live += np.int32(st[p] > 0)
    return live == 0

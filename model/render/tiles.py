"""Tile lists: which splats touch which TILE x TILE tile, in a given order (both numba rasterizers)."""

from __future__ import annotations

import numba
import numpy as np

from edmcgs.model.render.jit import njit_cached
from edmcgs.model.render.projection import TILE


@njit_cached(nogil=True, parallel=True)
def bin_tiles(rect, order, grid_x, grid_y, bands=1):
    """Tile lists: ids[start[t]:start[t + 1]] are the splats (taken in ``order``) whose rectangle
    touches tile t.

    bands: bands of tile rows binned in parallel (one per thread): each scans every splat and writes
    only its own tiles, so the lists come out exactly as one sequential pass writes them.
    """
    bands = max(min(bands, grid_y), 1)
    start = np.zeros(grid_x * grid_y + 1, np.int64)
    for b in numba.prange(bands):
        lo, hi = b * grid_y // bands, (b + 1) * grid_y // bands
        for g in order:
            if rect[g, 2] <= rect[g, 0] or rect[g, 3] <= rect[g, 1]:
                continue
            for ty in range(max(rect[g, 1] // TILE, lo), min((rect[g, 3] - 1) // TILE + 1, hi)):
                for tx in range(rect[g, 0] // TILE, (rect[g, 2] - 1) // TILE + 1):
                    start[ty * grid_x + tx + 1] += 1
    for t in range(grid_x * grid_y):
        start[t + 1] += start[t]
    ids = np.empty(start[-1], np.int32)
    for b in numba.prange(bands):
        lo, hi = b * grid_y // bands, (b + 1) * grid_y // bands
        fill = start[lo * grid_x:hi * grid_x].copy()
        for g in order:
            if rect[g, 2] <= rect[g, 0] or rect[g, 3] <= rect[g, 1]:
                continue
            for ty in range(max(rect[g, 1] // TILE, lo), min((rect[g, 3] - 1) // TILE + 1, hi)):
                for tx in range(rect[g, 0] // TILE, (rect[g, 2] - 1) // TILE + 1):
                    t = ty * grid_x + tx - lo * grid_x
                    ids[fill[t]] = g
                    fill[t] += 1
    return start, ids

"""Tile lists: which splats touch which TILE x TILE tile, in a given order (both numba rasterizers)."""

from __future__ import annotations

import numpy as np

from edmcgs.model.render.jit import njit_cached
from edmcgs.model.render.projection import TILE


@njit_cached(nogil=True)
def bin_tiles(rect, order, grid_x, grid_y):
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

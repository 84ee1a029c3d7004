"""Depth order, tile lists and the early stop shared by both numba rasterizers, against plain Python."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from edmcgs.model.render.projection import TILE
from edmcgs.model.render.tiles import all_stopped, bin_tiles, depth_order


def _rects(rng, n: int, width: int, height: int, max_size: int) -> np.ndarray:
    """Random pixel rectangles inside the image (some empty), many on its right and bottom edges."""
    x0 = rng.integers(0, width, n)
    y0 = rng.integers(0, height, n)
    x0[::7], y0[::5] = width - 1, height - 1
    x1 = np.minimum(x0 + rng.integers(0, max_size, n), width)
    y1 = np.minimum(y0 + rng.integers(0, max_size, n), height)
    return np.stack([x0, y0, x1, y1], -1).astype(np.int32)


def _reference(rect: np.ndarray, order: np.ndarray, grid_x: int, grid_y: int) -> list[list[int]]:
    lists = [[] for _ in range(grid_x * grid_y)]
    for g in order:
        x0, y0, x1, y1 = rect[g]
        for ty in range(y0 // TILE, (y1 - 1) // TILE + 1):
            for tx in range(x0 // TILE, (x1 - 1) // TILE + 1):
                lists[ty * grid_x + tx].append(int(g))
    return lists


@pytest.mark.parametrize("max_size", [3, 20, 60])  # mostly 1-2 tiles a side, and wider ones
def test_bin_tiles_matches_plain_python_in_depth_order(max_size):
    rng = np.random.default_rng(max_size)
    width, height = 173, 130  # partial tiles on the right and at the bottom
    grid_x, grid_y = -(-width // TILE), -(-height // TILE)
    rect = _rects(rng, 3000, width, height, max_size)
    depth = rng.uniform(0.5, 50.0, len(rect)).astype(np.float32)
    order = depth_order(rect, depth.view(np.uint32))
    nonempty = np.nonzero((rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1]))[0]
    assert sorted(order.tolist()) == nonempty.tolist()
    assert (np.diff(depth[order]) >= 0).all()
    start, ids = bin_tiles(rect, order, grid_x, grid_y)
    assert start.shape == (grid_x * grid_y + 1,) and start[0] == 0 and len(ids) == start[-1]
    want = _reference(rect, order, grid_x, grid_y)
    assert [ids[start[t]:start[t + 1]].tolist() for t in range(grid_x * grid_y)] == want


def test_bin_tiles_of_no_splats():
    start, ids = bin_tiles(np.zeros((0, 4), np.int32), np.zeros(0, np.int64), 3, 2)
    assert (start == 0).all() and start.shape == (7,) and ids.shape == (0,)


@numba.njit
def _stopped(st):
    return all_stopped(st)


def test_all_stopped_reads_the_transmittance_row_only():
    st = np.full(5 * TILE * TILE, 1.0, np.float32)
    st[:TILE * TILE] = -0.5
    assert _stopped(st)  # the colour rows' positive values are not transmittances
    st[TILE * TILE - 1] = 1e-30
    assert not _stopped(st)
    st[TILE * TILE - 1] = 0.0  # neither live nor counted as live
    assert _stopped(st)

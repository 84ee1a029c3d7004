"""The event map I_E: per-pixel signed polarity sum of a window of events (paper, section 3.3).

Accumulation is in int64 and cast to float32 once at the end: a window of any length cannot
overflow, and every pixel sum up to 2^24 (16.7 million events on one pixel) is exact in float32.
"""

from __future__ import annotations

import numba
import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.sensor.events import Events


@numba.njit(cache=True, nogil=True)
def _accumulate_signed(x, y, p, width, height, out):  # pragma: no cover - compiled
    for i in range(x.shape[0]):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi >= width or yi >= height:
            return i
        out[yi, xi] += p[i]
    return -1


@numba.njit(cache=True, nogil=True)
def _accumulate_split(x, y, p, width, height, out):  # pragma: no cover - compiled
    for i in range(x.shape[0]):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi >= width or yi >= height:
            return i
        out[0 if p[i] > 0 else 1, yi, xi] += 1
    return -1


def accumulate(events: Events, width: int, height: int, *, split_polarity: bool = False) -> np.ndarray:
    """I_E for ``events``: float32 [H, W] signed polarity sum per pixel.

    With ``split_polarity``: float32 [2, H, W], channel 0 the count of ON events, channel 1 the count
    of OFF events (both >= 0; their difference is the signed map). An empty window gives all zeros.
    An event outside width x height raises ``InvalidInputError`` (the caller passed the wrong resolution).
    """
    if not isinstance(events, Events):
        raise InvalidInputError(f"events must be an Events batch, got {type(events).__name__}")
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise InvalidInputError(f"resolution must be positive, got width={width} height={height}")
    if split_polarity:
        acc = np.zeros((2, height, width), np.int64)
        bad = _accumulate_split(events.x, events.y, events.p, width, height, acc)
    else:
        acc = np.zeros((height, width), np.int64)
        bad = _accumulate_signed(events.x, events.y, events.p, width, height, acc)
    if bad >= 0:
        raise InvalidInputError(
            f"event {bad} at (x={events.x[bad]}, y={events.y[bad]}) is outside the {width}x{height} "
            "resolution passed to accumulate")
    return acc.astype(np.float32)

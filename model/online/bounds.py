"""What the events since a frame say about each pixel of the event camera's view now.

The sensor's own model of a pixel: it fires an event each time its log intensity has moved by the
contrast threshold C since its last event, so with E the signed event count since the frame,

    log(I_t + eps) = log(I_frame + eps) + C E  ± C

(the change that has not fired yet is less than one threshold either way). ``integrate`` is the
estimate (a baseline on its own: ``model/eval/baselines.py``); ``project`` clips a render of the event
camera's view into the bounds: the model keeps what the events cannot tell apart (within one
threshold), and the events overrule it wherever its render contradicts them.
"""

from __future__ import annotations

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.luminance import LOG_EPS
from edmcgs.model.render.jit import njit_cached

MAX_LOG_CHANGE = 20.0
"""Clamp of C E: beyond it a pixel is black or white anyway, and exp() stays finite."""


@njit_cached(nogil=True)
def _bounded(frame, scale, event_map, rows, cols, erows, ecols, contrast, lo_shift, hi_shift, eps, image,
             out):  # pragma: no cover - compiled
    """out[i, j, c] = image clipped into [lo, hi], the frame's pixel (rows, cols) moved by the event
    pixel (erows, ecols) with its log intensity shifted by lo_shift / hi_shift; a NaN takes lo. float32
    and branch-free (a third of the time of float64 with branches). C E is clamped before the shift: a
    shift is one threshold, the clamp far beyond any pixel's range."""
    zero, one, limit = np.float32(0.0), np.float32(1.0), np.float32(MAX_LOG_CHANGE)
    c32, eps32, scale32 = np.float32(contrast), np.float32(eps), np.float32(scale)
    lo_factor, hi_factor = np.float32(np.exp(lo_shift)), np.float32(np.exp(hi_shift))
    for i in range(out.shape[0]):
        frame_row, event_row, image_row, out_row = frame[rows[i]], event_map[erows[i]], image[i], out[i]
        for j in range(out.shape[1]):
            gain = np.exp(min(max(c32 * event_row[ecols[j]], -limit), limit))
            lo_gain, hi_gain = gain * lo_factor, gain * hi_factor
            pixel = frame_row[cols[j]]
            for c in range(out.shape[2]):
                base = np.float32(pixel[c]) * scale32 + eps32
                lo = min(max(base * lo_gain - eps32, zero), one)
                hi = min(max(base * hi_gain - eps32, zero), one)
                v = image_row[j, c]
                out_row[j, c] = lo if v != v else min(max(v, lo), hi)


def _nearest(n_out: int, n_in: int) -> np.ndarray:
    """For each of n_out output pixels along an axis, its nearest of n_in source pixels."""
    return ((np.arange(n_out) * n_in) // n_out).astype(np.int64)


def _run(frame, event_map, contrast: float, lo_shift: float, hi_shift: float, eps: float,
         image: np.ndarray | None, size: tuple[int, int] | None) -> np.ndarray:
    frame, event_map = np.asarray(frame), np.asarray(event_map)
    if frame.ndim != 3 or event_map.ndim != 2:
        raise InvalidInputError(f"frame must be [H, W, C] and event_map [H, W]; got {frame.shape} and "
                                f"{event_map.shape}")
    if not (np.isfinite(contrast) and contrast > 0):
        raise InvalidInputError(f"contrast threshold must be a finite positive number, got {contrast}")
    if (frame.dtype != np.uint8 and not np.isfinite(frame).all()) or not np.isfinite(event_map).all():
        raise InvalidInputError("frame and event_map must be finite")
    w, h = (frame.shape[1], frame.shape[0]) if size is None else size
    out = np.empty((h, w, frame.shape[2]), np.float32)
    image = out if image is None else np.ascontiguousarray(image, np.float32)  # None: lo = hi, its value
    scale = 1.0 / 255.0 if frame.dtype == np.uint8 else 1.0
    frame = frame if frame.dtype == np.uint8 else np.ascontiguousarray(frame, np.float32)
    _bounded(frame, scale, np.ascontiguousarray(event_map, np.float32), _nearest(h, frame.shape[0]),
             _nearest(w, frame.shape[1]), _nearest(h, event_map.shape[0]), _nearest(w, event_map.shape[1]),
             float(contrast), float(lo_shift), float(hi_shift), float(eps), image, out)
    return out


def integrate(frame: np.ndarray, event_map: np.ndarray, contrast: float, *, shift: float = 0.0,
              size: tuple[int, int] | None = None, eps: float = LOG_EPS) -> np.ndarray:
    """frame [H, W, C] (uint8, or float in [0, 1]), event_map [He, We] signed polarity sum since it ->
    float32 [h, w, C] in [0, 1]: the frame moved by the events, log intensity shifted by ``shift`` more;
    at ``size`` (w, h), default the frame's (each output pixel takes its nearest frame and event pixel)."""
    return _run(frame, event_map, contrast, shift, shift, eps, None, size)


def project(image: np.ndarray, frame: np.ndarray, event_map: np.ndarray, contrast: float, *,
            eps: float = LOG_EPS) -> np.ndarray:
    """image [h, w, C] in [0, 1] (a render of the event camera's view at the time the events run to)
    clipped into the bounds the frame and the events since it put on each pixel -> float32 [h, w, C].
    A non-finite pixel of ``image`` takes the lower bound (+inf the upper)."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != np.shape(frame)[-1]:
        raise InvalidInputError(f"image must be [H, W, {np.shape(frame)[-1]}] like the frame, "
                                f"got {image.shape}")
    return _run(frame, event_map, contrast, -contrast, contrast, eps, image, (image.shape[1], image.shape[0]))

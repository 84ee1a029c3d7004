"""Rendered float images -> bytes on the wire (PNG, JPEG, raw uint8); depth maps -> grey with their
near and far; event maps -> DV-style RGBA."""

from __future__ import annotations

import io

import numba
import numpy as np
from PIL import Image

from edmcgs import protocol


@numba.njit(nogil=True, cache=True)
def _to_uint8(flat, out):
    for i in range(flat.shape[0]):
        v = flat[i] * np.float32(255.0) + np.float32(0.5)  # +inf stays +inf, -inf -inf, NaN NaN
        out[i] = np.uint8(min(max(v, np.float32(0.0)), np.float32(255.0))) if v == v else np.uint8(0)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """float [H, W, C] in [0, 1] (C = 1 or 3) -> uint8 [H, W, C], rounded; NaN -> 0, +-Inf -> 255 / 0.
    One compiled pass over the frame instead of numpy's four (check, scale, clip, cast)."""
    out = np.empty(np.shape(image), np.uint8)
    _to_uint8(np.ascontiguousarray(image, dtype=np.float32).reshape(-1), out.reshape(-1))
    return out


def encode(pixels: np.ndarray, fmt: str, *, jpeg_quality: int = 90, png_compress_level: int = 1) -> bytes:
    """uint8 [H, W, C] -> bytes in ``fmt``: "png", "jpeg", or "raw" (the pixels row-major)."""
    if fmt == "raw":
        return np.ascontiguousarray(pixels).tobytes()
    image = Image.fromarray(pixels[..., 0] if pixels.shape[2] == 1 else pixels)
    buf = io.BytesIO()
    if fmt == "png":
        image.save(buf, format="PNG", compress_level=png_compress_level)
    elif fmt == "jpeg":
        image.save(buf, format="JPEG", quality=jpeg_quality)
    else:
        raise ValueError(f"unknown image format {fmt!r}")
    return buf.getvalue()


def event_rgba(emap: np.ndarray) -> np.ndarray:
    """Signed event map [H, W] -> uint8 RGBA [H, W, 4]: ``protocol.EVENT_ON_RGB`` where the sum is
    positive, ``EVENT_OFF_RGB`` where negative, transparent where zero (DV's polarity colours, so that
    it reads over a render as well as on white)."""
    emap = np.asarray(emap)
    if emap.ndim != 2:
        raise ValueError(f"an event map is [H, W], got shape {emap.shape}")
    out = np.zeros((*emap.shape, 4), np.uint8)
    out[emap > 0] = (*protocol.EVENT_ON_RGB, 255)
    out[emap < 0] = (*protocol.EVENT_OFF_RGB, 255)
    return out


DEPTH_PERCENTILES = (1.0, 99.0)
"""A depth render's near and far: these percentiles of the depths it shows (a stray splat right in front
of the camera or far behind the scene does not flatten the rest)."""


def depth_grey(depth: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, float | None, float | None]:
    """Expected depth [H, W] and the splats' opacity [H, W] -> (uint8 [H, W, 1], near, far): grey
    ``protocol.DEPTH_GREY_NEAR`` (255) at ``near``, ``DEPTH_GREY_FAR`` (1) at ``far`` and linear between
    (nearer brighter; depths beyond them clipped), ``DEPTH_GREY_NONE`` (0) where the splats' opacity is
    below ``protocol.DEPTH_MIN_ALPHA``. near and far are None, and every pixel 0, when none reaches it."""
    covered = alpha >= protocol.DEPTH_MIN_ALPHA
    out = np.full((*depth.shape, 1), protocol.DEPTH_GREY_NONE, np.uint8)
    if not covered.any():
        return out, None, None
    near, far = (float(v) for v in np.percentile(depth[covered], DEPTH_PERCENTILES))
    far = max(far, near + max(1e-6, 1e-6 * abs(near)))  # a flat view: every covered pixel at 255
    lo, hi = protocol.DEPTH_GREY_FAR, protocol.DEPTH_GREY_NEAR
    grey = lo + (hi - lo) * (far - depth[covered].astype(np.float64)) / (far - near)
    out[covered, 0] = np.rint(np.clip(grey, lo, hi)).astype(np.uint8)
    return out, near, far

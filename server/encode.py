"""Rendered float images -> bytes on the wire (PNG, JPEG, raw uint8)."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image


def to_uint8(image: np.ndarray) -> np.ndarray:
    """float [H, W, C] in [0, 1] (C = 1 or 3) -> uint8 [H, W, C], rounded; NaN -> 0, +-Inf -> 255 / 0."""
    if not np.isfinite(image).all():
        image = np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0)
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)


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

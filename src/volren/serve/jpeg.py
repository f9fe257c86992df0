"""Frames to JPEG: composite over the background, sRGB 8-bit, encode (simplejpeg, libjpeg-turbo; Pillow fallback)."""

from __future__ import annotations

import io

import numpy as np

from volren.imageio import to_srgb8

try:
    import simplejpeg
except ImportError:  # the Pillow fallback: slower, same bytes format
    simplejpeg = None

JPEG_QUALITY = 85
"""libjpeg quality 1-100: 85 keeps a smooth volume free of visible blocks at ~1 bit per pixel"""


LUT_SIZE = 1 << 14
"""linear [0, 1] steps of the sRGB table: 1/16383 moves the steepest part of the curve (12.92 x 255 codes per unit
near black) by 0.2 of a code, so the table agrees with `to_srgb8` to within one code"""
SRGB_LUT = to_srgb8(np.linspace(0.0, 1.0, LUT_SIZE)[:, None])[:, 0]


def display_image(images: list[np.ndarray], background: tuple[float, float, float]) -> np.ndarray:
    """uint8 sRGB (H, W, 3) of one viewer: its view(s) over the background, the two eyes of a stereo viewer side by
    side (left eye on the left). A table lookup instead of `to_srgb8`'s float64 power: 14 ms instead of 49 ms at
    480x270 (CPU, 2 cores, shared with other jobs), the same bytes to within one code."""
    rgb = np.concatenate(images, axis=1) if len(images) > 1 else images[0]
    bg = np.asarray(background, dtype=np.float32)
    x = rgb[..., :3] + (1.0 - rgb[..., 3:4]) * bg
    np.clip(x * (LUT_SIZE - 1) + 0.5, 0.0, LUT_SIZE - 1, out=x)  # NaN stays NaN and becomes index 0 below
    return SRGB_LUT[np.nan_to_num(x, copy=False).astype(np.uint16)]


def encode_jpeg(rgb: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if simplejpeg is not None:
        return simplejpeg.encode_jpeg(rgb, quality=quality, colorspace="RGB", colorsubsampling="420", fastdct=True)
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def decode_jpeg(data: bytes) -> np.ndarray:
    """uint8 (H, W, 3) (tests and the bench's clients)."""
    if simplejpeg is not None:
        return simplejpeg.decode_jpeg(data, colorspace="RGB")
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

"""Frames to JPEG: composite over the background, sRGB 8-bit, encode (simplejpeg, libjpeg-turbo; Pillow fallback)."""

from __future__ import annotations

import io

import numpy as np

from volren.imageio import composite, to_srgb8

try:
    import simplejpeg
except ImportError:  # the Pillow fallback: slower, same bytes format
    simplejpeg = None

JPEG_QUALITY = 85
"""libjpeg quality 1-100: 85 keeps a smooth volume free of visible blocks at ~1 bit per pixel"""


def display_image(images: list[np.ndarray], background: tuple[float, float, float]) -> np.ndarray:
    """uint8 sRGB (H, W, 3) of one viewer: its view, or its two eyes side by side (left eye on the left)."""
    rgb = [to_srgb8(composite(image, background)) for image in images]
    return rgb[0] if len(rgb) == 1 else np.concatenate(rgb, axis=1)


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

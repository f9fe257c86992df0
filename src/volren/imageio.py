"""Image files: linear premultiplied RGBA in memory, sRGB PNG for eyes, ``.npy`` for exact linear data.

Images are float32 ``(H, W, 4)``: linear RGB radiance premultiplied by alpha, alpha = 1 - transmittance (DESIGN.md).
A PNG is a display image: composited over a background, scaled by an exposure, tone mapped, then sRGB encoded, so it
is lossy by design; ``.npy`` keeps the linear data bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from volren.errors import VolrenError

TONEMAPS = ("none", "reinhard", "aces")
"""Tone maps accepted by :func:`to_srgb8`."""

_LDR_SUFFIXES = (".png", ".jpg", ".jpeg")
# Large but finite, so x/(1+x) and the ACES fit stay finite (in float64) when a radiance is +inf.
_RADIANCE_CAP = 1e30


def _check_rgba(image: np.ndarray, what: str = "image") -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 4:
        raise VolrenError(f"{what} must have shape (H, W, 4) (premultiplied linear RGBA), got {image.shape}")
    return image


def composite(image: np.ndarray, background: tuple[float, float, float]) -> np.ndarray:
    """Composite a premultiplied RGBA image over an opaque linear RGB background: rgb + (1 - alpha) * background."""
    image = _check_rgba(image)
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape != (3,):
        raise VolrenError(f"background must be 3 linear RGB values, got {background!r}")
    return image[..., :3] + (1.0 - image[..., 3:4]) * bg


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """Exact piecewise sRGB encoding (IEC 61966-2-1) of linear values in [0, 1]; not the 2.2 power approximation."""
    linear = np.asarray(linear, dtype=np.float64)
    return np.where(
        linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(np.maximum(linear, 0.0031308), 1 / 2.4) - 0.055
    )


def srgb_eotf(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_oetf`: sRGB-encoded values in [0, 1] back to linear."""
    encoded = np.asarray(encoded, dtype=np.float64)
    return np.where(encoded <= 0.04045, encoded / 12.92, np.power((np.maximum(encoded, 0.04045) + 0.055) / 1.055, 2.4))


def _tonemap(x: np.ndarray, tonemap: str) -> np.ndarray:
    if tonemap == "none":
        return x
    if tonemap == "reinhard":
        return x / (1.0 + x)
    # Narkowicz 2015 fit of the ACES filmic curve (input already exposed).
    return (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)


def to_srgb8(rgb_linear: np.ndarray, exposure: float = 0.0, tonemap: str = "none") -> np.ndarray:
    """Linear RGB -> display uint8 sRGB: scale by 2**exposure (stops), tone map, clip to [0, 1], encode, round.

    ``tonemap`` is ``none`` (clip), ``reinhard`` (x / (1 + x)) or ``aces`` (Narkowicz fit). Negative radiance is
    clipped to 0 before the tone map; NaN is refused, since it would become an arbitrary byte.
    """
    if tonemap not in TONEMAPS:
        raise VolrenError(f"unknown tone map '{tonemap}': use one of {', '.join(TONEMAPS)}")
    x = np.asarray(rgb_linear, dtype=np.float64)
    if np.isnan(x).any():
        raise VolrenError("image contains NaN radiance; refusing to encode it as sRGB")
    x = np.clip(x * 2.0 ** float(exposure), 0.0, _RADIANCE_CAP)
    x = np.clip(_tonemap(x, tonemap), 0.0, 1.0)
    return np.round(srgb_oetf(x) * 255.0).astype(np.uint8)


def save_srgb8(path: str | Path, pixels: np.ndarray) -> None:
    """Write display-ready uint8 ``(H, W, 3)`` pixels (already sRGB) as a PNG, creating missing folders."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise VolrenError(f"'{path}': display images are written as .png")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(path, pixels, plugin="pillow")
    except (OSError, ValueError) as exc:
        raise VolrenError(f"cannot write image '{path}': {exc}") from exc


def save_png(
    path: str | Path,
    image_rgba: np.ndarray,
    background: tuple[float, float, float],
    exposure: float = 0.0,
    tonemap: str = "none",
) -> None:
    """Write a premultiplied linear RGBA image as an opaque sRGB PNG, composited over ``background`` (linear RGB)."""
    save_srgb8(path, to_srgb8(composite(image_rgba, background), exposure, tonemap))


def save_linear(path: str | Path, image: np.ndarray) -> None:
    """Write the exact linear premultiplied RGBA image as float32 ``.npy`` (for ``volren compare`` and references)."""
    path = Path(path)
    if path.suffix.lower() != ".npy":
        raise VolrenError(f"'{path}': linear images are written as .npy")
    image = _check_rgba(image)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, image.astype(np.float32, copy=False))
    except OSError as exc:
        raise VolrenError(f"cannot write '{path}': {exc}") from exc


def save_side_by_side(
    path: str | Path,
    images: Sequence[np.ndarray],
    background: tuple[float, float, float],
    exposure: float = 0.0,
    tonemap: str = "none",
) -> None:
    """Write views left to right in one PNG (view 0, the left eye, on the left), as a stereo viewer expects."""
    if len(images) == 0:
        raise VolrenError("save_side_by_side needs at least one image")
    images = [_check_rgba(image, f"view {i}") for i, image in enumerate(images)]
    heights = [image.shape[0] for image in images]
    if len(set(heights)) != 1:
        raise VolrenError(f"side-by-side views must have the same height, got heights {heights}")
    save_png(path, np.concatenate(images, axis=1), background, exposure, tonemap)


def load_image(path: str | Path) -> np.ndarray:
    """Read an image as linear float32 ``(H, W, 3 | 4)``: ``.npy`` as stored, PNG/JPEG decoded from 8/16-bit sRGB.

    A PNG's straight alpha is premultiplied into its RGB, so every loaded RGBA image follows the in-memory convention.
    Note that a PNG written by :func:`save_png` holds display values (exposure, tone map, background), not radiance.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix != ".npy" and suffix not in _LDR_SUFFIXES:
        raise VolrenError(f"'{path}': unsupported image type '{suffix}', use .npy, .png, .jpg or .jpeg")
    if not path.is_file():
        raise VolrenError(f"image file '{path}' does not exist")
    if suffix == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:  # an empty file: EOFError; no header: pickle advice
            why = "not a .npy file (no NumPy header)" if isinstance(exc, EOFError) or "pickle" in str(exc) else exc
            raise VolrenError(f"cannot read '{path}' as .npy: {why}") from None
        if data.dtype.kind != "f":
            raise VolrenError(f"'{path}': expected linear float data, got dtype {data.dtype}")
        image = data
    else:
        try:
            pixels = iio.imread(path, plugin="pillow")
        except Exception as exc:  # Pillow raises OSError, SyntaxError, ... for corrupt files: all mean unreadable
            raise VolrenError(f"cannot read image '{path}': {exc}") from exc
        image = _decode_ldr(path, pixels)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise VolrenError(f"'{path}': expected an image of shape (H, W, 3) or (H, W, 4), got {image.shape}")
    return np.ascontiguousarray(image, dtype=np.float32)


def _decode_ldr(path: Path, pixels: np.ndarray) -> np.ndarray:
    """sRGB integer pixels (grey, grey+alpha, RGB or RGBA) -> linear float, alpha premultiplied."""
    if pixels.dtype not in (np.uint8, np.uint16):
        raise VolrenError(f"'{path}': expected 8- or 16-bit pixels, got {pixels.dtype}")
    values = pixels.astype(np.float64) / np.iinfo(pixels.dtype).max
    if values.ndim == 2:
        values = values[..., None]
    if values.ndim != 3 or values.shape[2] not in (1, 2, 3, 4):
        raise VolrenError(f"'{path}': unsupported image layout {pixels.shape}")
    colour_count = 1 if values.shape[2] <= 2 else 3
    rgb = srgb_eotf(np.broadcast_to(values[..., :colour_count], (*values.shape[:2], 3)))
    if values.shape[2] == colour_count:
        return rgb
    alpha = values[..., -1:]
    return np.concatenate([rgb * alpha, alpha], axis=2)

"""Image quality metrics (PSNR, SSIM, FLIP) and error heat maps, as thin wrappers over well-kept libraries.

One rule for every metric here, so numbers from different functions describe the same images:

* Only RGB is compared. Images are premultiplied, so their RGB already is the image composited over black; alpha
  is dropped, and an ``(H, W, 3)`` image may be compared with an ``(H, W, 4)`` one.
* ``data_range`` is the reference's peak, ``ref_rgb.max()``, unless given. Renders are HDR linear radiance with no
  natural white; the reference's brightest value plays white, as on a display exposed for the reference. A
  reference with no signal (peak <= 0) has no such white and is refused.
* PSNR, SSIM and the absolute errors see the images as they are, unclipped, so a test image 100x too bright reports
  its true error (about -29 dB), not the error left after a display clipped it to the reference's peak.
* FLIP and the heat map are display comparisons: they see both images clipped to ``[0, data_range]`` and divided
  by ``data_range``.
"""

from __future__ import annotations

from pathlib import Path

import flip_evaluator
import matplotlib
import numpy as np
from skimage.metrics import mean_squared_error, peak_signal_noise_ratio, structural_similarity

from volren.errors import VolrenError
from volren.imageio import load_image, save_srgb8, srgb_oetf

HEATMAP_MAX_ERROR = 0.25
"""Normalised L1 error shown at the top of the heat map's colour scale (paper 000, Fig. 7 "D": [0, 25%])."""

HEATMAP_COLORMAP = "inferno"
"""Perceptually uniform and black at zero error, so error-free regions read as background."""

# Gaussian-weighted SSIM (sigma 1.5) spans 11 pixels in skimage (truncate 3.5).
_SSIM_MIN_SIDE = 11


def _prepare(
    ref: np.ndarray, test: np.ndarray, data_range: float | None, *, display: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Apply the module's rule: RGB only, data range from the reference; ``display`` clips both to [0, data_range]."""
    ref = np.asarray(ref)
    test = np.asarray(test)
    for name, image in (("reference", ref), ("test", test)):
        if image.ndim != 3 or image.shape[2] not in (3, 4):
            raise VolrenError(f"{name} image must have shape (H, W, 3) or (H, W, 4), got {image.shape}")
    if ref.shape[:2] != test.shape[:2]:
        raise VolrenError(f"image sizes differ: reference {ref.shape}, test {test.shape}")
    ref_rgb = ref[..., :3].astype(np.float64)
    test_rgb = test[..., :3].astype(np.float64)
    for name, image in (("reference", ref_rgb), ("test", test_rgb)):
        if not np.isfinite(image).all():
            raise VolrenError(f"{name} image contains NaN or infinite values")
    if data_range is None:
        data_range = float(ref_rgb.max())
        if not data_range > 0:
            raise VolrenError(f"reference image has no signal (its peak is {data_range:g}): no peak to measure "
                              "errors against; give data_range")
    elif not (np.isfinite(data_range) and data_range > 0):
        raise VolrenError(f"data_range must be a positive finite number, got {data_range}")
    if display:
        return np.clip(ref_rgb, 0.0, data_range), np.clip(test_rgb, 0.0, data_range), float(data_range)
    return ref_rgb, test_rgb, float(data_range)


def psnr(ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB, 10 log10(data_range^2 / MSE); ``inf`` for identical images."""
    ref_rgb, test_rgb, data_range = _prepare(ref, test, data_range)
    if mean_squared_error(ref_rgb, test_rgb) == 0.0:
        return float("inf")
    return float(peak_signal_noise_ratio(ref_rgb, test_rgb, data_range=data_range))


def ssim(ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> float:
    """Mean SSIM over RGB, with the settings of Wang et al. 2004 (Gaussian window, sigma 1.5, population statistics)."""
    ref_rgb, test_rgb, data_range = _prepare(ref, test, data_range)
    if min(ref_rgb.shape[:2]) < _SSIM_MIN_SIDE:
        raise VolrenError(f"SSIM needs images of at least {_SSIM_MIN_SIDE}x{_SSIM_MIN_SIDE} pixels, got {ref.shape}")
    return float(
        structural_similarity(
            ref_rgb,
            test_rgb,
            data_range=data_range,
            channel_axis=-1,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
    )


def flip(ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> float:
    """Mean LDR FLIP error (0 = identical, 1 = maximal) of the images divided by data_range and sRGB encoded.

    LDR rather than HDR FLIP because the clipped, normalised images are display images; HDR FLIP would instead
    pick its own exposure range and tone map.
    """
    ref_rgb, test_rgb, data_range = _prepare(ref, test, data_range, display=True)
    ref_srgb, test_srgb = (
        np.ascontiguousarray(srgb_oetf(image / data_range), dtype=np.float32) for image in (ref_rgb, test_rgb)
    )
    _, mean_error, _ = flip_evaluator.evaluate(ref_srgb, test_srgb, "LDR", inputsRGB=True, applyMagma=False)
    return float(mean_error)


def error_heatmap(ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> np.ndarray:
    """Colour uint8 ``(H, W, 3)`` map of the per-pixel L1 error of normalised RGB, mean over channels.

    As paper 000 (Fig. 7 "D"): both images are divided by data_range (the reference's max), and the error is
    mapped to [0, 25%] on the colour map; larger errors saturate at the top colour.
    """
    ref_rgb, test_rgb, data_range = _prepare(ref, test, data_range, display=True)
    error = np.abs(ref_rgb - test_rgb).mean(axis=-1) / data_range
    colours = matplotlib.colormaps[HEATMAP_COLORMAP](np.clip(error / HEATMAP_MAX_ERROR, 0.0, 1.0), bytes=True)
    return np.ascontiguousarray(colours[..., :3])


def save_heatmap(path: str | Path, ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> None:
    """Write :func:`error_heatmap` as a PNG (its colours are already display values)."""
    save_srgb8(path, error_heatmap(ref, test, data_range))


def compare(ref: np.ndarray, test: np.ndarray, data_range: float | None = None) -> dict[str, float]:
    """All metrics of ``test`` against ``ref`` under the module's rule.

    Returns psnr [dB], ssim, flip, max_abs_error and mean_abs_error (linear radiance, unclipped), and the
    data_range used, so a reader can normalise the absolute errors.
    """
    ref_rgb, test_rgb, data_range = _prepare(ref, test, data_range)
    abs_error = np.abs(ref_rgb - test_rgb)
    return {
        "psnr": psnr(ref_rgb, test_rgb, data_range),
        "ssim": ssim(ref_rgb, test_rgb, data_range),
        "flip": flip(ref_rgb, test_rgb, data_range),
        "max_abs_error": float(abs_error.max()),
        "mean_abs_error": float(abs_error.mean()),
        "data_range": data_range,
    }


def compare_files(
    ref_path: str | Path, test_path: str | Path, heatmap_path: str | Path | None = None
) -> dict[str, float]:
    """:func:`compare` two image files (``.npy``, PNG or JPEG via :func:`volren.imageio.load_image`).

    PNG/JPEG files hold display values (exposure, tone map, background), so compare like with like.
    """
    ref = load_image(ref_path)
    test = load_image(test_path)
    peak = float(ref[..., :3].max())
    if peak <= 0:  # NaN falls through to compare's clearer message
        raise VolrenError(f"reference '{ref_path}' has no signal (its brightest value is {peak:g}): nothing to "
                          "measure errors against")
    if ref.shape[:2] != test.shape[:2]:
        raise VolrenError(f"image sizes differ: '{ref_path}' is {ref.shape}, '{test_path}' is {test.shape}")
    metrics = compare(ref, test)
    if heatmap_path is not None:
        save_heatmap(heatmap_path, ref, test)
    return metrics

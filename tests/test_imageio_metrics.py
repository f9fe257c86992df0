"""Image files (sRGB encoding, compositing, round trips) and metrics (PSNR, SSIM, FLIP, heat maps)."""

from __future__ import annotations

import math

import imageio.v3 as iio
import matplotlib
import numpy as np
import pytest

from volren.errors import VolrenError
from volren.imageio import (
    composite,
    load_image,
    save_linear,
    save_png,
    save_side_by_side,
    save_srgb8,
    srgb_eotf,
    srgb_oetf,
    to_srgb8,
)
from volren.metrics import (
    HEATMAP_COLORMAP,
    compare,
    compare_files,
    error_heatmap,
    flip,
    psnr,
    save_heatmap,
    ssim,
)


def _rgba(height: int = 24, width: int = 32, seed: int = 0) -> np.ndarray:
    """A random premultiplied image: rgb <= alpha, as an emission-free render would give."""
    rng = np.random.default_rng(seed)
    alpha = rng.random((height, width, 1), dtype=np.float32)
    rgb = rng.random((height, width, 3), dtype=np.float32) * alpha
    return np.concatenate([rgb, alpha], axis=2)


def _smooth(height: int = 48, width: int = 64) -> np.ndarray:
    """A smooth HDR RGB image (peak 4), so structure metrics have structure to see."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    r = 2 + 2 * np.sin(x / 7) * np.cos(y / 5)
    return np.stack([r, 0.5 * r, 4 * x / width], axis=2).astype(np.float32)


# --- sRGB encoding -----------------------------------------------------------------------------------------------


def test_srgb8_known_values() -> None:
    values = to_srgb8(np.array([[[0.0, 1.0, 0.5]]]))
    assert values.dtype == np.uint8
    assert values.tolist() == [[[0, 255, 188]]]


def test_srgb_oetf_is_continuous_at_the_linear_segment_boundary() -> None:
    below, above = srgb_oetf(np.array([0.0031308 - 1e-9, 0.0031308 + 1e-9]))
    assert above - below == pytest.approx(0.0, abs=1e-6)
    assert srgb_oetf(np.array(0.0031308)) == pytest.approx(0.04045, abs=1e-5)


def test_srgb_eotf_inverts_oetf() -> None:
    linear = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_eotf(srgb_oetf(linear)), linear, atol=1e-12)


def test_exposure_plus_one_doubles_linear() -> None:
    rgb = np.random.default_rng(1).random((8, 8, 3)) * 0.5
    np.testing.assert_array_equal(to_srgb8(rgb, exposure=1.0), to_srgb8(2 * rgb))
    np.testing.assert_array_equal(to_srgb8(rgb, exposure=-1.0), to_srgb8(rgb / 2))


def test_tonemaps_compress_highlights_and_clip_negatives() -> None:
    rgb = np.array([[[1.0, 3.0, 1e6]], [[-1.0, np.inf, 0.0]]])
    assert to_srgb8(rgb).tolist() == [[[255, 255, 255]], [[0, 255, 0]]]
    reinhard = to_srgb8(rgb, tonemap="reinhard")
    assert reinhard[0, 0, 0] == round(float(srgb_oetf(np.array(0.5))) * 255)
    assert reinhard[0, 0, 0] < reinhard[0, 0, 1] < reinhard[0, 0, 2] == 255
    aces = to_srgb8(rgb, tonemap="aces")
    assert aces[0, 0, 0] < aces[0, 0, 1] <= aces[0, 0, 2] == 255
    assert aces[1].tolist() == [[0, 255, 0]]


def test_unknown_tonemap_and_nan_are_refused() -> None:
    with pytest.raises(VolrenError, match=r"unknown tone map 'filmic'.*reinhard"):
        to_srgb8(np.zeros((2, 2, 3)), tonemap="filmic")
    with pytest.raises(VolrenError, match="NaN"):
        to_srgb8(np.full((2, 2, 3), np.nan))


# --- compositing and files ---------------------------------------------------------------------------------------


def test_composite_is_premultiplied_over() -> None:
    image = np.array([[[0.2, 0.1, 0.0, 0.5], [0.0, 0.0, 0.0, 0.0], [0.3, 0.6, 0.9, 1.0]]], dtype=np.float32)
    out = composite(image, (1.0, 0.5, 0.25))
    np.testing.assert_allclose(out, [[[0.7, 0.35, 0.125], [1.0, 0.5, 0.25], [0.3, 0.6, 0.9]]], rtol=1e-6)


def test_composite_refuses_bad_shapes() -> None:
    with pytest.raises(VolrenError, match=r"\(H, W, 4\).*\(4, 4, 3\)"):
        composite(np.zeros((4, 4, 3)), (0, 0, 0))
    with pytest.raises(VolrenError, match="background"):
        composite(np.zeros((4, 4, 4)), (0, 0))


def test_png_round_trip_within_quantisation(tmp_path) -> None:
    image = _rgba()
    background = (0.1, 0.2, 0.3)
    path = tmp_path / "sub" / "a.png"
    save_png(path, image, background)
    loaded = load_image(path)
    assert loaded.shape == (24, 32, 3) and loaded.dtype == np.float32
    # Half an 8-bit step in sRGB is at most 0.5/255 * d(linear)/d(srgb) <= 0.5/255 * 2.4/1.055 in linear.
    np.testing.assert_allclose(loaded, composite(image, background), atol=0.5 / 255 * 2.4 / 1.055 + 1e-6)
    np.testing.assert_array_equal(to_srgb8(loaded), to_srgb8(composite(image, background)))


def test_png_alpha_is_premultiplied_on_load(tmp_path) -> None:
    path = tmp_path / "rgba.png"
    iio.imwrite(path, np.array([[[255, 255, 255, 51], [0, 0, 0, 0]]], dtype=np.uint8))
    np.testing.assert_allclose(load_image(path), [[[0.2, 0.2, 0.2, 0.2], [0, 0, 0, 0]]], atol=1e-6)


def test_16_bit_grey_png_loads_as_rgb(tmp_path) -> None:
    path = tmp_path / "grey16.png"
    iio.imwrite(path, np.array([[0, 65535]], dtype=np.uint16))
    np.testing.assert_array_equal(load_image(path), [[[0, 0, 0], [1, 1, 1]]])


def test_npy_round_trip_is_exact(tmp_path) -> None:
    image = _rgba() * 7.5
    path = tmp_path / "a.npy"
    save_linear(path, image)
    loaded = load_image(path)
    assert loaded.dtype == np.float32
    np.testing.assert_array_equal(loaded, image)


def test_side_by_side_puts_left_eye_left(tmp_path) -> None:
    left = np.zeros((10, 6, 4), np.float32)
    right = np.ones((10, 8, 4), np.float32)
    path = tmp_path / "stereo.png"
    save_side_by_side(path, [left, right], (0, 0, 0))
    loaded = load_image(path)
    assert loaded.shape == (10, 14, 3)
    assert loaded[:, :6].max() == 0 and loaded[:, 6:].min() == 1


def test_side_by_side_refuses_bad_input(tmp_path) -> None:
    with pytest.raises(VolrenError, match=r"same height.*\[10, 12\]"):
        save_side_by_side(tmp_path / "s.png", [np.zeros((10, 6, 4)), np.zeros((12, 6, 4))], (0, 0, 0))
    with pytest.raises(VolrenError, match="at least one"):
        save_side_by_side(tmp_path / "s.png", [], (0, 0, 0))


def test_writers_refuse_wrong_suffix_and_unwritable_paths(tmp_path) -> None:
    with pytest.raises(VolrenError, match=r"\.png"):
        save_png(tmp_path / "a.jpg", _rgba(), (0, 0, 0))
    with pytest.raises(VolrenError, match=r"\.npy"):
        save_linear(tmp_path / "a.png", _rgba())
    with pytest.raises(VolrenError, match=r"\(H, W, 4\)"):
        save_linear(tmp_path / "a.npy", np.zeros((4, 4)))
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(VolrenError, match="cannot write"):
        save_srgb8(blocker / "a.png", np.zeros((2, 2, 3), np.uint8))


def test_load_image_errors_name_the_file(tmp_path) -> None:
    missing = tmp_path / "missing.png"
    with pytest.raises(VolrenError, match=r"missing\.png.*does not exist"):
        load_image(missing)
    with pytest.raises(VolrenError, match=r"notes.txt.*unsupported.*\.npy"):
        load_image(tmp_path / "notes.txt")
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"not a png")
    with pytest.raises(VolrenError, match=r"cannot read image.*corrupt\.png"):
        load_image(corrupt)
    bad_npy = tmp_path / "bad.npy"
    bad_npy.write_bytes(b"garbage")
    with pytest.raises(VolrenError, match=r"cannot read.*bad\.npy"):
        load_image(bad_npy)
    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros((4, 4), np.float32))
    with pytest.raises(VolrenError, match=r"flat.npy.*\(4, 4\)"):
        load_image(flat)
    ints = tmp_path / "ints.npy"
    np.save(ints, np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(VolrenError, match=r"ints\.npy.*float"):
        load_image(ints)


# --- metrics -----------------------------------------------------------------------------------------------------


def test_psnr_identical_is_inf() -> None:
    image = _smooth()
    assert psnr(image, image.copy()) == math.inf


def test_psnr_matches_closed_form_with_reference_peak() -> None:
    ref = _smooth()
    test = ref.copy()
    test[0, 0, 0] += 0.25  # 2 -> 2.25, inside [0, peak], so clipping does not touch it
    mse = 0.25**2 / ref.size
    peak = float(ref.max())
    assert peak > 3.9
    assert psnr(ref, test) == pytest.approx(10 * math.log10(peak**2 / mse), rel=1e-9)
    assert psnr(ref, test, data_range=8.0) == pytest.approx(10 * math.log10(8.0**2 / mse), rel=1e-9)
    assert psnr(ref / 4, test / 4, data_range=1.0) == pytest.approx(psnr(ref, test, data_range=4.0), rel=1e-6)


def test_metrics_ignore_alpha_and_do_not_clip_the_test_image() -> None:
    ref = _smooth()
    ref_rgba = np.concatenate([ref, np.ones_like(ref[..., :1])], axis=2)
    assert psnr(ref_rgba, ref) == math.inf
    brighter = ref.copy()
    peak = float(ref.max())
    at_peak = ref == peak
    brighter[at_peak] = 100.0  # above the reference's peak: a true error, not clipped away
    mse = (100.0 - peak) ** 2 * at_peak.sum() / ref.size
    assert psnr(ref_rgba, brighter) == pytest.approx(10 * math.log10(peak**2 / mse), rel=1e-9)


def test_psnr_of_an_image_100x_too_bright_is_the_true_error() -> None:
    # MSE = mean((99 ref)^2) = 99^2 mean(ref^2); PSNR = 10 log10(peak^2 / MSE) over the reference's peak.
    ref = _smooth()
    expected = 10 * math.log10(float(ref.max()) ** 2 / (99.0**2 * float(np.mean(ref.astype(np.float64) ** 2))))
    assert psnr(ref, ref * 100) == pytest.approx(expected, rel=1e-9)
    assert expected < -20.0  # the clipped figure was positive
    result = compare(ref, ref * 100)
    assert result["psnr"] == pytest.approx(expected, rel=1e-9)
    assert result["max_abs_error"] == pytest.approx(99 * ref.max(), rel=1e-6)


def test_a_reference_with_no_signal_is_refused() -> None:
    black = np.zeros((16, 16, 3))
    with pytest.raises(VolrenError, match=r"reference image has no signal \(its peak is 0\)"):
        psnr(black, black + 1)
    with pytest.raises(VolrenError, match="no signal"):
        compare(black, black)
    assert psnr(black, black + 0.5, data_range=1.0) == pytest.approx(10 * math.log10(1 / 0.25))


def test_ssim_identical_is_one_and_falls_with_noise() -> None:
    ref = _smooth()
    rng = np.random.default_rng(2)
    scores = [ssim(ref, ref + rng.normal(0, sigma, ref.shape)) for sigma in (0.0, 0.05, 0.2, 0.8)]
    assert scores[0] == pytest.approx(1.0, abs=1e-12)
    assert scores == sorted(scores, reverse=True) and len(set(scores)) == 4
    assert scores[-1] < 0.5


def test_ssim_refuses_tiny_images() -> None:
    with pytest.raises(VolrenError, match="at least 11x11"):
        ssim(np.ones((8, 8, 3)), np.ones((8, 8, 3)))


def test_flip_is_zero_for_identical_and_positive_otherwise() -> None:
    ref = _smooth()
    assert flip(ref, ref.copy()) == 0.0
    small, large = flip(ref, ref * 0.95), flip(ref, ref * 0.5)
    assert 0.0 < small < large < 1.0


def test_heatmap_is_zero_colour_at_zero_and_saturates_at_25_percent() -> None:
    cmap = matplotlib.colormaps[HEATMAP_COLORMAP]
    zero_colour = np.array(cmap(0.0, bytes=True)[:3])
    top_colour = np.array(cmap(1.0, bytes=True)[:3])
    ref = np.ones((4, 5, 3), np.float32)  # peak 1, so errors below are already normalised
    test = ref.copy()
    test[1] -= 0.125
    test[2] -= 0.25
    test[3] -= 0.9
    heat = error_heatmap(ref, test)
    assert heat.shape == (4, 5, 3) and heat.dtype == np.uint8
    assert (heat[0] == zero_colour).all() and zero_colour.max() < 8  # inferno starts (almost) black
    assert (heat[1] == np.array(cmap(0.5, bytes=True)[:3])).all()
    assert (heat[2] == top_colour).all() and (heat[3] == top_colour).all()
    # Normalised by the reference's peak: scaling both images leaves the map unchanged.
    np.testing.assert_array_equal(error_heatmap(ref * 50, test * 50), heat)


def test_compare_reports_all_metrics() -> None:
    ref = _smooth()
    test = ref * 0.9
    result = compare(ref, test)
    assert set(result) == {"psnr", "ssim", "flip", "max_abs_error", "mean_abs_error", "data_range"}
    assert result["data_range"] == pytest.approx(ref.max())
    assert result["max_abs_error"] == pytest.approx(0.1 * ref.max(), rel=1e-5)
    assert result["mean_abs_error"] == pytest.approx(0.1 * ref.mean(), rel=1e-5)
    assert result["psnr"] == pytest.approx(psnr(ref, test))
    assert all(isinstance(value, float) for value in result.values())


def test_compare_errors_are_clear() -> None:
    ref = _smooth()
    with pytest.raises(VolrenError, match=r"reference \(48, 64, 3\), test \(48, 60, 3\)"):
        compare(ref, ref[:, :60])
    with pytest.raises(VolrenError, match=r"test image contains NaN"):
        compare(ref, np.where(ref > 3, np.nan, ref))
    with pytest.raises(VolrenError, match=r"reference image must have shape.*\(48, 64\)"):
        compare(ref[..., 0], ref)
    with pytest.raises(VolrenError, match="data_range must be a positive"):
        compare(ref, ref, data_range=0.0)


def test_compare_files_and_heatmap(tmp_path) -> None:
    ref = np.concatenate([_smooth(), np.ones((48, 64, 1), np.float32)], axis=2)
    test = ref * 0.8
    save_linear(tmp_path / "ref.npy", ref)
    save_linear(tmp_path / "test.npy", test)
    heat_path = tmp_path / "heat.png"
    result = compare_files(tmp_path / "ref.npy", tmp_path / "test.npy", heat_path)
    assert result == compare(ref, test)
    np.testing.assert_array_equal(iio.imread(heat_path), error_heatmap(ref, test))
    save_heatmap(tmp_path / "heat2.png", ref, test)
    assert heat_path.read_bytes() == (tmp_path / "heat2.png").read_bytes()


def test_compare_files_errors_name_both_files(tmp_path) -> None:
    save_linear(tmp_path / "a.npy", np.ones((16, 16, 4), np.float32))
    save_linear(tmp_path / "b.npy", np.ones((16, 12, 4), np.float32))
    save_linear(tmp_path / "black.npy", np.zeros((16, 16, 4), np.float32))
    with pytest.raises(VolrenError, match=r"a.npy' is \(16, 16, 4\).*b.npy' is \(16, 12, 4\)"):
        compare_files(tmp_path / "a.npy", tmp_path / "b.npy")
    with pytest.raises(VolrenError, match=r"nope\.npy.*does not exist"):
        compare_files(tmp_path / "a.npy", tmp_path / "nope.npy")
    with pytest.raises(VolrenError, match=r"reference '.*black\.npy' has no signal \(its brightest value is 0\)"):
        compare_files(tmp_path / "black.npy", tmp_path / "a.npy")

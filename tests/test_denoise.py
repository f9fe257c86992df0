"""The VPT denoisers of paper 002 §5 (ours) and its baselines (SVGF, WRLS).

Most tests feed the denoisers synthetic per-path records (noise-free fields, so every step has a closed form) and
compare with that form; two render the phantom against a high-spp reference."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from conftest import DEVICE, hard_phantom
from volren.bench.vpt import detail_kept
from volren.camera import Camera
from volren.kernels.common import CameraGPU
from volren.metrics import psnr
from volren.render import VPT, VPTConfig
from volren.render.compositing.surfaces import view_buffers
from volren.render.vpt.denoise import (
    CHANGE_UNIT,
    FRAMES_MAX,
    NOISE_Z,
    SIGMA_C,
    SIGMA_E,
    SIGMOID_A,
    WEIGHT_B,
    WRLS,
    Denoiser,
    reproject,
)
from volren.upload import camera_struct

H, W, N = 16, 20, 4
DEPTH = 2.0
CAM = Camera(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, -1.0), width=W, height=H, fov_y=40.0)


def records(f_x, f_l=1.0, albedo=0.0, f_m=0.0, hits=None, depth=DEPTH, opacity=None):
    """Per-path records (H, W, N): scalars or arrays broadcast to grey vec3 fields; ``hits`` (H, W, N) bool; the
    per-path opacity by default the hit indicator (a ratio tracker that agrees with the delta tracker)."""
    def vec(v):
        v = np.broadcast_to(np.asarray(v, np.float32), (H, W, N))
        return wp.array(np.repeat(v[..., None], 3, -1).copy(), dtype=wp.vec3, device=DEVICE)

    hit = np.ones((H, W, N), bool) if hits is None else hits
    d = np.where(hit, np.broadcast_to(np.float32(depth), (H, W, N)), -1.0).astype(np.float32)
    return SimpleNamespace(f_x=vec(f_x), f_l=vec(f_l), albedo=vec(albedo), f_m=vec(f_m),
                           emission=wp.zeros((1, 1, 1), dtype=wp.vec3, device=DEVICE),  # nothing emits
                           depth=wp.array(d, dtype=float, device=DEVICE),
                           density=wp.array(np.ones((H, W, N), np.float32), dtype=float, device=DEVICE),
                           opacity=wp.array(np.broadcast_to(np.asarray(hit if opacity is None else opacity, np.float32),
                                                            (H, W, N)).copy(), dtype=float, device=DEVICE))


def run(denoiser, frames, cams=None) -> list[np.ndarray]:
    """Denoise a sequence of records (one view); the RGBA outputs."""
    out = []
    for i, rec in enumerate(frames):
        cam = CAM if cams is None else cams[i]
        buffers = view_buffers(cam, DEVICE)
        denoiser.run(0, camera_struct(cam), rec, buffers)
        out.append(buffers.image.numpy())
    return out


def grey(v) -> float:
    return math.sqrt(3.0) * v  # |(v, v, v)|


def test_eq11_joint_bilateral_on_a_checkerboard():
    """F_x alternating 0.5 / 0.55 (one class per pixel), F_L = 1: an interior pixel is the Eq. 11 mean of itself,
    its 4 diagonal (equal) and 4 edge (other) neighbours, weights 1 and exp(-|dF_x| / sigma_c)."""
    rows, cols = np.mgrid[0:H, 0:W]
    board = np.where((rows + cols) % 2 == 0, 0.5, 0.55)[..., None]
    image = run(Denoiser(DEVICE), [records(board)])[0]
    w = math.exp(-grey(0.05) / SIGMA_C)
    for v, other in ((0.5, 0.55), (0.55, 0.5)):
        expected = (5 * v + 4 * w * other) / (5 + 4 * w)
        inner = (board[1:-1, 1:-1, 0] == v)
        np.testing.assert_allclose(image[1:-1, 1:-1, 0][inner], expected, rtol=1e-4)


def test_eq12_blends_the_previous_hdln_component():
    """A uniform F_x steps from 0.5 to 0.6 (static camera, F_L = 1): (0.6 + w 0.5) / (1 + w), Eq. 12's w for equal
    n = exp(-|dF_x| / sigma_e)."""
    out = run(Denoiser(DEVICE), [records(0.5), records(0.6)])[1]
    w = math.exp(-grey(0.1) / SIGMA_E)
    np.testing.assert_allclose(out[..., 0], (0.6 + w * 0.5) / (1 + w), rtol=1e-4)


def test_eq12_history_counts_its_accumulated_frames():
    """F_x 0.5 for three static frames, then 0.6: the history has accumulated 3 frames (1, 1 + 1, 1 + 2; below
    FRAMES_MAX), so Eq. 12's weight counts 3 times: (0.6 + 3 w 0.5) / (1 + 3 w), w = exp(-|dF_x| / sigma_e)."""
    assert FRAMES_MAX >= 3
    out = run(Denoiser(DEVICE), [records(0.5), records(0.5), records(0.5), records(0.6)])[3]
    w = 3 * math.exp(-grey(0.1) / SIGMA_E)
    np.testing.assert_allclose(out[..., 0], (0.6 + w * 0.5) / (1 + w), rtol=1e-4)


def test_eq12_sigma_widens_with_the_noise_of_f_x():
    """F_x exactly 0.5, then paths at 0.56 / 0.64 (one class, mean 0.6, standard error of the mean 0.0231): Eq. 12's
    sigma_e grows by NOISE_Z standard errors (as a grey vec3 length), so the history keeps more weight than at 0.2."""
    noisy = np.broadcast_to(np.array([0.56, 0.64, 0.56, 0.64], np.float32), (H, W, N))
    out = run(Denoiser(DEVICE), [records(0.5), records(noisy)])[1]
    error = math.sqrt(np.var([0.56, 0.64, 0.56, 0.64]) / 3)
    w = math.exp(-grey(0.1) / (SIGMA_E + NOISE_Z * grey(error)))
    np.testing.assert_allclose(out[..., 0], (0.6 + w * 0.5) / (1 + w), rtol=1e-4)


def test_eq13_blends_the_previous_ldhn_component():
    """A uniform F_L steps from 1 to 1.05 (F_x = 0.5): Eq. 13's w_hat = 1 + exp(-a (change - 1)) with the relative
    change in units of CHANGE_UNIT, w_k = 1 + b / w_hat."""
    out = run(Denoiser(DEVICE), [records(0.5, 1.0), records(0.5, 1.05)])[1]
    change = 0.05 / (CHANGE_UNIT * 0.5 * 2.05)
    w_hat = 1 + math.exp(-SIGMOID_A * (change - 1))
    w_k = 1 + WEIGHT_B / (1e-6 + w_hat)
    np.testing.assert_allclose(out[..., 0], 0.5 * (w_k * 1.05 + w_hat) / (w_k + w_hat), rtol=1e-4)


def test_eq14_blends_the_previous_opacity():
    """Alpha steps from 1 (4 of 4 paths hit) to 1/2 (2 of 4): (a + e a_prev) / (1 + e), e = exp(-(1 + |a - a_prev|))."""
    half = np.zeros((H, W, N), bool)
    half[..., :2] = True
    out = run(Denoiser(DEVICE), [records(0.5), records(0.5, hits=half)])[1]
    e = math.exp(-1.5)
    np.testing.assert_allclose(out[..., 3], (0.5 + e) / (1 + e), rtol=1e-4)


def test_clustering_keeps_the_product_of_correlated_components():
    """Half the paths hit a lit bright material (F_x = 1, F_L = 1), half a dark one in shadow (F_x = 0.1, F_L = 0):
    Eq. 10's two classes give 0.5 (the per-path mean of F_x F_L); one class would give 0.55 * 0.5 = 0.275."""
    f_x = np.broadcast_to(np.array([1.0, 1.0, 0.1, 0.1], np.float32), (H, W, N))
    f_l = np.broadcast_to(np.array([1.0, 1.0, 0.0, 0.0], np.float32), (H, W, N))
    out = run(Denoiser(DEVICE), [records(f_x, f_l)])[0]
    np.testing.assert_allclose(out[..., 0], 0.5, atol=0.005)


def test_the_second_part_carries_albedo_times_f_m():
    """Eq. 8 with both parts: F_x F_L + A F_m, each part filtered with its own guide (uniform fields: exact)."""
    out = run(Denoiser(DEVICE), [records(0.4, 2.0, albedo=0.7, f_m=0.5)])[0]
    np.testing.assert_allclose(out[..., 0], 0.4 * 2.0 + 0.7 * 0.5, rtol=1e-5)


def test_pixels_without_hits_are_filled_from_their_neighbours():
    """Isolated pixels none of whose paths hit, in a medium of ratio-tracked opacity 0.9 everywhere (a black dot each
    without filling: alpha 0.9 over no shading), take their neighbours' class and depth: 0.9 * 0.8 like them."""
    hits = np.ones((H, W, N), bool)
    holes = np.zeros((H, W), bool)
    holes[2:-2:5, 2:-2:5] = True
    hits[holes] = False
    out = run(Denoiser(DEVICE), [records(0.5, 1.6, hits=hits, opacity=0.9)])[0]
    np.testing.assert_allclose(out[..., 3][holes], 0.9, rtol=1e-5)
    np.testing.assert_allclose(out[..., 0][holes], 0.9 * 0.8, rtol=1e-4)


def test_alpha_is_the_ratio_tracked_opacity_without_a_spatial_filter():
    """Every path hits (N_p / N = 1) but the ratio tracker says 0.3 in a checkerboard against 0.7: the output alpha is
    each pixel's own ratio-tracked mean (no spatial blur), and the shading is composited with it (Eq. 15)."""
    rows, cols = np.mgrid[0:H, 0:W]
    board = np.where((rows + cols) % 2 == 0, 0.3, 0.7)[..., None]
    out = run(Denoiser(DEVICE), [records(0.5, 1.0, opacity=board)])[0]
    np.testing.assert_allclose(out[..., 3], board[..., 0], rtol=1e-5)
    np.testing.assert_allclose(out[..., 0], 0.5 * board[..., 0], rtol=1e-4)


def test_an_empty_pixel_outside_a_silhouette_stays_empty():
    """A straight silhouette: pixels outside it have only 3 hit neighbours of 8, too few to be filled."""
    hits = np.zeros((H, W, N), bool)
    hits[:, : W // 2] = True
    out = run(Denoiser(DEVICE), [records(0.5, hits=hits)])[0]
    assert out[:, W // 2 :, 3].max() == 0.0


def panning(frames: int, shift_px: int = 2, period_px: int = 8):
    """A fronto-parallel plane at DEPTH with stripes (F_x 0.2 / 1.2, F_L 1 / 2) seen by a camera moving sideways by
    ``shift_px`` pixels per frame: the cameras, the records, and each frame's true radiance."""
    pixel = 2 * DEPTH * CAM.tan_half_fov * (W / H) / W  # [m] one pixel's width on the plane
    cams, recs, truth = [], [], []
    for f in range(frames):
        x0 = f * shift_px * pixel
        cam = Camera(position=(x0, 0.0, 0.0), look_at=(x0, 0.0, -1.0), width=W, height=H, fov_y=CAM.fov_y)
        d = cam.ray_directions()
        x = x0 + d[..., 0] * DEPTH / -d[..., 2]
        stripe = (np.floor(x / (period_px / 2 * pixel) + 1e-3) % 2)[..., None]
        cams.append(cam)
        recs.append(records(np.where(stripe == 1, 1.2, 0.2), np.where(stripe == 1, 2.0, 1.0)))
        truth.append(np.where(stripe[..., 0] == 1, 2.4, 0.2))
    return cams, recs, truth


def test_reprojection_follows_the_previous_camera():
    """A camera panning over a striped plane: reprojected by the previous camera the history agrees with the current
    frame and the output stays exact; read with the current camera, Eq. 13 blends in the neighbouring stripe."""
    cams, recs, truth = panning(4)
    out = run(Denoiser(DEVICE), recs, cams)
    for f in (1, 2, 3):
        np.testing.assert_allclose(out[f][..., 0], truth[f], atol=0.01)


@wp.kernel
def reproject_kernel(cam: CameraGPU, prev: CameraGPU, depth: float, out: wp.array2d(dtype=wp.vec2i)):
    row, col = wp.tid()
    out[row, col] = reproject(cam, prev, row, col, depth)


def test_reprojection_maps_pixels_by_the_camera_motion():
    """Static: every pixel to itself; a sideways move of 2 pixels at the plane's depth: to the pixel 2 columns on."""
    cams, _, _ = panning(2)
    out = wp.zeros((H, W), dtype=wp.vec2i, device=DEVICE)
    rows, cols = np.mgrid[0:H, 0:W]
    wp.launch(reproject_kernel, dim=(H, W), inputs=[camera_struct(CAM), camera_struct(CAM), DEPTH, out],
              device=DEVICE)
    np.testing.assert_array_equal(out.numpy(), np.stack([rows, cols], -1))
    wp.launch(reproject_kernel, dim=(H, W), inputs=[camera_struct(cams[1]), camera_struct(cams[0]), DEPTH, out],
              device=DEVICE)
    inside = cols < W - 2
    np.testing.assert_array_equal(out.numpy()[inside], np.stack([rows, cols + 2], -1)[inside])
    assert (out.numpy()[~inside] == -1).all()


def test_wrls_regresses_on_the_albedo_feature():
    """A noise-free albedo checkerboard (0.2 / 0.8) under F_L = 1: the per-pixel linear model in the albedo
    luminance reproduces it (up to the prior P0's slight ridge bias, 0.012 measured); the final bilateral mixes in
    exp(-0.6 / sigma_c) of the 4 edge neighbours. Without the feature the 3x3 fit blurs it (errors ~0.25)."""
    rows, cols = np.mgrid[0:H, 0:W]
    board = np.where((rows + cols) % 2 == 0, 0.2, 0.8)[..., None]
    out = run(WRLS(DEVICE), [records(board, 0.0, albedo=board, f_m=1.0)])[0]
    w = math.exp(-0.6 / SIGMA_C)
    inner = out[1:-1, 1:-1, 0]
    expected = np.where(board[1:-1, 1:-1, 0] == 0.2, (5 * 0.2 + 4 * w * 0.8), (5 * 0.8 + 4 * w * 0.2)) / (5 + 4 * w)
    np.testing.assert_allclose(inner, expected, atol=0.03)


def test_wrls_accumulates_over_frames():
    """Noisy F_m (uniform truth 1, per-path noise) on a static view: the recursive fit's error after 8 frames is well
    below its first frame's (one 3x3 fit)."""
    rng = np.random.default_rng(3)
    frames = [records(0.0, 0.0, albedo=0.5, f_m=1.0 + 0.5 * rng.standard_normal((H, W, N))) for _ in range(8)]
    out = run(WRLS(DEVICE), frames)
    err = [float(np.sqrt(np.mean((o[2:-2, 2:-2, 0] - 0.5) ** 2))) for o in out]
    assert err[-1] < 0.6 * err[0], err


@pytest.fixture(scope="module")
def phantom():
    """The hard-edged phantom: issue 13's smooth skull has too little fine detail for the detail-kept floor to tell
    the paper's split from the albedo-only one."""
    scene = hard_phantom(64)
    cam = Camera(position=(1.6, 1.2, 2.4), width=64, height=54, fov_y=40.0)
    ref = VPT(VPTConfig(spp=256, transfer="ct-muscle"), device=DEVICE).render(scene, [cam]).images[0]
    return scene, cam, ref


def test_denoiser_beats_the_raw_frames_and_keeps_detail(phantom):
    """Phantom (ct-muscle), 64x54, 4 spp, 6 frames, against 256 spp. Measured: raw 20.9 dB, denoised 28.5 dB; the
    denoised frame keeps 0.72 of the reference's 0-1 px band (0.46 with the albedo alone as F_x, the split before
    paper 002 §5.1's SDF went into F_x); frame-to-frame change 0.27 of the raw frames'. Floors: +3 dB, 0.6 of the
    band, half the change."""
    scene, cam, ref = phantom
    raw = VPT(VPTConfig(spp=4, transfer="ct-muscle"), device=DEVICE)
    den = VPT(VPTConfig(spp=4, transfer="ct-muscle", denoise="ours"), device=DEVICE)
    raws = [raw.render(scene, [cam], f).images[0] for f in range(6)]
    dens = [den.render(scene, [cam], f).images[0] for f in range(6)]
    assert psnr(ref, dens[-1]) > psnr(ref, raws[-1]) + 3.0
    assert detail_kept(ref, dens[-1]) > 0.6
    assert np.abs(dens[-1] - dens[-2]).mean() < 0.5 * np.abs(raws[-1] - raws[-2]).mean()


def test_ratio_tracked_alpha_beats_the_hit_share(phantom):
    """Phantom, 64x54, one 4-spp frame (no history): the denoiser's alpha, the paths' mean ratio-tracked opacity,
    is closer to the 256-spp alpha than the raw frame's N_p / N (§5.3.3's advice for low spp) on the pixels of
    fractional alpha. Measured RMSE there over frames 0, 3, 5: 0.155-0.171 against 0.185-0.205 (the rest is the
    jittered rays' hit-or-miss across sharp silhouettes, which no transmittance estimator removes)."""
    scene, cam, ref = phantom
    raw = VPT(VPTConfig(spp=4, transfer="ct-muscle"), device=DEVICE).render(scene, [cam], 3).images[0]
    den = VPT(VPTConfig(spp=4, transfer="ct-muscle", denoise="ours"), device=DEVICE).render(scene, [cam], 3).images[0]
    fringe = (ref[..., 3] > 0.02) & (ref[..., 3] < 0.98)
    raw_err, den_err = (np.sqrt(((img[..., 3] - ref[..., 3])[fringe] ** 2).mean()) for img in (raw, den))
    assert den_err < 0.9 * raw_err, (den_err, raw_err)

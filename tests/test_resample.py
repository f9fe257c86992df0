"""CMSRM's cube resampling pass (issue 24): `cube_resample_kernel` finishes every pixel whose ray meets no box or one
cube-scheme box with one lookup and defers the rest (rims to march, several boxes, mesh layers) to
`layered_resample_kernel`. The split must not change a bit: pixel-rt sends every pixel through the layered kernel,
so it is the reference the one-box pass is held to."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from conftest import DEVICE
from volren.camera import Camera
from volren.data import builtin_scene
from volren.render import CMSRM, CMSRMConfig
from volren.render.marching.cubemap import cube_quad, cube_sample
from volren.scene import Environment, Scene, Volume, scale_translate

W, H = 96, 64
CAM = Camera(position=(0.9, 0.7, 2.4), width=W, height=H)
"""off-axis and near: three faces, silhouettes and face rims in view, the cube scheme (hybrid off)"""


@pytest.fixture(scope="module")
def cloud():
    return builtin_scene("cloud", 64)


def render(scene, **kw):
    cfg = CMSRMConfig(samples=64, light_samples=16, light_grid=16, hybrid=False, **kw)
    frame = CMSRM(cfg, "cpu").render(scene, [CAM])
    assert {p["scheme"] for p in frame.stats.info["volumes"][0]} == {"cube"}
    return frame


@pytest.mark.parametrize("faces", ["interior", "exterior"])
@pytest.mark.parametrize("mode", ["dvr", "mip"])
def test_one_box_pass_matches_the_layered_kernel(cloud, faces, mode):
    """Tiled and pixel-sort layer finding take the one-box pass, pixel-rt the layered kernel for every pixel: the
    same image and depth to the bit, the same marching counters, and box tests one per pixel for pixel-sort."""
    frames = {oit: render(cloud, oit=oit, cube_faces=faces, mode=mode) for oit in ("tiled", "pixel-sort", "pixel-rt")}
    layered = frames["pixel-rt"]
    assert layered.stats.info["deferred_pixels"] == [W * H]
    for oit in ("tiled", "pixel-sort"):
        frame = frames[oit]
        assert frame.stats.info["deferred_pixels"][0] < W * H // 10  # the rims marched directly, if any
        np.testing.assert_array_equal(frame.images[0], layered.images[0])
        np.testing.assert_array_equal(frame.depths[0], layered.depths[0])
        for counter in ("density_samples", "rays", "lightmap_lookups", "skipped_steps"):
            assert frame.stats.counters[counter] == layered.stats.counters[counter], (oit, counter)
    assert frames["pixel-sort"].stats.counters["box_tests"] == W * H
    assert (layered.images[0][..., 3] > 0.01).sum() > W * H // 20  # not an empty view


def test_deferred_pixels_are_the_rim_marches(cloud):
    """With ``rim_direct`` the pixels deferred are exactly those marched directly (the rays counter's excess over the
    texel rays, which do not depend on it); without it none is deferred."""
    rim = render(cloud)
    plain = render(cloud, rim_direct=False)
    deferred = rim.stats.info["deferred_pixels"][0]
    assert deferred > 0
    assert deferred == rim.stats.counters["rays"] - plain.stats.counters["rays"]
    assert plain.stats.info["deferred_pixels"] == [0]


@pytest.mark.parametrize("kw", [{}, {"rim_direct": False}, {"oit": "pixel-rt"}])
def test_progress_reports_every_row_once(cloud, kw):
    """`on_rows` gets the view's rows once in total, whether some, none or every pixel is deferred."""
    renderer = CMSRM(CMSRMConfig(samples=64, light_samples=16, light_grid=16, hybrid=False, **kw), "cpu")
    reported = []
    renderer.on_rows = reported.append
    renderer.render(cloud, [CAM])
    assert sum(reported) == H


def test_a_direct_box_beside_a_cube_box_is_marched():
    """Hybrid: a near box read from its cube map and a far one marched directly, side by side on screen. The one-box
    pass leaves the direct box's pixels to the layered kernel (it has no map to read): the same bits as pixel-rt."""
    n = 16
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n)] * 3, indexing="ij")
    density = np.clip(1.2 - np.sqrt(x * x + y * y + z * z), 0.0, 1.0).astype(np.float32)
    near = Volume(density, scale_translate(0.5, (-0.5, 0.0, 0.5)), density_scale=4.0, emission=(3.0, 0.2, 0.2))
    far = Volume(density, scale_translate(0.2, (1.2, 0.3, -1.5)), density_scale=4.0, emission=(0.2, 0.2, 3.0))
    scene = Scene((near, far), (), Environment(0.0))
    cam = Camera(position=(0.0, 0.0, 3.0), width=W, height=H)
    frames = {oit: CMSRM(CMSRMConfig(samples=64, light_samples=16, light_grid=16, cube_size=8, oit=oit),
                         "cpu").render(scene, [cam]) for oit in ("tiled", "pixel-rt")}
    assert [p["scheme"] for p in frames["tiled"].stats.info["volumes"][0]] == ["cube", "direct"]
    assert frames["tiled"].stats.info["deferred_pixels"][0] < W * H // 4
    np.testing.assert_array_equal(frames["tiled"].images[0], frames["pixel-rt"].images[0])
    np.testing.assert_array_equal(frames["tiled"].depths[0], frames["pixel-rt"].depths[0])
    far_pixels = frames["tiled"].images[0][..., 2] > 0.05
    assert far_pixels.sum() > 20  # the far box is in view


@wp.kernel
def sample_quad_kernel(color: wp.array(dtype=wp.vec4), z_end: wp.array(dtype=float), p: wp.vec3, size: int,
                       z_pixel: float, k_z: float, out: wp.array(dtype=wp.vec4), rim: wp.array(dtype=int)):
    idx, b, r = cube_quad(0, size, p)
    out[0] = cube_sample(color, z_end, idx, b, z_pixel, k_z)
    rim[0] = r


def test_cube_sample_edge_stops_and_falls_back_to_plain_bilinear():
    """Paper 001 §3.2's filter on one 2x2 quad of face +z (4 x 4 texels, the lookup between texels (1, 1)-(2, 2)):
    bilinear weights times w_z; a texel whose ray ends at the pixel's depth keeps the lookup alone where the others
    end 1 m away (k_z = 5: w_z = 0), and where every w_z is 0 the plain bilinear weights are used, not a blank; a
lookup within half a texel of any of the face's four edges is a rim lookup."""
    size = 4
    color = np.zeros((6 * size * size, 4), np.float32)
    z_end = np.full(6 * size * size, 9.0, np.float32)
    texels = {(1, 1): 0.1, (2, 1): 0.2, (1, 2): 0.3, (2, 2): 0.4}  # (i, j) of face 4 (+z) -> red
    for (i, j), red in texels.items():
        color[(4 * size + j) * size + i] = (red, 0.0, 0.0, 1.0 - red)
    fx, fy = 0.25, 0.75
    p = wp.vec3(-1.0 + (1.5 + fx) * 2.0 / size, -1.0 + (1.5 + fy) * 2.0 / size, 1.0)
    weights = {(1, 1): (1 - fx) * (1 - fy), (2, 1): fx * (1 - fy), (1, 2): (1 - fx) * fy, (2, 2): fx * fy}
    plain = sum(w * texels[k] for k, w in weights.items())

    def sample(z_pixel: float, p: wp.vec3 = p) -> tuple[float, int]:
        out = wp.zeros(1, dtype=wp.vec4, device=DEVICE)
        rim = wp.zeros(1, dtype=int, device=DEVICE)
        wp.launch(sample_quad_kernel, dim=1, inputs=[wp.array(color, dtype=wp.vec4, device=DEVICE),
                  wp.array(z_end, dtype=float, device=DEVICE), p, size, z_pixel, 5.0, out, rim], device=DEVICE)
        return float(out.numpy()[0, 0]), int(rim.numpy()[0])

    z_end[(4 * size + 2) * size + 1] = 8.0  # texel (1, 2) ends 1 m nearer than the others
    np.testing.assert_allclose(sample(8.0)[0], 0.3, rtol=1e-6)
    np.testing.assert_allclose(sample(9.0)[0], (plain - weights[(1, 2)] * 0.3) / (1 - weights[(1, 2)]), rtol=1e-6)
    value, rim = sample(3.0)
    np.testing.assert_allclose(value, plain, rtol=1e-6)
    assert rim == 0
    # within half a texel of a face edge, on every side, the quad straddles it (`rim_needs_march` then decides)
    h = 2.0 / size
    for x, y in ((-1 + 0.2 * h, 0.1), (1 - 0.2 * h, 0.1), (0.1, -1 + 0.2 * h), (0.1, 1 - 0.2 * h)):
        assert sample(9.0, wp.vec3(x, y, 1.0))[1] == 1, (x, y)

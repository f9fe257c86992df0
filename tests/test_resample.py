"""CMSRM's cube resampling pass (issue 24): `cube_resample_kernel` finishes every pixel whose ray meets no box or one
cube-scheme box with one lookup and defers the rest (rims to march, several boxes, mesh layers) to
`layered_resample_kernel`. The split must not change a bit: pixel-rt sends every pixel through the layered kernel,
so it is the reference the one-box pass is held to."""

from __future__ import annotations

import numpy as np
import pytest

from volren.camera import Camera
from volren.data import builtin_scene
from volren.render import CMSRM, CMSRMConfig
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

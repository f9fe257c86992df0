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

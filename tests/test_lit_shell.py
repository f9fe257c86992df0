"""The lit shell of a box (issue 19 item 3): light-map methods against the reference where light enters a face.

A uniform medium lit straight down, at the default light grid (half the density resolution: 4^3 for the 8^3 box,
24x6x4 for the slab). With the light map's values at voxel centres, half a light voxel inside the faces, and lookups
clamped there, DSSRM's mean radiance was 0.958 of the reference on the box (top lit rows 0.62-0.69, bottom rows up
to 1.60) and 0.945 on the slab (rows 0.74-1.21), CMSRM and CACRM alike. With the nodes on the faces and the optical
depth interpolated (`volren.render.lightmap`) all three measure 1.000 on both, every lit row within 0.1%; since issue
47 the nodes hold the mean extinction along the path, exact in any uniform medium, so the node placement, the reach
of the lookups and what they interpolate show only in media that vary: the graded and bumpy boxes at the end. CMSRM and
CACRM on the box with the 8-texel cube faces of the face sizing before issue 19 item 4 kept the mean within 1%
(0.996) but not the rows (0.92-1.23), so the row test runs them at 256-texel faces: the light map's rows alone.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera
from volren.render import CACRM, CMSRM, DSSRM, CACRMConfig, CMSRMConfig, DSSRMConfig, Reference, ReferenceConfig
from volren.scene import DirectionalLight, Environment, Scene, Volume, scale_translate

DOWN = DirectionalLight(direction=(0.0, -1.0, 0.0), irradiance=(2.0, 2.0, 2.0))
SCENES = {
    # 8^3 voxels in [-1, 1]^3, seen from the side
    "box": ((8, 8, 8), 1.0, Camera(position=(0.0, 0.0, 3.5), width=48, height=48, fov_y=45)),
    # 16 x 2 x 1 m, 48x12x8 voxels, seen from above at 45 degrees (its lit top and a side)
    "slab": ((8, 12, 48), (8.0, 1.0, 0.5), Camera(position=(0.0, 8.0, 8.0), look_at=(0.0, 0.0, 0.0), width=64,
                                                  height=32, fov_y=30)),
}
METHODS = {
    "dssrm": lambda **kw: DSSRM(DSSRMConfig(**kw), device=DEVICE),
    "cmsrm": lambda **kw: CMSRM(CMSRMConfig(**kw), device=DEVICE),
    "cacrm": lambda **kw: CACRM(CACRMConfig(**kw), device=DEVICE),
}


def scene(name: str) -> Scene:
    shape, scale, _ = SCENES[name]
    box = Volume(np.ones(shape, np.float32), scale_translate(scale, (0.0, 0.0, 0.0)), density_scale=2.0, albedo=1.0)
    return Scene((box,), (DOWN,), Environment(0.0))


@cache
def reference(name: str) -> np.ndarray:
    return Reference(ReferenceConfig(samples=256, light_samples=256), device=DEVICE).render(
        scene(name), [SCENES[name][2]]).images[0]


def rendered(name: str, method: str, **config) -> np.ndarray:
    return METHODS[method](**config).render(scene(name), [SCENES[name][2]]).images[0]


def lit_rows(ref: np.ndarray, img: np.ndarray) -> np.ndarray:
    """Per image row (those the box covers), the method's mean radiance over the reference's."""
    r = ref[..., :3].mean(axis=(1, 2))
    return img[..., :3].mean(axis=(1, 2))[r > 1e-3] / r[r > 1e-3]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", SCENES)
def test_mean_radiance_within_one_percent_at_defaults(name, method):
    ref = reference(name)
    img = rendered(name, method)
    assert img[..., :3].mean() / ref[..., :3].mean() == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", SCENES)
def test_every_lit_row_matches_the_reference(name, method):
    """Row by row, the lit top first: within 1% (was 0.62-1.60). CMSRM and CACRM at 256-texel cube faces, so the
    rows test the light map and not the cube faces' size (issue 19 item 4)."""
    ref = reference(name)
    img = rendered(name, method) if method == "dssrm" else rendered(name, method, cube_size=256)
    rows = lit_rows(ref, img)
    assert len(rows) >= 10
    np.testing.assert_allclose(rows, 1.0, atol=0.01)


def varying_scene(name: str) -> Scene:
    n = 8
    z, y, x = np.meshgrid(*[-1 + (np.arange(n) + 0.5) * 2 / n] * 3, indexing="ij")
    rho = {"graded": 0.1 + 0.9 * ((1 - y) / 2) ** 2 * (1 + 0.5 * np.sin(3 * x)),
           "bumpy": 0.55 + 0.45 * np.sin(3 * x + 1) * np.cos(2 * y) * np.cos(2.5 * z + 0.3)}[name]
    box = Volume(rho.astype(np.float32), scale_translate(1.0, (0.0, 0.0, 0.0)), density_scale=3.0, albedo=1.0)
    return Scene((box,), (DirectionalLight(direction=(0.2, -1.0, 0.1), irradiance=2.0),), Environment(0.0))


@pytest.mark.parametrize(("name", "low", "high"), [("graded", 0.965, 1.03), ("bumpy", 0.98, 1.015)])
def test_lit_rows_of_varying_media_match_the_reference(name, low, high):
    """An 8^3 box whose density grows with depth (graded) or varies on every axis (bumpy), lit from above at the
    default light grid (8^3: the floor of 8 nodes per axis): every lit row of DSSRM within [low, high] of the
    reference (measured 0.973-1.000 and 0.986-1.004). Light-map nodes at voxel centres instead of on the faces give
    rows up to 1.23 (graded) and 0.959 (bumpy), lookups clamped half a light voxel inside 1.14 (graded), and
    interpolating T instead of the optical depth 1.024 (bumpy)."""
    cam = SCENES["box"][2]
    ref = Reference(ReferenceConfig(samples=256, light_samples=256), device=DEVICE).render(
        varying_scene(name), [cam]).images[0]
    rows = lit_rows(ref, DSSRM(DSSRMConfig(), device=DEVICE).render(varying_scene(name), [cam]).images[0])
    assert len(rows) >= 20
    assert low <= rows.min() and rows.max() <= high, (rows.min(), rows.max())

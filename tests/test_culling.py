"""Empty-tile culling (paper 000 §3, coarse phase): sound (a culled tile's rays meet only zero density), effective,
and invisible in the image."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scipy import ndimage

from conftest import DEVICE, face_point_np
from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.render import CACRM, CMSRM, CACRMConfig, CMSRMConfig
from volren.render.cubemap import tile_occupancy_kernel, visible_faces
from volren.scene import Volume
from volren.upload import coarse_max_level


def sampled_density(density: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Trilinear density at local points p (..., 3), clamped at the border, as the kernels sample it."""
    n = np.array(density.shape[::-1])
    f = np.clip((p + 1) * 0.5 * n - 0.5, 0, n - 1)
    return ndimage.map_coordinates(density, [f[..., 2].ravel(), f[..., 1].ravel(), f[..., 0].ravel()], order=1,
                                   mode="nearest").reshape(p.shape[:-1])


@pytest.mark.parametrize("level", [0, 2])
@pytest.mark.parametrize("eye", [(0.3, 0.2, 3.0), (2.5, 1.5, -2.0), (0.2, -0.1, 0.3)])
def test_culled_tiles_only_see_zero_density(eye, level):
    """At tile level l > 0 the tile also marches an apron ring of one level-l texel (2^l texels) around it, wrapped
    onto the adjacent face at an edge: those rays must see zero density too."""
    size, tile = 32, 8
    density = np.zeros((32, 32, 32), np.float32)
    density[20:28, 18:30, 4:14] = 1.0  # one block: most tiles' rays miss it
    vol = Volume(density)
    grid = coarse_max_level(vol)
    eye = np.array(eye)
    faces = visible_faces(eye)
    tiles = np.array([(f, a, b) for f in faces for b in range(0, size, tile) for a in range(0, size, tile)], np.int32)
    live = wp.zeros(len(tiles), dtype=int, device=DEVICE)
    wp.launch(tile_occupancy_kernel, dim=len(tiles),
              inputs=[wp.array(tiles, dtype=wp.vec3i, device=DEVICE), tile, size, wp.vec3(*eye), wp.vec3(*eye), 0.0,
                      wp.full(len(tiles), level, dtype=int, device=DEVICE),
                      wp.array(grid.reshape(-1), dtype=float, device=DEVICE), 0, wp.vec3i(*grid.shape[::-1]), live],
              device=DEVICE)
    live = live.numpy()
    assert live.sum() > 0
    if level == 0:  # (wider level-2 bounds may keep every tile live, which is sound)
        assert live.sum() < len(tiles)
    h = 2.0 / size
    for (f, i0, j0), alive in zip(tiles, live, strict=True):
        if alive:
            continue
        apron = 2**level if level else 0
        sub = (np.arange(4 * (tile + 2 * apron)) + 0.5) / 4 - apron  # 4 x 4 rays per texel
        u, v = np.meshgrid(-1 + (i0 + sub) * h, -1 + (j0 + sub) * h)
        q = face_point_np(f, u, v)
        # Past an edge the apron wraps onto the adjacent face: fold the overflow back along the face's axis.
        axis, sign = f // 2, 1 - 2 * (f % 2)
        over = np.clip(np.abs(q) - 1, 0, None).max(axis=-1)
        q[..., axis] -= sign * over
        q = np.clip(q, -1, 1)
        d = q - eye
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (-1 - eye) / d, (1 - eye) / d
        t0 = np.clip(np.nanmax(np.minimum(ta, tb), axis=-1), 0, 1)
        s = t0[..., None] + (1 - t0[..., None]) * np.linspace(0, 1, 96)
        points = eye + s[..., None] * d[..., None, :]
        assert sampled_density(density, points).max() == 0.0, (f, i0, j0)


@pytest.mark.parametrize(("method", "config"), [(CMSRM, CMSRMConfig), (CACRM, CACRMConfig)])
def test_culling_leaves_the_image_unchanged_and_saves_samples(method, config):
    scene = builtin_scene("cloud", 128)
    views = make_views(Camera(position=(0.0, 0.4, 3.2), width=96, height=64), "stereo")
    full = method(config(hybrid=False, light_grid=32, cull_tiles=False), device=DEVICE).render(scene, views)
    culled = method(config(hybrid=False, light_grid=32), device=DEVICE).render(scene, views)
    for a, b in zip(full.images, culled.images, strict=True):
        np.testing.assert_array_equal(a, b)
    assert culled.stats.counters["density_samples"] < 0.8 * full.stats.counters["density_samples"]
    plan = culled.stats.info["volumes"][0][0]
    assert plan["live_tiles"] < plan["tiles"]

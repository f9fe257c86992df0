"""Bricked densities (issue 41 item 1): every renderer samples density through the brick page table
(`volren.kernels.common.gather_density`), and its images equal those of the dense upload, the path before issue 41,
on every built-in volume scene and method; memory goes with the active bricks."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import DEVICE
from volren._api import framed_camera
from volren.data import BUILTIN_SCENES, builtin_scene
from volren.render import CACRM, CMSRM, DSSRM, VPT, CACRMConfig, CMSRMConfig, DSSRMConfig, Reference, ReferenceConfig
from volren.render.compositing.channels import AdditiveChannels, channel_volumes
from volren.render.vpt.tracer import VPTConfig
from volren.scene import DirectionalLight, Environment, Scene, Volume
from volren.upload import BRICK, upload_scene

N = 64
"""voxels per axis of the built-in scenes (the instance scenes: N/2 per instance)"""
SIZE = (64, 48)
METHODS = {
    "dssrm": lambda mode: DSSRM(DSSRMConfig(samples=96, light_samples=32, mode=mode), device=DEVICE),
    "cmsrm": lambda mode: CMSRM(CMSRMConfig(samples=96, light_samples=32, mode=mode), device=DEVICE),
    "cacrm": lambda mode: CACRM(CACRMConfig(samples=96, light_samples=32, mode=mode), device=DEVICE),
    "reference": lambda mode: Reference(ReferenceConfig(samples=96, light_samples=32), device=DEVICE),
    "vpt": lambda mode: VPT(VPTConfig(spp=2, seed=7), device=DEVICE),
}


def images(make, scene: Scene, cams) -> tuple[np.ndarray, np.ndarray]:
    """The images of ``scene`` with bricked and with dense densities, each by a fresh renderer from ``make``."""
    out = []
    for bricked in (True, False):
        r = make()
        inner = getattr(r, "renderers", [r])  # AdditiveChannels: a renderer per channel
        for one in inner:
            one.bricked = bricked
        frame = r.render(scene, list(cams))
        out.append(np.stack(frame.images))
        for one in inner:  # each took the upload asked for: bricks in the pool, or none
            assert (one._device_scene.active_bricks > 0) == bricked
        for info in frame.stats.info.get("channels", [frame.stats.info]):  # and its stats say so
            bricks = info["bricks"]
            assert (bricks["active"] > 0) == bricked
            assert bricks["pool_bytes"] == 4 * (BRICK + 1) ** 3 * bricks["active"]
    return out[0], out[1]


def scene_views(name: str):
    scene = builtin_scene(name, N)
    return scene, [framed_camera(scene, name, *SIZE)]


@pytest.mark.timeout(600)
@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
@pytest.mark.parametrize("method", list(METHODS))
def test_bricked_images_equal_the_dense_ones(name, method):
    scene, cams = scene_views(name)
    bricked, dense = images(lambda: METHODS[method]("dvr"), scene, cams)
    assert dense[..., 3].max() > 0.05  # the view sees the volume
    assert np.abs(bricked - dense).max() == 0.0


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mode", ["mip", "mida", "iso"])
@pytest.mark.parametrize("method", ["dssrm", "cacrm"])
def test_sci_vis_modes_equal_the_dense_ones(mode, method):
    scene, cams = scene_views("phantom")
    bricked, dense = images(lambda: METHODS[method](mode), scene, cams)
    assert dense[..., 3].max() > 0.05
    assert np.abs(bricked - dense).max() == 0.0


@pytest.mark.timeout(300)
def test_channels_equal_the_dense_ones():
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    blobs = [np.exp(-((x - cx) ** 2 + (y - N / 2) ** 2 + (z - N / 2) ** 2) / 60.0) for cx in (22.0, 42.0)]
    scene = Scene(channel_volumes(blobs, np.eye(4), colors=((0.0, 1.0, 0.0), (1.0, 0.0, 1.0)), opacity=[3.0]),
                  lights=(), environment=Environment((0.0, 0.0, 0.0)))
    cams = [framed_camera(scene, None, *SIZE)]
    bricked, dense = images(lambda: AdditiveChannels(lambda: METHODS["dssrm"]("dvr"), 2), scene, cams)
    assert dense[..., 3].max() > 0.05
    assert np.abs(bricked - dense).max() == 0.0


def ball_and_slab() -> Scene:
    """N^3 voxels, zero but for a ball inside one brick and a constant slab (0.25) over the last quarter in x."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    # non-zero at voxels 19..29 per axis: inside brick 1's apron block [16, 32], off its faces
    grid = np.clip(1.0 - np.sqrt((x - 24) ** 2 + (y - 24) ** 2 + (z - 24) ** 2) / 6.0, 0.0, None)
    grid[:, :, 48:] = 0.25  # x bricks 3 are constant; x bricks 2 (voxels [32, 48]) hold the slab's face
    return Scene((Volume(grid.astype(np.float32), density_scale=8.0),), lights=(DirectionalLight(),),
                 environment=Environment((0.1, 0.1, 0.1)))


@pytest.mark.timeout(300)
@pytest.mark.parametrize("method", ["dssrm", "reference"])
def test_constant_bricks_render_as_the_dense_grid(method):
    """The built-in scenes' constant bricks are all empty: here non-empty ones (OpenVDB tiles) read their value."""
    scene = ball_and_slab()
    bricked, dense = images(lambda: METHODS[method]("dvr"), scene, [framed_camera(scene, None, *SIZE)])
    assert dense[..., 3].max() > 0.05
    assert np.abs(bricked - dense).max() == 0.0


@pytest.mark.timeout(120)
def test_sparse_volume_holds_pool_memory_only_for_its_active_bricks():
    """A 64^3 grid, zero but for a ball inside one brick and a constant slab: the pool holds the ball's brick and the
    bricks whose apron meets the slab's face; the slab's other bricks and the empty ones are page-table entries only,
    and the upload says so (issue 41 item 1)."""
    n = N
    scene = ball_and_slab()
    ds = upload_scene(scene, DEVICE)
    dense = upload_scene(scene, DEVICE, bricked=False)
    bricks = -(-(n - 1) // BRICK)  # per axis
    active = 1 + bricks * bricks
    assert ds.active_bricks == active
    assert ds.pool_bytes == active * (BRICK + 1) ** 3 * 4
    assert ds.density.shape[0] == active * (BRICK + 1) ** 3 + 2  # the pool, then the constants 0 and 0.25
    assert ds.table.shape[0] == bricks**3
    assert dense.density.shape[0] == n**3 and dense.pool_bytes == 0 and dense.active_bricks == 0


@pytest.mark.timeout(300)
def test_two_unlike_volumes_each_read_their_own_page_table():
    """Two volumes of different grids side by side (the built-in instance scenes repeat one grid, so a volume reading
    the other's page table looks the same there): the bricked image equals the dense one, each ball where it lies."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    volumes = []
    for i, (cx, cz) in enumerate(((20.0, 44.0), (44.0, 20.0))):
        grid = np.clip(1.0 - np.sqrt((x - cx) ** 2 + (y - 32) ** 2 + (z - cz) ** 2) / 10.0, 0.0, None)
        place = np.eye(4)
        place[0, 3] = 2.2 * i - 1.1
        volumes.append(Volume(grid.astype(np.float32), density_scale=8.0, to_world=place))
    scene = Scene(tuple(volumes), lights=(DirectionalLight(),), environment=Environment((0.1, 0.1, 0.1)))
    bricked, dense = images(lambda: METHODS["dssrm"]("dvr"), scene, [framed_camera(scene, None, *SIZE)])
    assert dense[..., 3].max() > 0.05
    assert np.abs(bricked - dense).max() == 0.0

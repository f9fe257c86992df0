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
from volren.scene import Environment, Scene, Volume
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
        r.bricked = bricked
        out.append(np.stack(r.render(scene, list(cams)).images))
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


@pytest.mark.timeout(120)
def test_sparse_volume_holds_pool_memory_only_for_its_active_bricks():
    """A 64^3 grid, zero but for a ball of radius 6 voxels and a constant slab: the pool holds the bricks the ball
    touches (apron included), the slab's bricks are constants, and the upload counts them (issue 41 item 1)."""
    n = 64
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float32)
    grid = np.clip(1.0 - np.sqrt((x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2) / 6.0, 0.0, None)
    grid[:, :, 48:] = 0.25  # constant bricks (x cells 48-62: the last brick column), whose apron is all 0.25
    scene = Scene((Volume(grid.astype(np.float32)),), lights=(), environment=Environment((0.0, 0.0, 0.0)))
    ds = upload_scene(scene, DEVICE)
    dense = upload_scene(scene, DEVICE, bricked=False)
    # the ball's voxels [14, 26] per axis meet the aprons of bricks 0 and 1 on each axis: 2^3 resident bricks
    assert ds.active_bricks == 8
    assert ds.pool_bytes == 8 * (BRICK + 1) ** 3 * 4
    assert ds.density.shape[0] * 4 < dense.density.shape[0] * 4 / 4  # pool + 2 constants, against 64^3 floats
    assert ds.table.shape[0] == (-(-(n - 1) // BRICK)) ** 3
    assert dense.pool_bytes == 0 and dense.active_bricks == 0

"""Sparse volumes render as their dense copies do (issue 41 items 1 and 2): a `SparseGrid` built without a dense copy
(as the OpenVDB reader builds one) stands for the volume's density in every renderer. What it derives from its bricks
rather than from the voxels (empty-space skipping in cells of B voxels, majorants per brick, a capped default light
map) changes which samples are taken, never what a sample reads: the marches equal the dense images to float
rounding, the path tracer agrees statistically."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import DEVICE
from test_bricked_render import METHODS as BRICKED_METHODS
from test_bricked_render import SIZE, N
from volren._api import framed_camera
from volren.data import builtin_scene
from volren.metrics import psnr
from volren.render import VPT
from volren.render.vpt.tracer import VPTConfig
from volren.scene import Volume
from volren.sparse import BRICK, BrickBuilder, SparseGrid
from volren.upload import SPARSE_LIGHT_GRID, light_grid_resolution

METHODS = {name: make for name, make in BRICKED_METHODS.items() if name != "vpt"}
"""the marches of the bricked-equals-dense tests (the path tracer is compared statistically here)"""


def sparse_copy(grid: np.ndarray) -> SparseGrid:
    """``grid`` bricked voxel by voxel from its non-zero voxels (the OpenVDB reader's path), never from the array."""
    voxels = np.argwhere(grid != 0)
    builder = BrickBuilder(grid.shape, BRICK)
    builder.touch(voxels, voxels)
    builder.scatter(voxels, grid[tuple(voxels.T)])
    return builder.build()


def sparse_scene(name: str):
    scene = builtin_scene(name, N)
    volumes = tuple(dataclasses.replace(v, density=sparse_copy(v.density),
                                        emission_grid=None if v.emission_grid is None else sparse_copy(v.emission_grid))
                    for v in scene.volumes)
    return scene, dataclasses.replace(scene, volumes=volumes), [framed_camera(scene, name, *SIZE)]


@pytest.mark.timeout(600)
@pytest.mark.parametrize("name", ["smoke", "fire", "multi"])
@pytest.mark.parametrize("method", list(METHODS))
def test_sparse_volumes_render_as_the_dense_ones(name, method):
    dense_scene, scene, cams = sparse_scene(name)
    assert all(isinstance(v.density, SparseGrid) for v in scene.volumes)
    sparse = np.stack(METHODS[method]("dvr").render(scene, cams).images)
    dense = np.stack(METHODS[method]("dvr").render(dense_scene, cams).images)
    assert dense[..., 3].max() > 0.3 and dense[..., 3].min() < 0.05  # the view sees the medium and its edge
    assert np.abs(sparse - dense).max() <= 1e-5, np.abs(sparse - dense).max()


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mode", ["mip", "iso"])
def test_sparse_sci_vis_modes_render_as_the_dense_ones(mode):
    dense_scene, scene, cams = sparse_scene("phantom")
    sparse = np.stack(METHODS["dssrm"](mode).render(scene, cams).images)
    dense = np.stack(METHODS["dssrm"](mode).render(dense_scene, cams).images)
    assert dense[..., 3].max() > 0.3
    assert np.abs(sparse - dense).max() <= 1e-5


@pytest.mark.timeout(300)
def test_sparse_path_tracing_agrees_with_the_dense_one():
    """Majorants per brick (16^3) instead of per 8^3 macrocell: other free flights, the same expectation: the sparse
    image is as close to the dense one as a second dense image of another seed is (the noise floor)."""
    dense_scene, scene, cams = sparse_scene("smoke")
    frames = [VPT(VPTConfig(spp=64, seed=seed, denoise="none"), device=DEVICE).render(s, cams).images[0]
              for s, seed in ((scene, 3), (dense_scene, 3), (dense_scene, 4))]
    assert frames[1][..., 3].max() > 0.3
    floor = psnr(frames[2][..., :3], frames[1][..., :3])
    assert psnr(frames[0][..., :3], frames[1][..., :3]) >= floor - 1.0, floor
    assert abs(float(frames[0][..., 3].mean()) - float(frames[1][..., 3].mean())) < 0.01


def test_a_sparse_grid_gets_a_capped_default_light_map():
    """Half of a 2000^3 index box would be a 1000^3 light map (8 GB per light)."""
    assert light_grid_resolution((2000, 2000, 1000), None, sparse=True) == (SPARSE_LIGHT_GRID, SPARSE_LIGHT_GRID, 128)
    assert light_grid_resolution((2000, 2000, 1000), None) == (1000, 1000, 500)
    assert light_grid_resolution((400, 400, 400), None, sparse=True) == (200, 200, 200)


def test_a_sparse_volume_refuses_bad_values_in_one_line():
    grid = sparse_copy(np.pad(np.ones((4, 4, 4), np.float32), 2))
    bad = grid.map(lambda v: np.where(v > 0, np.float32(np.nan), v))
    with pytest.raises(Exception, match="NaN/Inf"):
        Volume(bad)
    with pytest.raises(Exception, match="negative values"):
        Volume(grid.map(lambda v: -v))


@pytest.mark.parametrize("limit", [None, 0])
def test_a_sparse_volume_skips_empty_space_from_its_bricks(limit, monkeypatch):
    """Its skip grid comes from the bricks: cells of `SKIP_CELL` voxels as a dense grid's (`SparseGrid.cell_max`),
    or, where those would be more than `MAX_SPARSE_SKIP_CELLS`, one cell per brick (`SparseGrid.cell_ranges`)."""
    import volren.upload as upload

    if limit is not None:
        monkeypatch.setattr(upload, "MAX_SPARSE_SKIP_CELLS", limit)
    scene = builtin_scene("multi", N)
    vol = dataclasses.replace(scene.volumes[0], density=sparse_copy(scene.volumes[0].density))
    ds = upload.upload_scene(dataclasses.replace(scene, volumes=(vol,)), DEVICE)
    s = ds.levels[0][0]
    cells = vol.density.cell_max(upload.SKIP_CELL) if limit is None else vol.density.cell_ranges()[1]
    assert s.skip_cell == (upload.SKIP_CELL if limit is None else BRICK) and tuple(s.skip_res) == cells.shape[::-1]
    grid = ds.max_density.numpy()[s.skip_offset : s.skip_offset + cells.size].reshape(cells.shape)
    assert np.array_equal(grid > 0, cells > 0)  # occupied where a cell's bound is > 0, radii elsewhere


@pytest.mark.timeout(120)
def test_a_kilometre_wide_volume_is_framed_whole_by_the_cli_and_the_api(tmp_path):
    """The issue's file is 1.6 km across in OpenVDB's metres, framed from 4 km: the default far plane (1000 m) had
    the whole box beyond it, a black picture. The framed eye's far plane reaches past the box."""
    import imageio.v3 as iio

    import volren as vr
    from volren.cli import main
    from volren.scene import scale_translate

    z, y, x = np.mgrid[-1:1:32j, -1:1:32j, -1:1:32j]
    ball = np.clip(1.0 - (x * x + y * y + z * z) / 0.25, 0.0, None).astype(np.float32)
    vol = Volume(ball, scale_translate(800.0, (1000.0, 1000.0, 1000.0)), density_scale=0.02)
    frame = vr.render(vol, width=48, height=32, samples=32, light_samples=8, device=DEVICE)
    assert frame.images[0][..., 3].max() > 0.5
    np.save(tmp_path / "km.npy", ball)
    args = ["render", "--volume", str(tmp_path / "km.npy"), "--spacing", "50,50,50", "--units", "m", "--views",
            "mono", "--width", "48", "--height", "32", "--samples", "32", "--light-samples", "8", "--device", DEVICE]
    assert main([*args, "--out", str(tmp_path / "out")]) == 0
    assert iio.imread(tmp_path / "out" / "view0.png")[..., :3].max() > 60

"""Every method draws a streamed pyramid (issue 41): the cube-map methods march the file's levels as their mip levels,
the path tracer's majorants and every method's empty-space skipping are bounded per brick by what the device's
bricks draw (`volren.render.stream_bounds`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp
import zarr

from conftest import DEVICE
from test_stream_render import (  # noqa: F401 (fixtures)
    SIZE,
    N,
    close_camera,
    pyramid,
    sample_points,
    scene_of,
    write_levels,
)
from volren.camera import Camera
from volren.kernels.common import VolumeGPU
from volren.metrics import psnr
from volren.render import CACRM, CMSRM, VPT, CACRMConfig, CMSRMConfig
from volren.render.marching.cubemap import cube_lod
from volren.render.stream_bounds import drawn_bounds
from volren.render.vpt.tracer import VPTConfig
from volren.stream.lod import frame_needs
from volren.upload import cull_level

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def float_pyramid(tmp_path_factory):
    """Three float32 levels, each the 2x2x2 mean of the one before (as `volren.scene.Volume.mip_pyramid` makes a
    dense grid's), placed by scales and translations: the levels a dense volume's cube-map march reads, exactly."""
    path = tmp_path_factory.mktemp("stream") / "float.zarr"
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    levels = [sum(np.exp(-((x - cx) ** 2 + (y - 30) ** 2 + (z - 32) ** 2) / 90.0) for cx in (20.0, 44.0))]
    for _ in range(2):
        n = levels[-1].shape[0] // 2
        levels.append(levels[-1].reshape(n, 2, n, 2, n, 2).mean(axis=(1, 3, 5)).astype(np.float32))
    write_levels(path, levels, [1.0, 2.0, 4.0], centred=True)
    return path


@pytest.fixture(scope="module")
def corner_pyramid(tmp_path_factory):
    """128^3 uint16, zero but for a blob of radius 12 around voxel (40, 40, 40) (level-0 bricks 1 to 3 on each
    axis), three levels of every second voxel."""
    path = tmp_path_factory.mktemp("stream") / "corner.zarr"
    z, y, x = np.mgrid[0:128, 0:128, 0:128].astype(np.float32)
    level = np.round(4000 * np.exp(-((x - 40) ** 2 + (y - 40) ** 2 + (z - 40) ** 2) / 16.0)).astype(np.uint16)
    levels = [level, level[::2, ::2, ::2].copy(), level[::4, ::4, ::4].copy()]
    write_levels(path, levels, [1.0, 2.0, 4.0], centred=False)
    return path


def far_camera(scene, distance: float) -> Camera:
    vol = scene.volumes[0]
    size = float(np.linalg.norm(vol.to_world[:3, 0])) * 2
    c = vol.center_world
    return Camera(position=tuple(c + np.array([0.3, 0.2, distance]) * size), look_at=tuple(c), fov_y=40.0,
                  width=SIZE[0], height=SIZE[1], near=1e-4 * size, far=100 * size)


@pytest.mark.parametrize("method", ["cmsrm", "cacrm"])
@pytest.mark.parametrize(("distance", "level"), [(2.5, 0), (3.0, 1), (6.0, 2)])
def test_the_cube_map_methods_march_a_streamed_pyramids_level_as_a_dense_volumes_mip_level(
        float_pyramid, method, distance, level):
    """Away from the eye the cube map is marched at LOD level l: a streamed volume's level l is its file's (the
    bricks of level l are asked for as well as the footprint's: at 2.5 the footprint wants level 1 for the far
    bricks, the cube map level 0), which equals the dense volume's mip level l here. (Rim and
    hybrid pixels are marched directly at level 0 by the dense volume and at the footprint's level by the streamed
    one, and so is the light map: off here, and no light, so that only the cube map is compared.)"""
    make = {"cmsrm": lambda: CMSRM(CMSRMConfig(samples=64, rim_direct=False, hybrid=False), device=DEVICE),
            "cacrm": lambda: CACRM(CACRMConfig(samples=64, rim_direct=False, hybrid=False), device=DEVICE)}[method]
    dense, streamed = (dataclasses.replace(scene_of(float_pyramid, **load), lights=())
                       for load in ({"level": 0}, {"memory_budget": 2**26, "stream": True}))
    cam = far_camera(dense, distance)
    c = make().config
    vol = dense.volumes[0]
    assert cube_lod(vol, cam, max(vol.resolution), c.samples, c.k_u, c.k_c, True, screen_sizing=True).level == level
    want = make().render(dense, [cam]).images[0]
    got = make().render(streamed, [cam])
    assert want[..., 3].max() > 0.5
    assert np.abs(got.images[0] - want).max() <= 2e-5
    assert got.stats.info["stream"][0]["levels_used"][level] > 0


def test_a_cube_map_method_with_its_defaults_draws_a_far_streamed_pyramid_with_no_hole(pyramid):  # noqa: F811
    dense = scene_of(pyramid, level=0)
    streamed = scene_of(pyramid, memory_budget=2**26, stream=True)
    cam = far_camera(dense, 3.0)
    want = CMSRM(CMSRMConfig(samples=64), device=DEVICE).render(dense, [cam]).images[0][..., 3]
    got = CMSRM(CMSRMConfig(samples=64), device=DEVICE).render(streamed, [cam]).images[0][..., 3]
    assert want.max() > 0.5 and np.all(got[want > 0.05] > 0.02) and np.abs(got - want).mean() < 0.01


def test_the_path_tracer_draws_a_streamed_pyramid_at_its_noise_floor(pyramid):  # noqa: F811
    """Majorants per brick from the device's bricks (`drawn_bounds`): unbiased, so the streamed picture is as close
    to the dense one as two seeds of the dense one are to each other."""
    def thin(scene):  # a tenth of the default opacity: the blobs translucent, so a biased majorant shows
        vol = scene.volumes[0]
        return dataclasses.replace(scene, volumes=(dataclasses.replace(vol, density_scale=vol.density_scale / 10),))

    dense = thin(scene_of(pyramid, level=0))
    streamed = thin(scene_of(pyramid, memory_budget=2**26, stream=True))
    cam = close_camera(dense)

    def vpt(scene, seed):
        return VPT(VPTConfig(spp=32, seed=seed, denoise="none"), device=DEVICE).render(scene, [cam])

    got = vpt(streamed, 1)
    frames = [vpt(dense, 1).images[0], vpt(dense, 2).images[0]]
    floor = psnr(frames[1][..., :3], frames[0][..., :3])
    assert 0.3 < frames[0][..., 3].max() < 0.97
    assert psnr(got.images[0][..., :3], frames[0][..., :3]) >= floor - 1.0, floor
    assert abs(got.images[0][..., 3].mean() - frames[0][..., 3].mean()) < 0.1 * frames[0][..., 3].mean()
    assert got.stats.info["stream"][0]["bricks_pending"] == 0


@pytest.mark.parametrize("group", [1, 2])
def test_the_bounds_hold_every_drawn_density_and_leave_the_empty_bricks_empty(corner_pyramid, monkeypatch, group):
    """Level-0 bricks x 0-2 on the device (some holding the blob, most empty), the rest drawn from level 2 (the
    blob's level-2 brick reaches x 63). Every density sampled anywhere is at most its skip cell's bound; the cells
    whose neighbours are empty on the device or drawn from an empty coarse brick are empty (so they are skipped);
    a resident brick's bound is its own and its neighbours' largest voxel, no more. ``group`` 2: skip cells of 2^3
    bricks (a level of more than `MAX_STREAM_SKIP_CELLS` bricks, made small here)."""
    from volren import upload
    from volren.render import DSSRM, DSSRMConfig, streaming
    from volren.stream.lod import need

    monkeypatch.setattr(upload, "MAX_STREAM_SKIP_CELLS", 512 // group**3)
    monkeypatch.setattr(streaming, "frame_needs", lambda views, to_world, layout, **levels: [
        need((0, *b), True, 1.0) for b in np.ndindex(8, 8, 3)])
    streamed = scene_of(corner_pyramid, memory_budget=2**26, stream=True)
    renderer = DSSRM(DSSRMConfig(samples=64, light_samples=8), device=DEVICE)
    renderer.render(streamed, [close_camera(streamed)])
    ds = renderer._device_scene
    state = ds.streams[0]
    s = ds.levels[0][0]
    cells = 8 // group
    assert s.skip_cell == 16 * group and tuple(s.skip_res) == (cells,) * 3
    skip = ds.max_density.numpy()[s.skip_offset:s.skip_offset + cells**3].reshape((cells,) * 3)
    points = np.random.default_rng(3).uniform(-1.0, 1.0, (40000, 3)).astype(np.float32)
    out = wp.zeros(len(points), dtype=float, device=ds.device)
    wp.launch(sample_points, dim=len(points), inputs=[wp.array([s], dtype=VolumeGPU, device=ds.device), ds.density,
                                                      wp.array(points, dtype=wp.vec3, device=ds.device), out],
              device=ds.device)
    at = np.clip(np.floor((points + 1.0) * 128 / 2 / s.skip_cell).astype(int), 0, cells - 1)
    bound = skip[at[:, 2], at[:, 1], at[:, 0]]
    values = out.numpy()
    assert values.max() > 0.5 and np.all(values <= np.maximum(bound, 0.0) + 1e-6)
    level0 = [key for key in state.slots if key[0] == 0]
    assert 8 <= len(level0) < 27  # the blob's bricks x 1-2 resident, x 3 drawn from level 2
    if group == 2:  # cells of bricks 0-1, 2-3, ...: the blob in cells 0-1, empty from bricks 6 on
        assert np.all(skip[3:, :, :] <= 0) and np.all(skip[:, 3:, :] <= 0) and np.all(skip[:2, :2, :2] > 0)
        return
    assert np.all(skip[5:, :, :] <= 0) and np.all(skip[:, 5:, :] <= 0) and np.all(skip[1:4, 1:4, 1:4] > 0)
    assert np.all(skip[:4, :4, 3:5] > 0)  # drawn from the blob's level-2 brick, or next to it
    bounds = drawn_bounds(state)[0]
    exact = 0
    for key in level0:
        around = [state.maxima.get((0, *n), 0.0 if (0, *n) in state.empty else None) for n in np.ndindex(8, 8, 8)
                  if max(abs(a - b) for a, b in zip(n, key[1:], strict=True)) <= 1]
        if None not in around:  # every neighbour on the device: the bound is exactly their largest voxel
            assert bounds[key[1:]] == pytest.approx(max(around))
            exact += 1
    assert exact >= 1
    cube = CMSRM(CMSRMConfig(samples=32), device=DEVICE)  # the cube-map methods' culling level: from the bounds
    cube.render(streamed, [close_camera(streamed)])
    ds = cube._device_scene
    want = cull_level(ds.streams[0].bounds[0])
    culled = ds.max_density.numpy()[ds.streams[0].cull:ds.streams[0].cull + want.size]
    assert (want == 0).any() and np.array_equal(culled, want.reshape(-1))


def test_a_renderer_that_marches_a_level_asks_for_its_bricks_and_their_ancestors(pyramid):  # noqa: F811
    streamed = scene_of(pyramid, memory_budget=2**26, stream=True)
    vol = streamed.volumes[0]
    layout = vol.density.layout
    cam = far_camera(streamed, 6.0)
    plain = {n.key for n in frame_needs([cam], vol.to_world, layout)}
    assert {k[0] for k in plain} == {2}  # the footprint wants the coarsest level there
    marched = {n.key for n in frame_needs([cam], vol.to_world, layout, marched=1, ancestors=True)}
    assert {k for k in marched if k[0] == 1} == {(1, *b) for b in np.ndindex(*layout.bricks(1))}
    assert plain <= marched and all((k[0] + 1, *layout.parent(k[0], k[1:])) in marched for k in marched if k[0] < 2)


@pytest.fixture(scope="module")
def uneven_pyramid(tmp_path_factory):
    """Levels of 64^3, 32^3 (2x2x2 means) and 8^3 (4x4x4 means of level 1), each centred on the voxels it averages
    (scales 1, 2, 8; translations (s - 1) / 2): level 1 to level 2 is not level 0 to level 1."""
    path = tmp_path_factory.mktemp("stream") / "uneven.zarr"
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    level0 = sum(np.exp(-((x - cx) ** 2 + (y - 30) ** 2 + (z - 32) ** 2) / 90.0) for cx in (20.0, 44.0))
    level1 = level0.reshape(32, 2, 32, 2, 32, 2).mean(axis=(1, 3, 5))
    levels = [level0.astype(np.float32), level1.astype(np.float32),
              level1.reshape(8, 4, 8, 4, 8, 4).mean(axis=(1, 3, 5)).astype(np.float32)]
    write_levels(path, levels, [1.0, 2.0, 8.0], centred=True)
    return path


def test_a_coarser_levels_missing_brick_is_drawn_from_the_level_above_it(uneven_pyramid, monkeypatch):
    """The cube-map methods' level-1 struct (`volren.upload.pack_stream`, base 1): level 1's bricks x 0-15 on the
    device, x 16-31 not: a sample there is level 2's, interpolated at its place on level 2 (index (v + 0.5) 2 / 8 -
    0.5 of level-1 voxel v: level 1 to 2 by their own scales, not level 0 to 1's), cell by cell as `ancestor_voxel`
    does."""
    from scipy.ndimage import map_coordinates

    from volren.render import streaming
    from volren.stream.lod import need

    monkeypatch.setattr(streaming, "frame_needs", lambda views, to_world, layout, **levels: [
        need((1, z, y, 0), True, 1.0) for z in range(2) for y in range(2)])
    streamed = scene_of(uneven_pyramid, memory_budget=2**26, stream=True)
    renderer = CMSRM(CMSRMConfig(samples=32), device=DEVICE)
    renderer.render(streamed, [close_camera(streamed)])
    ds = renderer._device_scene
    s = ds.levels[0][1]
    assert tuple(s.res) == (32, 32, 32) and s.stream_levels == 2
    level2 = np.asarray(zarr.open_group(str(uneven_pyramid), mode="r")["s2"])
    f = np.stack([np.linspace(18.0, 28.0, 41), np.full(41, 15.3), np.full(41, 12.6)], axis=1)  # level-1 x, y, z
    cell = np.floor(f).astype(int)
    frac = f - cell
    want = np.zeros(len(f))
    for n in range(8):
        o = np.array([n % 2, (n // 2) % 2, n // 4])
        j = (cell + o + 0.5) / 4.0 - 0.5
        corner = map_coordinates(level2, j[:, ::-1].T, order=1, mode="nearest")
        want += np.prod(np.where(o == 1, frac, 1.0 - frac), axis=1) * corner
    points = (-1.0 + (f + 0.5) * 2.0 / 32).astype(np.float32)
    out = wp.zeros(len(points), dtype=float, device=ds.device)
    wp.launch(sample_points, dim=len(points), inputs=[wp.array([s], dtype=VolumeGPU, device=ds.device), ds.density,
                                                      wp.array(points, dtype=wp.vec3, device=ds.device), out],
              device=ds.device)
    assert want.max() > 0.2
    np.testing.assert_allclose(out.numpy(), want, rtol=1e-5, atol=1e-6)


def test_a_skip_cell_of_several_bricks_is_drawn_from_the_ancestors_unless_all_its_bricks_are_on_the_device(
        monkeypatch):
    """`_drawn` by hand on a two-level pyramid (64^3 then 32^3, scales 1 and 2), skip cells of 2^3 bricks: a cell
    whose bricks are all on the device is their largest voxel; one with a brick missing also takes the level-1 brick
    its voxels map into; one with none, that brick alone."""
    from types import SimpleNamespace

    from volren import upload
    from volren.render.stream_bounds import _drawn, _on_device
    from volren.stream.layout import PyramidLayout

    monkeypatch.setattr(upload, "MAX_STREAM_SKIP_CELLS", 8)
    layout = PyramidLayout(((64, 64, 64), (32, 32, 32)), ((2, 2, 2),))
    maps = {0: np.array([[1, 1, 1, 0, 0, 0], [0.5, 0.5, 0.5, -0.25, -0.25, -0.25]], np.float32),
            1: np.array([[1, 1, 1, 0, 0, 0]], np.float32)}
    sd = SimpleNamespace(layout=layout, brick=16, level_maps=maps.__getitem__)
    full = {(0, *b): 0.25 for b in np.ndindex(2, 2, 2)}  # cell (0, 0, 0): all its bricks, largest 0.25
    full[(0, 1, 1, 1)] = 0.5
    part = {(0, 0, 0, 2): 0.0}  # cell (0, 0, 1): one of its eight bricks, empty
    ancestors = {(1, *b): 0.1 * (1 + b[2]) for b in np.ndindex(2, 2, 2)}  # level 1: x brick 0 0.1, x brick 1 0.2
    slots = {**full, **{k: v for k, v in part.items() if v}, **ancestors}
    state = SimpleNamespace(density=sd, slots=slots, maxima=slots, empty={k for k, v in part.items() if not v})
    drawn = _drawn(_on_device(state, 2), 0, sd)
    assert drawn.shape == (2, 2, 2)
    assert drawn[0, 0, 0] == pytest.approx(0.5)  # its own bricks only: level 1's 0.1 is not drawn there
    assert drawn[0, 0, 1] == pytest.approx(0.2)  # level-0 x 32-63: level-1 x 16-31, the x brick 1
    assert drawn[1, 1, 0] == pytest.approx(0.1)


def test_a_precomputed_ambient_field_is_computed_again_when_a_streamed_volumes_bricks_come(pyramid):  # noqa: F811
    """PRT precomputes per density: a frame drawn from the coarse level, then one whose bricks came, holds the
    ambient grid of a fresh renderer's frame with them (up to the Monte Carlo noise of the precomputation)."""
    from volren.render import DSSRM, DSSRMConfig
    from volren.render.gi.ambient import GIConfig

    def make():
        return DSSRM(DSSRMConfig(samples=32, light_grid=8, light_samples=8, gi=GIConfig(method="prt", rays=128)),
                     device=DEVICE)

    streamed = scene_of(pyramid, memory_budget=2**26, stream=True)
    cam = close_camera(streamed)
    renderer = make()
    renderer.stream_wait = False
    renderer.render(streamed, [cam])  # drawn from what is resident at once
    coarse = renderer._device_scene.ambient_grid.numpy().copy()
    streamed.volumes[0].density.streamer.wait(timeout=60)
    renderer.stream_wait = True
    renderer.render(streamed, [cam])
    fresh = make()
    fresh.render(scene_of(pyramid, memory_budget=2**26, stream=True), [cam])
    want = fresh._device_scene.ambient_grid.numpy()
    got = renderer._device_scene.ambient_grid.numpy()
    # the precomputation's noise (its seed follows the frames): 5.5e-5 mean against the coarse field's 2.4e-4
    assert np.abs(got - want).mean() < 0.5 * np.abs(coarse - want).mean()

"""Streamed pyramids in the renderers (issue 41 item 3): an OME-Zarr pyramid larger than the memory budget is read
brick by brick as the views need them; what is not resident is drawn from its finest resident ancestor, never a
hole; ``render`` waits for the needed bricks, a tick of ``serve`` never does."""

from __future__ import annotations

import dataclasses
import time
import warnings

import numpy as np
import pytest
import warp as wp
import zarr
from ome_zarr import writer

from conftest import DEVICE
from volren.camera import Camera
from volren.data.loaders import load_volume
from volren.kernels.common import (
    MISSING,
    VolumeGPU,
    ancestor_voxel,
    gather_density,
    level0_voxel,
    sample_density,
)
from volren.plan.volume import volume_from_file
from volren.render import DSSRM, DSSRMConfig
from volren.scene import DirectionalLight, Environment, Scene
from volren.stream.density import StreamedDensity

pytestmark = pytest.mark.timeout(300)

N = 64
SIZE = (64, 48)


def write_levels(path, levels: list[np.ndarray], scales: list[float], centred: bool) -> None:
    """``levels`` (z, y, x, finest first) as an NGFF pyramid written by ome-zarr, chunks of 16^3, in micrometres:
    level k's voxels ``scales[k]`` level-0 voxels apart, and with ``centred`` each centred on the level-0 voxels it
    averages (translation (s - 1) / 2)."""
    axes = [{"name": n, "type": "space", "unit": "micrometer"} for n in "zyx"]
    transforms = [[{"type": "scale", "scale": [float(f)] * 3}]
                  + ([{"type": "translation", "translation": [(f - 1) / 2] * 3}] if centred else [])
                  for f in scales]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        writer.write_multiscale(levels, zarr.open_group(str(path), mode="w"), axes=axes,
                                coordinate_transformations=transforms, storage_options={"chunks": (16, 16, 16)})


def write_pyramid(path, levels: int = 3, mean: bool = False) -> list[np.ndarray]:
    """A smooth uint16 field (two blobs) and its levels, chunks of 16^3: each the previous one's every second voxel
    (a level-k voxel j is level 0's voxel 2^k j: the file's scales say so), or with ``mean`` its 2x2x2 mean (a
    level-k voxel is centred between its 2^k level-0 voxels: the scales and translations say so)."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    field = sum(np.exp(-((x - cx) ** 2 + (y - 30) ** 2 + (z - 32) ** 2) / 90.0) for cx in (20.0, 44.0))
    pyramid = [np.round(field / field.max() * 4000).astype(np.uint16)]
    for _ in range(levels - 1):
        last = pyramid[-1]
        if mean:
            n = last.shape[0] // 2
            pyramid.append(np.round(last.reshape(n, 2, n, 2, n, 2).mean(axis=(1, 3, 5))).astype(np.uint16))
        else:
            pyramid.append(np.ascontiguousarray(last[::2, ::2, ::2]))
    write_levels(path, pyramid, [2.0**k for k in range(levels)], centred=mean)
    return pyramid


@pytest.fixture(scope="module")
def pyramid(tmp_path_factory):
    path = tmp_path_factory.mktemp("stream") / "blobs.zarr"
    write_pyramid(path)
    return path


@pytest.fixture(scope="module")
def mean_pyramid(tmp_path_factory):
    path = tmp_path_factory.mktemp("stream") / "means.zarr"
    write_pyramid(path, mean=True)
    return path


def scene_of(path, **load) -> Scene:
    loaded = load_volume(path, **load)
    vol = volume_from_file(loaded, "blobs", density_scale=None)
    return Scene((vol,), lights=(DirectionalLight(direction=(0.3, -1.0, -0.4)),),
                 environment=Environment((0.05, 0.05, 0.06)))


def close_camera(scene: Scene) -> Camera:
    """Near enough that every visible brick wants level 0 (a pixel's footprint under a voxel)."""
    vol = scene.volumes[0]
    size = float(np.linalg.norm(vol.to_world[:3, 0])) * 2
    centre = vol.center_world
    return Camera(position=tuple(centre + np.array([0.0, 0.0, 1.6 * size])), look_at=tuple(centre),
                  fov_y=40.0, width=SIZE[0], height=SIZE[1], near=1e-4 * size, far=10 * size)


def render(scene: Scene, cam: Camera, wait: bool = True, renderer=None):
    r = renderer or DSSRM(DSSRMConfig(samples=96, light_samples=16), device=DEVICE)
    r.stream_wait = wait
    return r, r.render(scene, [cam])


def test_a_streamed_pyramid_renders_as_its_finest_level_once_its_bricks_came(pyramid):
    dense = scene_of(pyramid, level=0)
    streamed = scene_of(pyramid, memory_budget=2**26, stream=True)
    assert isinstance(streamed.volumes[0].density, StreamedDensity)
    assert np.allclose(streamed.volumes[0].to_world, dense.volumes[0].to_world)
    cam = close_camera(dense)
    _, want = render(dense, cam)
    _, got = render(streamed, cam)
    stream = got.stats.info["stream"][0]
    assert stream["levels_used"][0] > 0 and stream["bricks_pending"] == 0
    assert want.images[0][..., 3].max() > 0.5
    assert np.abs(got.images[0] - want.images[0]).max() <= 1e-5


def test_a_pyramid_larger_than_the_budget_streams_and_draws_the_rest_from_coarser_levels(pyramid):
    """Half a MiB (level 0 is 1 MiB of float32): it streams by itself; the budget holds 13 bricks, level 0's 64 do
    not fit, so the needs stop at level 1 (its 8 bricks and the coarsest: `frame_needs`' limit) and every visible
    brick is drawn from it: the picture has no hole where the full one has medium."""
    dense = scene_of(pyramid, level=0)
    streamed = scene_of(pyramid, memory_budget=2**19)
    assert isinstance(streamed.volumes[0].density, StreamedDensity)
    cam = close_camera(dense)
    _, want = render(dense, cam)
    _, got = render(streamed, cam)
    stream = got.stats.info["stream"][0]
    assert stream["device_capacity"] == 13 and stream["device_bricks"] == 9 and stream["levels_used"][0] == 0
    a, b = want.images[0][..., 3], got.images[0][..., 3]
    assert np.all(b[a > 0.05] > 0.02)  # no hole
    assert np.abs(a - b).mean() < 0.05


def test_a_frame_that_does_not_wait_draws_the_coarse_level_at_once_and_sharpens_after(pyramid, monkeypatch):
    """``serve``'s ticks (``stream_wait`` False) over a store that answers slowly: the first frame comes at once from
    the coarsest level, never blocked by a read; once the reads are done, the next frame is the full one."""
    from volren.stream.source import PyramidSource

    read = PyramidSource.read_brick

    def slow(self, level, *brick, **kw):
        if level < self.layout.coarsest:
            time.sleep(0.3)
        return read(self, level, *brick, **kw)

    dense = scene_of(pyramid, level=0)
    cam = close_camera(dense)
    _, want = render(dense, cam)
    monkeypatch.setattr(PyramidSource, "read_brick", slow)
    streamed = scene_of(pyramid, memory_budget=2**26, stream=True)
    renderer = DSSRM(DSSRMConfig(samples=96, light_samples=16), device=DEVICE)
    render(streamed, cam, renderer=renderer, wait=False)  # compiles the kernels
    streamed = scene_of(pyramid, memory_budget=2**26, stream=True)
    start = time.perf_counter()
    _, first = render(streamed, cam, renderer=renderer, wait=False)
    took = time.perf_counter() - start
    stream = first.stats.info["stream"][0]
    assert took < 2.0 and stream["bricks_pending"] > 0
    assert stream["levels_used"][:2] == [0, 0] and stream["levels_used"][2] > 0  # all from the coarsest level
    assert first.images[0][..., 3].max() > 0.3  # a picture, not a hole
    assert streamed.volumes[0].density.streamer.wait(timeout=60)
    _, later = render(streamed, cam, renderer=renderer, wait=False)
    assert later.stats.info["stream"][0]["levels_used"][1:] == [0, 0]
    assert np.abs(later.images[0] - want.images[0]).max() <= 1e-5


@wp.kernel
def sample_points(volumes: wp.array(dtype=VolumeGPU), density: wp.array(dtype=float), points: wp.array(dtype=wp.vec3),
                  out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = sample_density(density, volumes[0], points[i])


def test_no_seam_where_a_resident_brick_meets_one_drawn_from_a_coarser_level(mean_pyramid, monkeypatch):
    """Level-0 bricks x 0-31 resident, x 32-63 drawn from level 1 (2x2x2 means, centred): across the face at voxel 32
    the density is continuous (the coarse side takes the face voxels from the resident brick's apron); only the
    bricks' insides differ from the finest level, by the coarse level's error."""
    from volren.render import streaming
    from volren.stream.lod import need

    def needs(views, to_world, layout, **levels):
        fine = [need((0, z, y, x), True, 1.0) for z in range(4) for y in range(4) for x in range(2)]
        return fine + [need((1, z, y, 1), True, 2.0) for z in range(2) for y in range(2)]

    monkeypatch.setattr(streaming, "frame_needs", needs)
    dense, streamed = scene_of(mean_pyramid, level=0), scene_of(mean_pyramid, memory_budget=2**26, stream=True)
    cam = close_camera(dense)
    x = np.linspace(28.0, 36.0, 321)  # voxel coordinates across the face at 32 (step 0.025)
    points = np.stack([-1.0 + (x + 0.5) * 2.0 / N, np.full_like(x, -1.0 + 30.5 * 2.0 / N),
                       np.full_like(x, -1.0 + 32.5 * 2.0 / N)], axis=1).astype(np.float32)
    values = []
    for scene in (dense, streamed):
        renderer, _ = render(scene, cam)
        ds = renderer._device_scene
        out = wp.zeros(len(points), dtype=float, device=ds.device)
        wp.launch(sample_points, dim=len(points), inputs=[ds.volumes, ds.density,
                                                          wp.array(points, dtype=wp.vec3, device=ds.device), out],
                  device=ds.device)
        values.append(out.numpy())
    fine, mixed = values
    at = int(np.argmin(np.abs(x - 32.0)))
    assert np.array_equal(mixed[: at + 1], fine[: at + 1])  # up to the face: the resident brick, exactly
    assert np.abs(mixed[at + 1 :] - fine[at + 1 :]).max() > 1e-3  # beyond: level 1's values
    step = np.abs(np.diff(mixed))
    assert step[at - 1 : at + 1].max() <= 2.0 * np.abs(np.diff(fine)).max()  # no jump at the face: a slope's step


@pytest.mark.parametrize("level", [1, 2])
def test_a_missing_brick_is_drawn_from_its_finest_ancestor_on_the_device(mean_pyramid, monkeypatch, level):
    """Level 0's bricks x 0-15, the coarsest level and (``level`` 1) level 1's bricks x 32-63 on the device: a sample
    at x 40-56 finds no level-0 brick and is drawn from the finest level there, 1 or (its level-1 parent not on the
    device) 2: each of its cell's 8 voxels interpolated on that level at its place (a v + b from the centred means'
    scales and translations), then the cell trilinearly."""
    from scipy.ndimage import map_coordinates

    from volren.render import streaming
    from volren.stream.lod import need

    parents = [need((1, z, y, 1), True, 2.0) for z in range(2) for y in range(2)] if level == 1 else []
    monkeypatch.setattr(streaming, "frame_needs", lambda views, to_world, layout, **levels: [
        need((0, z, y, 0), True, 1.0) for z in range(4) for y in range(4)] + parents)
    streamed = scene_of(mean_pyramid, memory_budget=2**26, stream=True)
    renderer, frame = render(streamed, close_camera(streamed))
    assert frame.stats.info["stream"][0]["device_bricks"] == 16 + len(parents) + 1  # asked for, and the floor
    sd = streamed.volumes[0].density
    coarse = sd.mapped(np.asarray(zarr.open_group(str(mean_pyramid), mode="r")[f"s{level}"]))
    f = np.stack([np.linspace(40.0, 56.0, 41), np.full(41, 30.3), np.full(41, 25.6)], axis=1)  # x, y, z voxels
    cell = np.floor(f).astype(int)
    frac = f - cell
    want = np.zeros(len(f))
    for n in range(8):
        o = np.array([n % 2, (n // 2) % 2, n // 4])
        v = cell + o
        j = (v + 0.5) / 2.0**level - 0.5  # that level's index of level-0 voxel v (x, y, z)
        corner = map_coordinates(coarse, j[:, ::-1].T, order=1, mode="nearest")
        want += np.prod(np.where(o == 1, frac, 1.0 - frac), axis=1) * corner
    points = (-1.0 + (f + 0.5) * 2.0 / N).astype(np.float32)
    ds = renderer._device_scene
    out = wp.zeros(len(points), dtype=float, device=ds.device)
    wp.launch(sample_points, dim=len(points),
              inputs=[ds.volumes, ds.density, wp.array(points, dtype=wp.vec3, device=ds.device), out], device=ds.device)
    assert want.max() > 0.2
    np.testing.assert_allclose(out.numpy(), want, rtol=1e-5, atol=1e-6)


@wp.kernel
def cells_two_ways(volumes: wp.array(dtype=VolumeGPU), density: wp.array(dtype=float), cells: wp.vec3i,
                   at_once: wp.array(dtype=float), each: wp.array(dtype=float)):
    """Every cell's 8 voxels by `gather_density`, and each voxel searched alone: level 0, else its ancestors."""
    i = wp.tid()
    cell = wp.vec3i(i % cells[0], (i / cells[0]) % cells[1], i / (cells[0] * cells[1]))
    got = gather_density(density, volumes[0], cell)
    for n in range(8):
        v = cell + wp.vec3i(n % 2, (n / 2) % 2, n / 4)
        x = level0_voxel(density, volumes[0], v)
        if x == MISSING:
            x = ancestor_voxel(density, volumes[0], v)
        at_once[i * 8 + n] = got[n]
        each[i * 8 + n] = x


def test_a_streamed_cell_read_at_once_is_its_voxels_searched_one_by_one(mean_pyramid, monkeypatch):
    """Level 0's bricks in a checkerboard, level 1's of x 32-63 and the coarsest on the device: every cell of the
    grid (inside a brick, on its faces beside a resident or a missing one, its voxels drawn from levels 0, 1 and 2,
    straddling a brick of level 1) reads the values each of its voxels' own search gives, exactly."""
    from volren.render import streaming
    from volren.stream.lod import need

    monkeypatch.setattr(streaming, "frame_needs", lambda views, to_world, layout, **levels: [
        need((0, *b), True, 1.0) for b in np.ndindex(4, 4, 4) if sum(b) % 2 == 0] + [
        need((1, z, y, 1), True, 2.0) for z in range(2) for y in range(2)])
    streamed = scene_of(mean_pyramid, memory_budget=2**26, stream=True)
    renderer, frame = render(streamed, close_camera(streamed))
    assert frame.stats.info["stream"][0]["levels_used"] == [32, 4, 0]
    ds = renderer._device_scene
    count = (N - 1) ** 3
    at_once, each = (wp.zeros(count * 8, dtype=float, device=ds.device) for _ in range(2))
    wp.launch(cells_two_ways, dim=count, inputs=[ds.volumes, ds.density, wp.vec3i(N - 1, N - 1, N - 1), at_once, each],
              device=ds.device)
    got, want = at_once.numpy().reshape(N - 1, N - 1, N - 1, 8), each.numpy().reshape(N - 1, N - 1, N - 1, 8)
    assert np.array_equal(got, want)
    fine = streamed.volumes[0].density.mapped(np.asarray(zarr.open_group(str(mean_pyramid), mode="r")["s0"]))
    level0 = np.stack([fine[n // 4 : N - 1 + n // 4, (n // 2) % 2 : N - 1 + (n // 2) % 2, n % 2 : N - 1 + n % 2]
                       for n in range(8)], axis=-1)
    drawn = np.mean(want != level0)  # the voxels drawn from levels 1 and 2
    assert 0.2 < drawn < 0.8


def test_a_pyramid_on_a_web_server_renders_as_the_folder_does(pyramid):
    """``vr.load("http://...zarr")``: an fsspec URL (a loopback HTTP server here) streams as the folder does."""
    import volren as vr
    from test_stream_source import serve_folder

    folder = scene_of(pyramid, memory_budget=2**26, stream=True)
    cam = close_camera(folder)
    _, want = render(folder, cam)
    with serve_folder(pyramid.parent) as url:
        vol = vr.load(f"{url}/{pyramid.name}", memory_budget=2**26 / 2**30, stream=True)
        assert isinstance(vol.density, StreamedDensity) and vol.name == pyramid.name
        assert np.array_equal(vol.to_world, folder.volumes[0].to_world)
        remote = Scene((dataclasses.replace(folder.volumes[0], density=vol.density),), lights=folder.lights,
                       environment=folder.environment)
        _, got = render(remote, cam)
        assert got.stats.info["stream"][0]["bytes_read"] > 0
        vol.density.close()
    assert np.array_equal(got.images[0], want.images[0])


def test_the_cli_renders_a_store_by_its_url_as_the_folder(pyramid, tmp_path):
    """``volren render --volume http://.../x.zarr``: the URL is kept whole (a Path would fold its //), streamed as
    the folder is, the same picture; and a render spec of it round-trips through JSON as the URL."""
    import imageio.v3 as iio

    from test_stream_source import serve_folder
    from volren.cli import main
    from volren.plan.spec import RenderSpec
    from volren.store import StoreURL

    args = ["--memory-budget", "0.0005", "--width", "48", "--height", "32", "--views", "mono", "--samples", "48",
            "--light-samples", "8", "--device", DEVICE]
    assert main(["render", "--volume", str(pyramid), *args, "--out", str(tmp_path / "local")]) == 0
    with serve_folder(pyramid.parent) as url:
        volume = f"{url}/{pyramid.name}"
        assert main(["render", "--volume", volume, *args, "--out", str(tmp_path / "url")]) == 0
        spec = RenderSpec.parse(["render", "--volume", volume, *args])
    back = RenderSpec.from_json(spec.to_json())
    assert isinstance(dict(back.options)["volume"], StoreURL) and dict(back.options)["volume"] == volume
    local, remote = (iio.imread(tmp_path / d / "view0.png") for d in ("local", "url"))
    assert local.std() > 5 and np.array_equal(local, remote)


@pytest.mark.parametrize("mode", ["dvr", "iso"])
def test_the_reference_and_iso_draw_a_streamed_pyramid_as_its_finest_level(pyramid, mode):
    """The reference and the iso mode read densities through the same device function as DSSRM's DVR: a streamed
    pyramid's picture, once its bricks came, is the finest level's. (MIP and MIDA too, but they normalise by the
    largest density, which a streamed volume takes from its coarsest level: `volren.stream.density`.)"""
    from volren.render import Reference, ReferenceConfig

    def make():
        if mode == "dvr":
            return Reference(ReferenceConfig(samples=64, light_samples=8), device=DEVICE)
        return DSSRM(DSSRMConfig(samples=64, light_samples=8, mode=mode, iso_value=0.3), device=DEVICE)

    dense = scene_of(pyramid, level=0)
    streamed = scene_of(pyramid, memory_budget=2**26, stream=True)
    cam = close_camera(dense)
    want = make().render(dense, [cam]).images[0]
    got = make().render(streamed, [cam]).images[0]
    assert want[..., 3].max() > 0.5 and np.abs(got - want).max() <= 1e-5

"""Multi-channel OME-Zarr pyramids streamed (issue 41 item 3): each channel a `StreamedDensity` of its own within
budget / C, its values mapped by its own range (the omero window where the file states one, else the coarsest
level's min and max) as the dense read maps each channel by its min and max: once its bricks came, the streamed
render is the dense one, each channel in its colour where its data is. And a one-channel pyramid's omero window end
stands for its largest density, which MIP normalises by."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import zarr
from ome_zarr import writer

from conftest import DEVICE
from test_stream_render import close_camera, scene_of, write_pyramid
from volren.data.loaders import load_volume
from volren.errors import VolrenError
from volren.plan.volume import file_channels
from volren.render import DSSRM, DSSRMConfig
from volren.render.compositing.channels import AdditiveChannels
from volren.stream.density import StreamedDensity

pytestmark = pytest.mark.timeout(300)

N = 32
PEAKS = (3000, 1000)
"""channel 0's and channel 1's brightest value (uint16): differing gains, each mapped to density 1"""


def write_channels(path, mean: bool = False, window: bool = False) -> np.ndarray:
    """Two channels (c, z, y, x) of N^3 uint16, three levels, chunks of 16^3: channel 0 a ball left (x 8), channel
    1 a ball right (x 24). Levels: every second voxel (the balls' centres, multiples of 4, and the zeros stay, so
    the coarsest level holds each channel's extremes), or with ``mean`` 2x2x2 means (their peaks lower); ``window``
    writes each channel's true range as its omero window."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    data = np.stack([np.round(peak * np.exp(-((x - cx) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) / 18.0))
                     for cx, peak in zip((8.0, 24.0), PEAKS, strict=True)]).astype(np.uint16)
    levels = [data]
    for _ in range(2):
        last, n = levels[-1], levels[-1].shape[1] // 2
        levels.append(np.round(last.reshape(2, n, 2, n, 2, n, 2).mean(axis=(2, 4, 6))).astype(np.uint16) if mean
                      else np.ascontiguousarray(last[:, ::2, ::2, ::2]))
    axes = [{"name": "c", "type": "channel"}] + [{"name": n, "type": "space", "unit": "micrometer"} for n in "zyx"]
    transforms = [[{"type": "scale", "scale": [1.0] + [2.0**k] * 3}]
                  + ([{"type": "translation", "translation": [0.0] + [(2.0**k - 1) / 2] * 3}] if mean else [])
                  for k in range(3)]
    channels = [{"color": color} | ({"window": {"start": 0, "end": int(data[c].max()), "min": 0, "max": 65535}}
                                    if window else {}) for c, color in enumerate(("FF0000", "00FF00"))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        writer.write_multiscale(levels, zarr.open_group(str(path), mode="w"), axes=axes,
                                coordinate_transformations=transforms, storage_options={"chunks": (1, 16, 16, 16)},
                                metadata={"omero": {"channels": channels}})
    return data


def channel_render(path, **load):
    loaded = load_volume(path, **load)
    scene = file_channels(loaded, path).scene
    renderer = AdditiveChannels(lambda: DSSRM(DSSRMConfig(samples=96, light_samples=8), device=DEVICE), 2)
    return loaded, renderer.render(scene, [close_camera(scene)])


@pytest.mark.parametrize("kind", ["coarsest extremes", "omero window"])
def test_a_streamed_multi_channel_pyramid_renders_as_its_dense_read_each_channel_in_its_colour(tmp_path, kind):
    """``stream=True`` (and a budget under level 0, streamed by itself): two streams of budget / 2; after the bricks
    came, the image is the dense level 0's within 1e-4; red (channel 0) on the left, green (channel 1) on the
    right. The ranges agree with the dense read's: the coarsest level holds the extremes, or (means, lower peaks)
    the omero window says them."""
    path = tmp_path / "two.zarr"
    write_channels(path, mean=kind == "omero window", window=kind == "omero window")
    dense, want = channel_render(path, level=0)
    streamed, got = channel_render(path, stream=True, memory_budget=2**26)
    assert all(isinstance(c, StreamedDensity) for c in streamed.channels) and len(streamed.channels) == 2
    assert [c.memory_budget for c in streamed.channels] == [2**25, 2**25]
    assert streamed.channel_colors == ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    assert np.allclose(streamed.to_world, dense.to_world)
    for c in range(2):
        stream = got.stats.info["channels"][c]["stream"][0]
        assert stream["levels_used"][0] > 0 and stream["bricks_pending"] == 0, c
    image, reference = got.images[0], want.images[0]
    third = image.shape[1] // 3
    red, green = image[..., 0], image[..., 1]
    assert red[:, :third].max() > 0.3 and green[:, -third:].max() > 0.3
    assert red[:, -third:].max() < 0.01 and green[:, :third].max() < 0.01  # each colour where its channel's ball is
    assert np.abs(image - reference).max() <= 1e-4


def test_a_multi_channel_pyramid_over_the_budget_streams_rather_than_a_coarse_level(tmp_path):
    """Level 0 (2 x 128 KiB of float32) over a 192 KiB budget: no longer the finest level that fits (level 1),
    each channel streams in 96 KiB; channel c's densities are its values over its own range."""
    path = tmp_path / "two.zarr"
    data = write_channels(path)
    loaded = load_volume(path, memory_budget=3 * 2**16)
    assert loaded.level == 0 and loaded.density.shape == (N, N, N)
    assert [type(c).__name__ for c in loaded.channels] == ["StreamedDensity"] * 2
    for c, sd in enumerate(loaded.channels):
        assert sd.memory_budget == 3 * 2**15 and sd.source.channel == c
        assert float(sd.max()) == pytest.approx(1.0) and float(sd.min()) == 0.0
        np.testing.assert_allclose(sd[::4, ::4, ::4], data[c, ::4, ::4, ::4] / PEAKS[c], atol=1e-6)
    with pytest.raises(VolrenError, match=r"stream= reads a pyramid brick by brick; it takes no level="):
        load_volume(path, stream=True, level=0)


def test_the_omero_window_end_is_a_streamed_pyramids_largest_density_for_mip(tmp_path):
    """A mean pyramid's coarsest level peaks below the data: its streamed MIP, normalised by that, saturated. With
    the file's omero window stating the true top (4000 of 4095), the largest density is the dense level 0's, and the
    MIP image after refinement is the dense one's."""
    path = tmp_path / "means.zarr"
    top = int(write_pyramid(path, mean=True)[0].max())
    cam = close_camera(scene_of(path, level=0))

    def mip(**load):
        scene = scene_of(path, **load)
        frame = DSSRM(DSSRMConfig(samples=96, mode="mip"), device=DEVICE).render(scene, [cam])
        return scene.volumes[0].density, frame.images[0]

    dense, want = mip(level=0)
    coarse, _ = mip(stream=True, memory_budget=2**26)
    assert float(coarse.max()) < float(dense.max()) - 0.05  # the means' peak: MIP would saturate
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["ome"]["omero"] = {"channels": [{"window": {"start": 0, "end": top, "min": 0, "max": 65535}}]}
    (path / "zarr.json").write_text(json.dumps(meta))
    streamed, got = mip(stream=True, memory_budget=2**26)
    assert float(streamed.max()) == pytest.approx(float(dense.max()), abs=1e-6)
    assert want[..., 3].max() > 0.5 and np.abs(got - want).max() <= 1e-4

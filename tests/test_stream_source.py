"""Streaming sources (issue 41 item 3, `volren.stream.source`): an OME-Zarr pyramid read brick by brick, in the brick
layout of `volren.kernels.bricks` (voxels [b B, b B + B], the last voxel repeated past the border), the same from a
folder, a zip and a loopback HTTP server; bad chunks (missing where the coarser level has data, or corrupt) read as
None with one warning naming the chunk."""

from __future__ import annotations

import contextlib
import http.server
import shutil
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

zarr = pytest.importorskip("zarr")
writer = pytest.importorskip("ome_zarr.writer")

from volren.errors import VolrenError, VolrenWarning  # noqa: E402
from volren.stream import BRICK, PyramidSource  # noqa: E402

B = BRICK


def write_pyramid(path: Path, *, shape=(40, 40, 40), levels: int = 3, chunks: int = 16, channels: int = 0,
                  zero_box: tuple[slice, ...] | None = None, seed: int = 7) -> list[np.ndarray]:
    """An OME-Zarr (NGFF 0.5) pyramid of random uint16 values 1..999 (no chunk equals the fill value 0, so every
    chunk is on disk, unless ``zero_box`` zeroes some), each level the previous one's every second voxel per axis;
    returns the levels ([c,] z, y, x)."""
    data = np.random.default_rng(seed).integers(1, 1000, ((channels,) if channels else ()) + tuple(shape),
                                                dtype=np.uint16)
    if zero_box is not None:
        data[(..., *zero_box)] = 0
    pyramid = [data]
    for _ in range(levels - 1):
        pyramid.append(np.ascontiguousarray(pyramid[-1][..., ::2, ::2, ::2]))
    axes = ([{"name": "c", "type": "channel"}] if channels else []) + [
        {"name": n, "type": "space", "unit": "micrometer"} for n in "zyx"]
    lead = [1.0] if channels else []
    transforms = [[{"type": "scale", "scale": lead + [2.0**k] * 3}] for k in range(levels)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        writer.write_multiscale(pyramid, zarr.open_group(str(path), mode="w"), axes=axes,
                                coordinate_transformations=transforms,
                                storage_options={"chunks": ((1,) if channels else ()) + (chunks,) * 3})
    return pyramid


def expected_brick(level: np.ndarray, brick) -> np.ndarray:
    """Brick ``brick`` cut from the level's array: voxels [b B, b B + B], the last voxel repeated past the border."""
    padded = np.pad(level.astype(np.float32), [(0, B + 1)] * 3, mode="edge")
    return padded[tuple(slice(b * B, b * B + B + 1) for b in brick)]


@contextlib.contextmanager
def serve_folder(folder: Path, *, slow: str | None = None, delay: float = 0.0):
    """A loopback HTTP server of ``folder`` in a thread; GETs of paths starting with ``slow`` wait ``delay`` [s]."""

    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, directory=str(folder), **kwargs)

        def log_message(self, *args):
            pass

        def do_GET(self):
            if slow is not None and self.path.startswith(slow):
                time.sleep(delay)
            super().do_GET()

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


@pytest.mark.timeout(60)
def test_every_brick_equals_slicing_its_level(tmp_path):
    levels = write_pyramid(tmp_path / "p.zarr")
    with PyramidSource(tmp_path / "p.zarr") as source:
        assert source.layout.shapes == ((40, 40, 40), (20, 20, 20), (10, 10, 10))
        assert source.layout.factors == ((2, 2, 2), (2, 2, 2))
        assert [source.layout.bricks(k) for k in range(3)] == [(3, 3, 3), (2, 2, 2), (1, 1, 1)]
        assert source.scales == ((1.0,) * 3, (2.0,) * 3, (4.0,) * 3)
        for k, level in enumerate(levels):
            for brick in np.ndindex(*source.layout.bricks(k)):
                got = source.read_brick(k, *brick)
                assert got.dtype == np.float32 and got.shape == (B + 1,) * 3
                np.testing.assert_array_equal(got, expected_brick(level, brick), err_msg=f"level {k} {brick}")
        interior = source.read_brick(0, 0, 1, 0)
        assert interior[B, 0, B] == levels[0][B, B, B]  # the apron: the next brick's first voxel
        border = source.read_brick(0, 2, 2, 2)  # voxels 32..39, then voxel 39 repeated to 48
        assert border[7, 7, 7] == levels[0][39, 39, 39] and border[B, B, B] == levels[0][39, 39, 39]
        assert border[B, 0, 0] == levels[0][39, 32, 32] and border[6, 0, 0] == levels[0][38, 32, 32]
        with pytest.raises(VolrenError, match=r"no brick \(3, 0, 0\) at level 0"):
            source.read_brick(0, 3, 0, 0)


@pytest.mark.timeout(60)
def test_bytes_read_count_each_chunk_once(tmp_path):
    write_pyramid(tmp_path / "p.zarr")
    with PyramidSource(tmp_path / "p.zarr") as source:
        source.read_brick(0, 0, 0, 0)  # voxels 0..16: chunks 0 and 1 per axis, 16^3 and 16^3 uint16 each
        assert source.bytes_read == 8 * 16**3 * 2
        source.read_brick(0, 0, 0, 1)  # voxels x 16..32: chunks x 1 (cached) and 2 (8 voxels: 40 = 2 x 16 + 8)
        assert source.bytes_read == 8 * 16**3 * 2 + 4 * 16 * 16 * 8 * 2


@pytest.mark.timeout(60)
def test_a_channel_is_chosen(tmp_path):
    levels = write_pyramid(tmp_path / "c.zarr", channels=2, levels=2)
    with PyramidSource(tmp_path / "c.zarr", channel=1) as source:
        assert source.channels == 2 and source.layout.shapes == ((40, 40, 40), (20, 20, 20))
        np.testing.assert_array_equal(source.read_brick(1, 1, 0, 1), expected_brick(levels[1][1], (1, 0, 1)))
        assert source.chunk_key(0, (1, 2, 0)) == "s0/c/1/1/2/0"  # the channel's chunk
    with pytest.raises(VolrenError, match="2 channels; choose one"):
        PyramidSource(tmp_path / "c.zarr")
    with pytest.raises(VolrenError, match="channel 2 is out of range"):
        PyramidSource(tmp_path / "c.zarr", channel=2)


@pytest.mark.timeout(60)
def test_zip_store_reads_as_the_folder(tmp_path):
    levels = write_pyramid(tmp_path / "p.zarr")
    shutil.make_archive(str(tmp_path / "p"), "zip", tmp_path / "p.zarr")
    with PyramidSource(tmp_path / "p.zip") as source:
        for k in range(3):
            for brick in np.ndindex(*source.layout.bricks(k)):
                np.testing.assert_array_equal(source.read_brick(k, *brick), expected_brick(levels[k], brick))


@pytest.mark.timeout(60)
def test_http_store_reads_as_the_folder(tmp_path):
    levels = write_pyramid(tmp_path / "p.zarr")
    with serve_folder(tmp_path) as url, PyramidSource(f"{url}/p.zarr") as source:
        assert source.layout.shapes == ((40, 40, 40), (20, 20, 20), (10, 10, 10))
        for k in range(3):
            for brick in np.ndindex(*source.layout.bricks(k)):
                np.testing.assert_array_equal(source.read_brick(k, *brick), expected_brick(levels[k], brick))
        assert source.bad_chunks == {}


@pytest.mark.timeout(60)
def test_a_missing_chunk_reads_none_with_one_warning(tmp_path):
    levels = write_pyramid(tmp_path / "p.zarr")
    (tmp_path / "p.zarr" / "s0" / "c" / "1" / "1" / "1").unlink()  # level 0's chunk (1, 1, 1): voxels 16..31
    with PyramidSource(tmp_path / "p.zarr") as source:
        with pytest.warns(VolrenWarning) as record:
            assert source.read_brick(0, 1, 1, 1) is None  # voxels 16..32: the chunk, and its neighbours' faces
            assert source.read_brick(0, 0, 0, 0) is None  # voxels 0..16: the apron meets the chunk's corner
        assert len(record) == 1
        message = str(record[0].message)
        assert "chunk 's0/c/1/1/1'" in message and str(tmp_path / "p.zarr") in message
        assert "missing where level 1 holds data" in message and "drawn from level 1" in message
        assert source.bad_chunks.keys() == {"s0/c/1/1/1"}
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no second warning for the same chunk
            assert source.read_brick(0, 1, 1, 0) is None
            np.testing.assert_array_equal(source.read_brick(0, 2, 2, 2), expected_brick(levels[0], (2, 2, 2)))


@pytest.mark.timeout(60)
def test_an_absent_chunk_over_empty_coarse_data_is_empty(tmp_path):
    """zarr leaves out a chunk of fill values: where the coarser level is empty too it reads as zeros, unwarned."""
    levels = write_pyramid(tmp_path / "p.zarr", zero_box=(slice(0, 32), slice(0, 32), slice(0, 32)))
    assert not (tmp_path / "p.zarr" / "s0" / "c" / "0" / "0" / "0").exists()
    with PyramidSource(tmp_path / "p.zarr") as source, warnings.catch_warnings():
        warnings.simplefilter("error")
        brick = source.read_brick(0, 0, 0, 0)
        assert not brick.any()
        np.testing.assert_array_equal(brick, expected_brick(levels[0], (0, 0, 0)))
        assert source.bad_chunks == {}


@pytest.mark.timeout(60)
def test_a_corrupt_chunk_reads_none_and_the_coarsest_reads_its_fill(tmp_path):
    write_pyramid(tmp_path / "p.zarr")
    (tmp_path / "p.zarr" / "s1" / "c" / "0" / "1" / "0").write_bytes(b"not zstd at all")
    (tmp_path / "p.zarr" / "s2" / "c" / "0" / "0" / "0").write_bytes(b"garbage")
    with PyramidSource(tmp_path / "p.zarr") as source:
        with pytest.warns(VolrenWarning, match=r"chunk 's1/c/0/1/0' of level 1 cannot be read"):
            assert source.read_brick(1, 0, 1, 0) is None
        with pytest.warns(VolrenWarning, match=r"chunk 's2/c/0/0/0' of level 2 cannot be read .* fill value 0"):
            coarsest = source.read_brick(2, 0, 0, 0)
        np.testing.assert_array_equal(coarsest, np.zeros((B + 1,) * 3, np.float32))


@pytest.mark.timeout(60)
def test_a_place_without_a_pyramid_is_one_line(tmp_path):
    with pytest.raises(VolrenError, match="file not found"):
        PyramidSource(tmp_path / "none.zarr")
    zarr.open_group(str(tmp_path / "g.zarr"), mode="w")
    with pytest.raises(VolrenError, match="without OME-Zarr 'multiscales'"):
        PyramidSource(tmp_path / "g.zarr")


@pytest.mark.timeout(60)
def test_a_missing_chunk_over_http_is_found_as_on_disk(tmp_path):
    write_pyramid(tmp_path / "p.zarr")
    (tmp_path / "p.zarr" / "s1" / "c" / "0" / "0" / "1").unlink()  # level 1's chunk (0, 0, 1): x voxels 16..19
    with serve_folder(tmp_path) as url, PyramidSource(f"{url}/p.zarr") as source:
        with pytest.warns(VolrenWarning, match=r"chunk 's1/c/0/0/1' of level 1 is missing where level 2 holds data"):
            assert source.read_brick(1, 0, 0, 1) is None
        assert list(source.bad_chunks) == ["s1/c/0/0/1"]


@pytest.mark.timeout(60)
def test_the_stream_package_builds_on_data_only():
    """Source -> cache -> renderer, one way: volren.stream imports no renderer, plan, front end or Warp itself."""
    from test_layout import SRC, imported_modules

    files = sorted((SRC / "stream").glob("*.py"))
    assert {p.stem for p in files} >= {"__init__", "layout", "source", "lod", "cache", "streamer", "density"}
    found = {m for p in files for _, m in imported_modules(p.read_text(), "volren.stream")}
    allowed = ("volren.stream", "volren.data.ngff", "volren.data.grid", "volren.errors", "volren.camera",
               "volren.sparse")
    volren = {m for m in found if m.startswith("volren.")}
    assert {m for m in volren if not m.startswith(allowed)} == set()
    assert {a for a in allowed if any(m.startswith(a) for m in volren)} == set(allowed)  # the check reads imports
    assert not any(m == "warp" or m.startswith("warp.") for m in found)

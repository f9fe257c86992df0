"""Where a pyramid's bytes come from (issue 41 item 3): an OME-Zarr multiscale image in a local folder, a ``.zip``
store or at any fsspec URL (``http://``, ``s3://`` with s3fs installed), read one brick at a time.

A brick of level k is read as `volren.kernels.bricks` lays it out: voxels [b B, b B + B] per axis, (B+1)^3 float32
with a one-voxel apron, past the level's high border the last voxel repeated. The values are the file's, as float32
(no normalisation: that needs the whole volume's range; the coarsest level's is at hand).

Chunks are read whole (a shard, where the array is sharded) and kept decoded in a small LRU (``chunk_cache_bytes``),
so the bricks of a chunk cost one read; ``bytes_read`` counts the decoded bytes of every chunk read, in the file's
dtype.

A chunk is **bad** where it cannot be decoded (a codec or store error), or is absent where the next coarser level
holds data (zarr leaves out a chunk that holds only the fill value, so an absent chunk is empty or lost: it is lost
where the coarser level shows data in its box, margins left out, as `volren.data.omezarr._missing_chunks` decides).
A brick touching a bad chunk reads as None: the caller draws the brick's coarser ancestor. Each bad chunk is warned of
once, naming the store and the chunk's key. At the coarsest level, with no ancestor, a bad chunk reads as the fill
value, and the warning says so.
"""

from __future__ import annotations

import importlib.util
import math
import threading
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from volren.data.grid import one_line
from volren.data.ngff import _attributes, _axes, _fill, _scale_translation, coarser_inner_box
from volren.errors import VolrenError, VolrenWarning
from volren.stream.layout import BRICK, Brick, PyramidLayout

CHUNK_CACHE_BYTES = 64 << 20
"""[bytes] of decoded chunks a source keeps for the next bricks of the same chunks"""


def _open_group(url: str, storage_options: dict[str, Any] | None) -> tuple[Any, Any]:
    """The Zarr group at ``url`` and the store to close (a zip's), or None."""
    import zarr  # lazy: only Zarr users pay for the import

    if "://" in url and not url.startswith("file://"):
        if url.startswith(("s3://", "s3a://")) and importlib.util.find_spec("s3fs") is None:
            raise VolrenError(f"{url}: s3:// stores need s3fs: pip install 'volren[s3]'")
        return zarr.open_group(url, mode="r", storage_options=storage_options), None
    path = Path(url.removeprefix("file://"))
    if not path.exists():
        raise VolrenError(f"{url}: file not found")
    if path.is_file() and path.suffix.lower() == ".zip":
        store = zarr.storage.ZipStore(path, mode="r")
        try:
            return zarr.open_group(store, mode="r"), store
        except Exception:
            store.close()
            raise
    return zarr.open_group(str(path), mode="r"), None


class PyramidSource:
    """One channel of an OME-Zarr multiscale image, read brick by brick (module docstring). Thread-safe: the
    streamer's readers share one source. Use as a context manager, or `close`."""

    def __init__(self, url: str | Path, *, channel: int | None = None, chunk_cache_bytes: int = CHUNK_CACHE_BYTES,
                 storage_options: dict[str, Any] | None = None) -> None:
        self.name = str(url)
        try:
            group, self._store = _open_group(self.name, storage_options)
        except VolrenError:
            raise
        except Exception as exc:  # zarr and fsspec raise many types for a place that holds no Zarr group
            raise VolrenError(f"{self.name}: not a readable Zarr group ({one_line(exc)})") from None
        try:
            self._read_metadata(group, channel)
        except VolrenError:
            self.close()
            raise
        except Exception as exc:  # KeyError, TypeError, ValueError: metadata that is not NGFF
            self.close()
            raise VolrenError(f"{self.name}: malformed OME-Zarr metadata ({one_line(exc)})") from None
        self._lock = threading.Lock()
        self._chunks: OrderedDict[tuple[int, ...], np.ndarray | None] = OrderedDict()
        self._chunk_bytes = 0
        self._chunk_budget = int(chunk_cache_bytes)
        self._reading: dict[tuple[int, ...], threading.Event] = {}
        self.bad_chunks: dict[str, str] = {}
        """chunk key (the array's path and the chunk's key in the store) -> why it is bad"""
        self._unwarned: list[str] = []
        self.bytes_read = 0
        """[bytes] decoded chunk bytes read from the store, in the file's dtype, since the source opened"""

    def _read_metadata(self, group: Any, channel: int | None) -> None:
        attrs = _attributes(group)
        if "multiscales" not in attrs:
            raise VolrenError(f"{self.name}: a Zarr group without OME-Zarr 'multiscales' metadata")
        multiscale = attrs["multiscales"][0]
        datasets = multiscale["datasets"]
        if not datasets:
            raise ValueError("'datasets' is empty")
        self._arrays = [group[str(d["path"])] for d in datasets]
        ndim = self._arrays[0].ndim
        axes = _axes(multiscale, ndim)
        names = [a[0] for a in axes]
        self._space = [i for i, a in enumerate(axes) if a[1] == "space"]
        if [names[i] for i in self._space] != ["z", "y", "x"]:
            raise VolrenError(f"{self.name}: axes {''.join(names)}: volren needs the space axes z, y, x in that order")
        chan = [i for i, a in enumerate(axes) if a[1] == "channel"]
        if len(chan) > 1:
            raise VolrenError(f"{self.name}: axes {''.join(names)} hold more than one channel axis")
        self.channels = self._arrays[0].shape[chan[0]] if chan else 1
        if channel is None and self.channels > 1:
            raise VolrenError(f"{self.name}: {self.channels} channels; choose one (channel=0 to "
                              f"{self.channels - 1})")
        self.channel = 0 if channel is None else int(channel)
        if not 0 <= self.channel < self.channels:
            raise VolrenError(f"{self.name}: channel {channel} is out of range: the image has channels 0 to "
                              f"{self.channels - 1}")
        for i, (name, _, _) in enumerate(axes):
            if i not in self._space and i not in chan and self._arrays[0].shape[i] != 1:
                raise VolrenError(f"{self.name}: axis '{name}' has {self._arrays[0].shape[i]} entries; a stream "
                                  "reads one volume (a channel axis 'c' and z, y, x)")
        self._chan_axis = chan[0] if chan else None
        outer, outer_offset = _scale_translation(multiscale.get("coordinateTransformations", []), ndim)
        own = [_scale_translation(d["coordinateTransformations"], ndim) for d in datasets]
        self.scales = tuple(tuple(float(s[i] * outer[i]) for i in self._space) for s, _ in own)
        """[file units] voxel size (z, y, x) per level"""
        self.translations = tuple(tuple(float(t[i] * outer[i] + outer_offset[i]) for i in self._space)
                                  for _, t in own)
        """[file units] where voxel 0 (z, y, x) of each level lies: coordinate = index * scale + translation"""
        shapes = tuple(tuple(int(a.shape[i]) for i in self._space) for a in self._arrays)
        factors = []
        for k in range(len(shapes) - 1):
            ratio = [c / f for c, f in zip(self.scales[k + 1], self.scales[k], strict=True)]
            whole = [round(r) for r in ratio]
            if any(w < 1 or abs(r - w) > 1e-6 * w for r, w in zip(ratio, whole, strict=True)):
                raise VolrenError(f"{self.name}: level {k + 1}'s voxel is {ratio} times level {k}'s (z, y, x); "
                                  "streaming needs whole downsampling factors")
            factors.append(tuple(whole))
        self.layout = PyramidLayout(shapes, tuple(factors))  # type: ignore[arg-type]
        self._units = [tuple(int(u) for u in (a.shards or a.chunks)) for a in self._arrays]

    # ------------------------------------------------------------------ chunks

    def _chunk_index(self, level: int, space_chunk: Brick) -> tuple[int, ...]:
        """The chunk's coordinates over all of the array's axes: the channel's chunk, 0 on a length-1 axis."""
        unit, out = self._units[level], []
        for i in range(len(unit)):
            if i in self._space:
                out.append(space_chunk[self._space.index(i)])
            else:
                out.append(self.channel // unit[i] if i == self._chan_axis else 0)
        return tuple(out)

    def chunk_key(self, level: int, space_chunk: Brick) -> str:
        """The chunk's key in the store: the level array's path and its chunk key (``s0/c/0/1/0/2``)."""
        array = self._arrays[level]
        key = array.metadata.encode_chunk_key(self._chunk_index(level, space_chunk))
        return f"{array.store_path.path}/{key}" if array.store_path.path else key

    def _selection(self, level: int, box: list[tuple[int, int]]) -> tuple[Any, ...]:
        ndim = len(self._units[level])
        return tuple(slice(*box[self._space.index(i)]) if i in self._space else
                     (self.channel if i == self._chan_axis else 0) for i in range(ndim))

    def _box(self, level: int, space_chunk: Brick) -> list[tuple[int, int]]:
        unit = [self._units[level][i] for i in self._space]
        return [(c * u, min((c + 1) * u, n)) for c, u, n in zip(space_chunk, unit, self.layout.shapes[level],
                                                                  strict=True)]

    def _exists(self, level: int, space_chunk: Brick) -> bool:
        from zarr.core.sync import sync

        array = self._arrays[level]
        return bool(sync(array.store_path.store.exists(self.chunk_key(level, space_chunk))))

    def _bad(self, level: int, space_chunk: Brick, why: str) -> None:
        key = self.chunk_key(level, space_chunk)
        with self._lock:
            if key in self.bad_chunks:
                return
            self.bad_chunks[key] = why
            drawn = (f"its bricks are drawn from level {level + 1}" if level < self.layout.coarsest else
                     f"read as the fill value {_fill(self._arrays[level]):g} (the coarsest level has no ancestor)")
            self._unwarned.append(f"{self.name}: chunk '{key}' of level {level} {why}; {drawn}")

    def _hole(self, level: int, space_chunk: Brick, box: list[tuple[int, int]]) -> bool:
        """Whether the chunk at ``box``, read as the fill value, is absent where level + 1 holds data."""
        if self._exists(level, space_chunk):
            return False
        inner = coarser_inner_box(box, [1 / f for f in self.layout.factors[level]])
        if not all(s.start < s.stop for s in inner):
            return False
        try:
            coarser = np.asarray(self._arrays[level + 1][self._selection(level + 1, [(s.start, s.stop)
                                                                                    for s in inner])])
        except Exception:  # the coarser chunk is bad too: it warns when its own bricks are read
            return False
        with self._lock:
            self.bytes_read += coarser.nbytes
        return bool(np.any((coarser != _fill(self._arrays[level + 1])) & ~np.isnan(coarser)))

    def _read_chunk(self, level: int, space_chunk: Brick) -> np.ndarray | None:
        """The chunk's voxels (z, y, x) of the channel, decoded, or None where it is bad."""
        array = self._arrays[level]
        box = self._box(level, space_chunk)
        try:
            data = np.asarray(array[self._selection(level, box)])
        except Exception as exc:  # a codec's or the store's error: the chunk cannot be read
            self._bad(level, space_chunk, f"cannot be read ({one_line(exc)})")
            return None
        with self._lock:
            self.bytes_read += data.nbytes
        fill = _fill(array)
        empty = np.all(data == fill) or (math.isnan(fill) and np.all(np.isnan(data)))
        if level < self.layout.coarsest and empty and self._hole(level, space_chunk, box):
            self._bad(level, space_chunk, f"is missing where level {level + 1} holds data")
            return None
        return data

    def _chunk(self, level: int, space_chunk: Brick) -> np.ndarray | None:
        """The chunk from the LRU, or read once: a reader that meets a chunk another is reading waits for it."""
        key = (level, *space_chunk)
        while True:
            with self._lock:
                if key in self._chunks:
                    self._chunks.move_to_end(key)
                    return self._chunks[key]
                event = self._reading.get(key)
                if event is None:
                    event = self._reading[key] = threading.Event()
                    break
            event.wait()  # then take it from the LRU (or read it, where it was already evicted or failed)
        done, data = False, None
        try:
            data = self._read_chunk(level, space_chunk)
            done = True
        finally:
            with self._lock:
                del self._reading[key]
                if done:
                    self._chunks[key] = data
                    self._chunk_bytes += 0 if data is None else data.nbytes
                    while self._chunk_bytes > self._chunk_budget and len(self._chunks) > 1:
                        _, old = self._chunks.popitem(last=False)
                        self._chunk_bytes -= 0 if old is None else old.nbytes
            event.set()
        return data

    # ------------------------------------------------------------------ bricks

    def read_brick(self, level: int, bz: int, by: int, bx: int, *, warn: bool = True) -> np.ndarray | None:
        """Brick (bz, by, bx) of ``level`` as float32 (B+1)^3: voxels [b B, b B + B] per axis, the last voxel
        repeated past the level's high border; None where a chunk it touches is bad (module docstring) and the
        level has a coarser one. ``warn``: emit the warnings of newly found bad chunks now (else `pop_warnings`)."""
        brick = (bz, by, bx)
        if not self.layout.contains(level, brick):
            raise VolrenError(f"{self.name}: no brick {brick} at level {level} (the pyramid has levels 0 to "
                              f"{self.layout.coarsest}; level {level} has bricks "
                              f"{self.layout.bricks(level) if 0 <= level < self.layout.count else '-'})")
        shape = self.layout.shapes[level]
        lo = [b * BRICK for b in brick]
        hi = [min(a + BRICK, n - 1) for a, n in zip(lo, shape, strict=True)]  # the last voxel read, inclusive
        out = np.empty([h - a + 1 for a, h in zip(lo, hi, strict=True)], np.float32)
        unit = [self._units[level][i] for i in self._space]
        ranges = [range(a // u, h // u + 1) for a, h, u in zip(lo, hi, unit, strict=True)]
        whole = True
        for cz in ranges[0]:
            for cy in ranges[1]:
                for cx in ranges[2]:
                    chunk = self._chunk(level, (cz, cy, cx))
                    if chunk is None:
                        if level < self.layout.coarsest:
                            whole = False
                            continue
                        chunk = np.full([b - a for a, b in self._box(level, (cz, cy, cx))],
                                        _fill(self._arrays[level]), np.float32)
                    box = self._box(level, (cz, cy, cx))
                    src = tuple(slice(max(a, c0) - c0, min(h + 1, c1) - c0)
                                for a, h, (c0, c1) in zip(lo, hi, box, strict=True))
                    dst = tuple(slice(max(a, c0) - a, min(h + 1, c1) - a)
                                for a, h, (c0, c1) in zip(lo, hi, box, strict=True))
                    out[dst] = chunk[src]
        if warn:
            for message in self.pop_warnings():
                warnings.warn(message, VolrenWarning, stacklevel=2)
        if not whole:
            return None
        pad = [(0, BRICK + 1 - n) for n in out.shape]
        return np.pad(out, pad, mode="edge") if any(p for _, p in pad) else out

    def pop_warnings(self) -> list[str]:
        """The warnings (one line each) of the bad chunks found since the last call, each chunk once."""
        with self._lock:
            out, self._unwarned = self._unwarned, []
        return out

    def close(self) -> None:
        if getattr(self, "_store", None) is not None:
            self._store.close()
            self._store = None

    def __enter__(self) -> PyramidSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

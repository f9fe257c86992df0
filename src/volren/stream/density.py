"""A streamed pyramid standing where a volume's dense grid stands (`volren.scene.Volume.density`; issue 41 item 3):
the finest level's shape, values mapped to densities as the loader maps a level's, and the bricks a frame needs read
on demand (`volren.stream.streamer`) into a device pool by the renderers (`volren.render.streaming`).

What a renderer derives from a whole grid it derives here from the coarsest level, which is always resident: the
largest and smallest density (`max`, `min`), and the strided reads of a threshold or a flame's brightness
(`__getitem__`). A coarse level's voxels are means of the finer ones, so its maximum may be below the data's: the
densities keep the mapping fixed at open (`value_scale`, `value_offset`), and MIP's normalisation by the maximum may
saturate where a fine voxel is brighter than every coarse one, unless the file states the data's top (``peak``: the
omero window's end, `volren.data.omezarr._streamed`), which `max` then reports.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from volren.stream.layout import BRICK, PyramidLayout
from volren.stream.source import PyramidSource
from volren.stream.streamer import BRICK_BYTES, BrickStreamer


class StreamedDensity:
    """The finest level of ``source`` as a volume's density, streamed brick by brick within ``memory_budget``
    [bytes]: half for the host's brick cache, half for the device pool (module docstring). Values v read as
    ``v * value_scale + value_offset``; ``peak``: the largest density where the file states it (module
    docstring)."""

    ndim = 3
    dtype = np.dtype(np.float32)
    brick = BRICK
    level = 0
    """its level in the pyramid (`StreamedLevel`)"""
    streamed = True
    """what the scene and the upload recognise it by (they do not import the stream package)"""

    def __init__(self, source: PyramidSource, memory_budget: float, value_scale: float = 1.0,
                 value_offset: float = 0.0, peak: float | None = None) -> None:
        self.source, self.layout = source, source.layout
        self.memory_budget = int(memory_budget)
        self.value_scale, self.value_offset = float(value_scale), float(value_offset)
        self.streamer = BrickStreamer(source, memory_budget=self.memory_budget // 2)
        # the readers stop when the volume goes (a notebook dropping it), not only on close
        self._finalizer = weakref.finalize(self, _close, self.streamer, source)
        self.shape: tuple[int, int, int] = tuple(self.layout.shapes[0])  # type: ignore[assignment]
        top = self.layout.coarsest
        self._coarse = self.mapped(self._coarsest_level(top))
        self.peak = None if peak is None else float(peak)

    def _coarsest_level(self, top: int) -> np.ndarray:
        """The coarsest level's voxels, from its resident bricks (their apron-less parts)."""
        out = np.zeros(self.layout.shapes[top], np.float32)
        b = self.layout.brick
        for key in self.streamer.floor_keys():
            _, bz, by, bx, array = *key, self.streamer.cache.get(key)
            part = out[bz * b : bz * b + b + 1, by * b : by * b + b + 1, bx * b : bx * b + b + 1]
            part[...] = array[: part.shape[0], : part.shape[1], : part.shape[2]]
        return out

    def __repr__(self) -> str:
        return (f"StreamedDensity({self.source.name}, {'x'.join(map(str, self.shape[::-1]))} voxels (x, y, z) in "
                f"{self.layout.count} levels, budget {self.memory_budget / 2**20:.0f} MiB)")

    def mapped(self, raw: np.ndarray) -> np.ndarray:
        """File values as densities (the mapping fixed at open)."""
        out = raw.astype(np.float32) * np.float32(self.value_scale) + np.float32(self.value_offset)
        return np.maximum(out, 0.0, out=out)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        """[bytes] the host's resident bricks now."""
        return int(self.streamer.cache.resident_bytes)

    @property
    def device_bricks(self) -> int:
        """Bricks the device pool holds: half of the budget."""
        return max(len(self.streamer.floor_keys()), (self.memory_budget // 2) // BRICK_BYTES)

    def max(self, axis: None = None, out: None = None) -> np.float32:
        """The largest density: the file's ``peak`` where it states one above the coarsest level's largest (module
        docstring)."""
        return np.float32(max(self._coarse.max(), self.peak or 0.0))

    def min(self, axis: None = None, out: None = None) -> np.float32:
        return np.float32(self._coarse.min())

    @property
    def coarsest(self) -> np.ndarray:
        """The coarsest level's densities (always resident)."""
        return self._coarse

    def __getitem__(self, key: tuple[slice, slice, slice]) -> np.ndarray:
        """``grid[::s, ::s, ::s]``, read from the coarsest level at the stride nearest s over its factor."""
        if not (isinstance(key, tuple) and len(key) == 3 and all(isinstance(k, slice) for k in key)):
            raise TypeError(f"a StreamedDensity takes three slices, got {key!r}")
        factors = np.prod(np.array(self.layout.factors, dtype=np.int64).reshape(-1, 3), axis=0)
        steps = [max(1, round((k.step or 1) / f)) for k, f in zip(key, factors, strict=True)]
        return self._coarse[:: steps[0], :: steps[1], :: steps[2]]

    @cached_property
    def levels(self) -> tuple[StreamedLevel, ...]:
        """The pyramid's levels as a volume's mip levels (`volren.scene.Volume.mip_pyramid`): what the cube-map
        methods march far away, streamed from the same pool (`volren.upload.pack_stream`)."""
        return tuple(StreamedLevel(self, k) for k in range(self.layout.count))

    def level_maps(self, base: int = 0) -> np.ndarray:
        """(levels - base, 6) float32: per level k >= ``base`` (a x, y, z, b x, y, z) with level-k index = a v + b
        for level-``base`` index v (x, y, z), from the levels' scales and translations: a = s_base / s_k,
        b = (t_base - t_k) / s_k."""
        s = np.array(self.source.scales, np.float64)[base:, ::-1]
        t = np.array(self.source.translations, np.float64)[base:, ::-1]
        return np.concatenate([s[0] / s, (t[0] - t) / s], axis=1).astype(np.float32)

    def stats(self) -> dict[str, Any]:
        return self.streamer.stats()

    def close(self) -> None:
        self._finalizer()


@dataclass(frozen=True)
class StreamedLevel:
    """Level ``level`` of a streamed pyramid as a mip level of its volume: its shape, and where its bricks come from
    (the level 0 `StreamedDensity`)."""

    density: StreamedDensity
    level: int
    streamed = True
    ndim = 3
    brick = BRICK

    @property
    def layout(self) -> PyramidLayout:
        return self.density.layout

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.density.layout.shapes[self.level])  # type: ignore[return-value]


def _close(streamer: BrickStreamer, source: PyramidSource) -> None:
    streamer.close()
    source.close()

"""Streamed volumes on the device (issue 41 item 3): each frame, the bricks the views need are asked of the volume's
`volren.stream.streamer.BrickStreamer` (and waited for by ``render`` and ``animate``; never by ``serve``'s ticks),
and those resident on the host are placed in the volume's device pool, a fixed number of brick slots reserved at
upload (`volren.upload.pack_stream`). The page table of every level then says, per brick: its slot, `EMPTY` (a
brick whose voxels are all 0 takes no slot), or `NOT_RESIDENT`, which `volren.kernels.common.gather_density` draws
from the finest resident ancestor: the coarsest level is always on the device, so a sample never meets a hole.

Slots: a brick keeps its slot while a frame wants it; a new one takes a free slot, else the least recently wanted
one. When a frame wants more bricks than the pool holds, the coarsest level and then the needs in priority order
(`volren.stream.lod`) get slots, and the rest are drawn from their ancestors.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from volren.camera import Camera
from volren.kernels.common import NOT_RESIDENT
from volren.render.stream_bounds import refresh_bounds
from volren.sparse import EMPTY
from volren.stream.lod import frame_needs
from volren.upload import BrickKey, StreamState, write_device


def _entry(state: StreamState, key: BrickKey) -> int:
    level, bz, by, bx = key
    bricks = state.density.layout.bricks(level)
    return state.level_starts[level] + (bz * bricks[1] + by) * bricks[2] + bx


def update_stream(ds, state: StreamState, views: Sequence[Camera], wait: bool,
                  progress: Callable[[int, int], Any] | None = None, *, marched: int | None = None,
                  ancestors: bool = False) -> bool:
    """Ask for the bricks ``views`` need (waiting for them with ``wait``; ``marched`` and ``ancestors`` as in
    `volren.stream.lod.frame_needs`), place the resident ones in the device pool and write the page tables (module
    docstring). Returns whether the device's bricks changed."""
    sd = state.density
    streamer = sd.streamer
    vol = ds.scene.volumes[state.volume]
    needs = frame_needs(views, vol.to_world, sd.layout, marched=marched, ancestors=ancestors, limit=streamer.room)
    if wait:
        streamer.wait(needs, progress=progress)
    else:
        streamer.request(needs)
    wanted: dict[BrickKey, np.ndarray] = {}
    for key in streamer.floor_keys():
        wanted[key] = streamer.cache.get(key)
    for key, array in streamer.resident_for(needs).items():  # each need as the finest brick resident for it, in
        wanted.setdefault(key, array)  # priority order
    changed = False
    edge3 = (sd.brick + 1) ** 3
    placed = 0
    for key, array in wanted.items():
        if key in state.empty:
            continue
        if key in state.slots:
            state.slots.move_to_end(key)
            placed += 1
            continue
        if placed >= state.capacity:  # the pool holds as many bricks as the host's cache, but a reader may have
            continue  # cached one more while this frame looked: drawn from its ancestor, not over an urgent one
        values = sd.mapped(array)
        if not values.any():
            state.empty.add(key)
            state.tables[_entry(state, key)] = EMPTY
            changed = True
            continue
        if len(state.slots) < state.capacity:
            slot = len(state.slots)
        else:
            old, slot = state.slots.popitem(last=False)  # the least recently wanted
            state.tables[_entry(state, old)] = NOT_RESIDENT
            del state.maxima[old]
        state.slots[key] = slot
        state.maxima[key] = float(values.max())
        state.tables[_entry(state, key)] = slot
        write_device(ds.density, state.pool_offset + slot * edge3, values)
        placed += 1
        changed = True
    if changed:
        write_device(ds.table, state.table_offset, state.tables)
    return changed


def update_streams(ds, views: Sequence[Camera], wait: bool, progress: Callable[[int, int], Any] | None = None,
                   marched: Sequence[int] | None = None, ancestors: bool = False) -> list[dict[str, Any]]:
    """`update_stream` for each streamed volume of ``ds`` (``marched``: per volume of the scene, a level the renderer
    marches besides the footprint's, or None); their stats (stats.json's ``stream``). A change rewrites the
    bounds of what the bricks draw (`volren.render.stream_bounds`) and makes the light map and what else derives from
    the densities out of date: ``ds.stream_generation`` counts them."""
    out = []
    for state in ds.streams:
        level = marched[state.volume] if marched is not None else None
        if update_stream(ds, state, views, wait, progress, marched=level, ancestors=ancestors) or not state.bounds:
            refresh_bounds(ds, state)
            ds.stream_generation += 1
        out.append({**state.density.stats(), "device_bricks": len(state.slots), "device_capacity": state.capacity,
                    "empty_bricks": len(state.empty)})
    return out

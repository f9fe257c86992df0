"""Bounds of the densities a streamed volume draws now (issue 41: empty-space skipping, culling and VPT majorants
derived from the page table, never from a dense copy).

A streamed volume's sample comes from the bricks on the device (`volren.kernels.common.gather_density`): its own
brick where resident, else a resident level-0 neighbour's apron, else the finest resident ancestor (a trilinear
sample inside one ancestor brick). So, per brick c of level j, every density drawn there is at most

    D_j(c) = R_j(c)       where c is on the device (its largest voxel, apron included; 0 for an `EMPTY` brick),
    D_j(c) = the largest R_k of the bricks of level k > j that c's voxels map into (`ancestor_voxel`'s map and
             clamps), for k = j + 1, j + 2, ... up to the first level where they are all on the device, otherwise,

and the level's bound per brick is D_j's maximum over the 3 x 3 x 3 bricks around it: a trilinear sample in brick
c reads voxels up to one beyond it, and a voxel on a brick's first plane may come from the brick before it. These
bounds change only when the device's bricks do, and are rewritten then (`refresh_bounds`): the skip grid of each
uploaded level (cells of one brick, or 2^j bricks a side in a level of more than 128^3 bricks), the cube-map
methods' culling level, and the path tracer's majorants
(`volren.render.vpt.tracer`). They bound the density drawn now, not the file's: a region empty at the coarse level
is skipped until finer bricks come, as its coarse samples are zero.
"""

from __future__ import annotations

import numpy as np

from volren.upload import StreamState, cull_level, neighbourhood_max, skip_cells, stream_skip_group, write_device


def _mapped(a: np.float32, b: np.float32, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a v + b in float32 as the device may compute it: rounded after the product and the sum, or once (fused);
    the smaller and the larger of the two."""
    v32 = v.astype(np.float32)
    plain = a * v32 + b
    fused = (np.float64(a) * v + np.float64(b)).astype(np.float32)
    return np.minimum(plain, fused), np.maximum(plain, fused)


def _covering(maps: np.ndarray, shape: tuple[int, ...], cells: tuple[int, ...], cell: int, shape_up: tuple[int, ...],
              bricks_up: tuple[int, ...], brick: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per axis (z, y, x), for each cell of ``cell`` voxels of a level, the first and last brick of a coarser level
    holding the trilinear cells its voxels [cell c, cell c + cell] are drawn from (``maps``: (a x, y, z, b x, y, z) to
    that level, as `volren.kernels.common.ancestor_voxel` maps them: clamped into the grid, the cell's lowest corner
    at most n - 2)."""
    out = []
    for axis in range(3):
        c = np.arange(cells[axis])
        lo, _ = _mapped(maps[2 - axis], maps[5 - axis], cell * c)
        _, hi = _mapped(maps[2 - axis], maps[5 - axis], np.minimum(cell * c + cell, shape[axis] - 1))
        ends = []
        for x in (lo, hi):
            x = np.clip(x, 0.0, shape_up[axis] - 1)
            lowest = np.clip(np.minimum(x.astype(np.int64), shape_up[axis] - 2), 0, None)
            ends.append(np.minimum(lowest // brick, bricks_up[axis] - 1))
        out.append((ends[0], ends[1]))
    return out


def _range_max(grid: np.ndarray, ranges: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """out[i, j, k] = max of ``grid`` over the box of rows ranges[0][i], columns ranges[1][j], ... (inclusive),
    axis by axis."""
    for axis, (lo, hi) in enumerate(ranges):
        width = int((hi - lo).max()) + 1
        out = None
        for step in range(width):
            part = np.take(grid, np.minimum(lo + step, hi), axis=axis)
            out = part if out is None else np.maximum(out, part)
        grid = out
    return grid


def _on_device(state: StreamState, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per level, the bricks on the device ((m, 3) z, y, x) and their largest voxels (0 for an `EMPTY` brick)."""
    keys = [[] for _ in range(count)]
    values = [[] for _ in range(count)]
    for key in state.empty:
        keys[key[0]].append(key[1:])
        values[key[0]].append(0.0)
    for key in state.slots:
        keys[key[0]].append(key[1:])
        values[key[0]].append(state.maxima[key])
    return [(np.array(k, np.int64).reshape(-1, 3), np.array(v, np.float32)) for k, v in zip(keys, values, strict=True)]


def _known(bricks: tuple[np.ndarray, np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    """A level's largest voxel per brick on the device, NaN where the brick is not."""
    out = np.full(shape, np.nan, np.float32)
    out[tuple(bricks[0].T)] = bricks[1]
    return out


def _drawn(device: list[tuple[np.ndarray, np.ndarray]], base: int, sd) -> np.ndarray:
    """Per skip cell of level ``base`` (`volren.upload.stream_skip_group` bricks per axis), the largest density the
    device draws there (undilated): the largest voxel of its bricks on the device (``device``, `_on_device`), and
    where a brick is not, the largest of the known bricks its voxels map into at levels base + 1, base + 2, ... up
    to the first level where all of them are known (`ancestor_voxel`'s search). Scattered from the bricks on the
    device: a 4096^3 level's 256^3 bricks are never a grid here."""
    layout = sd.layout
    bricks = layout.bricks(base)
    group, shape = stream_skip_group(bricks)
    coords, values = device[base]
    cells = tuple((coords // group).T)
    out = np.zeros(shape, np.float32)
    np.maximum.at(out, cells, values)
    count = np.zeros(shape, np.int64)
    np.add.at(count, cells, 1)
    sizes = [np.minimum(group, b - group * np.arange(n)) for b, n in zip(bricks, shape, strict=True)]
    pending = count < sizes[0][:, None, None] * sizes[1][None, :, None] * sizes[2][None, None, :]
    maps = sd.level_maps(base)
    for k in range(base + 1, layout.count):
        if not pending.any():
            break
        ranges = _covering(maps[k - base], layout.shapes[base], shape, sd.brick * group, layout.shapes[k],
                           layout.bricks(k), sd.brick)
        known = _known(device[k], layout.bricks(k))
        missing = np.isnan(known)
        found = _range_max(np.where(missing, np.float32(0.0), known), ranges)
        out = np.where(pending, np.maximum(out, found), out)
        pending &= _range_max(missing, ranges)
    return out


def drawn_bounds(state: StreamState, levels: int = 1) -> list[np.ndarray]:
    """For the first ``levels`` levels, finest first, the bound per skip cell of the densities drawn there now
    (module docstring; cells of `volren.upload.stream_skip_group` bricks)."""
    device = _on_device(state, state.density.layout.count)
    return [neighbourhood_max(_drawn(device, base, state.density)) for base in range(levels)]


def refresh_bounds(ds, state: StreamState) -> None:
    """Recompute ``state.bounds`` and write what derives from them to the device: each uploaded level's skip grid
    (`volren.upload.skip_cells`) and, for the cube-map methods, the culling level."""
    state.bounds = drawn_bounds(state, max(len(state.skips), 1))
    for level, offset in enumerate(state.skips):
        write_device(ds.max_density, offset, skip_cells(state.bounds[level]))
    if state.cull is not None:
        write_device(ds.max_density, state.cull, cull_level(state.bounds[0]))

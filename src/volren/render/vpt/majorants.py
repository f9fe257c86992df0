"""Majorants for null-collision tracking (paper 002 §4.3): macrocells with an octree of coarser levels over them.

Level 0 splits the voxel grid into macrocells of ``MACROCELL`` voxels per axis; each holds the range of scalar
values its trilinear samples can take (its voxels and a one-voxel border), built once per volume. When the transfer
function changes, each cell's majorant mu_max is the transfer function's largest extinction over that range
(a range-maximum table over the lookup table, so the rebuild is a gather). Level l + 1 is the max-pool of level l,
up to a single cell: the octree. Tracking (`track`) walks the ray cell by cell (3D-DDA): at each step it looks for
the coarsest empty node containing the current point and jumps over it, and otherwise samples free flights against
the local macrocell's majorant until it leaves the cell.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from volren.kernels.common import INF, VolumeGPU, box_hit, sample_density
from volren.sparse import SparseGrid

MACROCELL = 8
"""voxels per macrocell axis"""
MAX_LEVELS = 8
vec8i = wp.types.vector(length=MAX_LEVELS, dtype=wp.int32)


@wp.struct
class MajorantGrid:
    """One volume's majorant octree; level l has res_x[l] x res_y[l] x res_z[l] cells of cell_voxels * 2^l voxels."""

    levels: int
    offset: vec8i
    res_x: vec8i
    res_y: vec8i
    res_z: vec8i
    cell_voxels: wp.vec3
    """voxels per level-0 cell and axis"""
    voxels: wp.vec3
    """the density grid's voxels per axis"""


def scalar_ranges(density: np.ndarray, cell: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per level-0 cell (z, y, x) the min and max of its voxels and their one-voxel border (trilinear support).

    A cell's box with its border is a product of index ranges, so its min (max) is taken one axis at a time: each
    cell's block of voxels along the axis (`ufunc.reduceat`) with the voxel before and the one after it (clamped at the
    grid's ends). One pass over the grid and a few over the shrinking results: 256^3 in 0.19 s, where the 27 shifted
    full-grid passes of a 3x3x3 min / max filter took 1.48 s (one thread), the first frame's and every
    transfer-function switch's wait."""
    lo, hi = density, density
    for axis, c in enumerate(cell[::-1]):
        lo = _axis_range(lo, axis, c, np.minimum)
        hi = _axis_range(hi, axis, c, np.maximum)
    return lo, hi


def _axis_range(a: np.ndarray, axis: int, cell: int, op: np.ufunc) -> np.ndarray:
    """``op`` over each cell's block along ``axis`` and the voxel on either side of it (within the grid)."""
    n = a.shape[axis]
    starts = np.arange(0, n, cell)
    blocks = op.reduceat(a, starts, axis=axis)
    before = np.take(a, np.maximum(starts - 1, 0), axis=axis)
    after = np.take(a, np.minimum(starts + cell, n - 1), axis=axis)
    return op(blocks, op(before, after))


def range_max_table(values: np.ndarray) -> np.ndarray:
    """M[i, j] = max(values[i : j + 1]) for i <= j (the lookup table's largest extinction over an index range)."""
    n = len(values)
    out = np.zeros((n, n), dtype=np.float32)
    for i in range(n):
        out[i, i:] = np.maximum.accumulate(values[i:])
    return out


@dataclass
class Majorants:
    """Host side of one volume's majorant octree: the scalar ranges (transfer-function independent) and the
    levels built for the current transfer function."""

    lo: np.ndarray
    hi: np.ndarray
    cell: tuple[int, int, int]
    voxels: tuple[int, int, int]
    scale: float
    """largest scalar of the volume (u = value / scale)"""
    levels: list[np.ndarray]
    build_ms: float = 0.0

    @property
    def nbytes(self) -> int:
        return int(self.lo.nbytes + self.hi.nbytes + sum(level.nbytes for level in self.levels))


def table_scale(density: np.ndarray | SparseGrid) -> float:
    """The density that u = 1 of an extinction table stands for (u = density / scale)."""
    return float(density.max()) or 1.0


def build_majorants(density: Any, extinction: np.ndarray, ranges: np.ndarray | None = None,
                    global_majorant: bool = False, *, bounds: tuple[np.ndarray, int] | None = None,
                    scale: float | None = None) -> Majorants:
    """The majorant octree of a density grid [z, y, x] under the extinction table (indexed by u = value / ``scale``,
    `table_scale` if None). ``ranges``: the range-maximum table of ``extinction`` (computed if None).
    ``global_majorant``: one cell for the whole volume (the single global majorant, for comparison). A `SparseGrid`'s
    macrocells are its bricks (issue 41: "majorants per brick"), their ranges read from the page table
    (`SparseGrid.cell_ranges`), not a dense copy; so are a streamed volume's: ``bounds`` (per cell of that many
    voxels, `volren.render.stream_bounds`) bound what its bricks draw now (ranges [0, bound])."""
    start = time.perf_counter()
    voxels = tuple(density.shape[::-1])
    if bounds is not None or isinstance(density, SparseGrid):
        lo, hi, edge = ((np.zeros_like(bounds[0]), bounds[0], bounds[1]) if bounds is not None
                        else (*density.cell_ranges(), density.brick))
        cell = (edge,) * 3
        if global_majorant:
            lo, hi, cell = np.full((1, 1, 1), lo.min()), np.full((1, 1, 1), hi.max()), voxels
    else:
        cell = voxels if global_majorant else (MACROCELL,) * 3
        lo, hi = scalar_ranges(density, cell)
    scale = table_scale(density) if scale is None else scale
    m = range_max_table(extinction) if ranges is None else ranges
    n = len(extinction) - 1
    i = np.clip(np.floor(lo / scale * n), 0, n).astype(np.int64)
    j = np.clip(np.ceil(hi / scale * n), 0, n).astype(np.int64)
    level = m[i, j].astype(np.float32)
    levels = [level]
    while max(level.shape) > 1 and len(levels) < MAX_LEVELS:
        shape = tuple(math.ceil(s / 2) for s in level.shape)
        padded = np.pad(level, [(0, 2 * s - t) for s, t in zip(shape, level.shape, strict=True)])
        level = padded.reshape(shape[0], 2, shape[1], 2, shape[2], 2).max(axis=(1, 3, 5))
        levels.append(level)
    return Majorants(lo, hi, cell, voxels, scale, levels, (time.perf_counter() - start) * 1e3)


def majorant_struct(m: Majorants, offset: int) -> MajorantGrid:
    """The device description of ``m`` whose levels start at ``offset`` in the packed values array."""
    g = MajorantGrid()
    g.levels = len(m.levels)
    offsets, rx, ry, rz = [0] * MAX_LEVELS, [1] * MAX_LEVELS, [1] * MAX_LEVELS, [1] * MAX_LEVELS
    for k, level in enumerate(m.levels):
        offsets[k] = offset
        rz[k], ry[k], rx[k] = level.shape
        offset += level.size
    g.offset, g.res_x, g.res_y, g.res_z = vec8i(*offsets), vec8i(*rx), vec8i(*ry), vec8i(*rz)
    g.cell_voxels, g.voxels = wp.vec3(*m.cell), wp.vec3(*m.voxels)
    return g


@wp.func
def level_cell(grid: MajorantGrid, level: int, p: wp.vec3) -> wp.vec3i:
    """The level's cell holding local point p (clamped to the grid)."""
    size = grid.cell_voxels * float(1 << level)
    f = wp.cw_div(wp.cw_mul(p + wp.vec3(1.0), grid.voxels) * 0.5, size)
    return wp.vec3i(wp.clamp(int(wp.floor(f[0])), 0, grid.res_x[level] - 1),
                    wp.clamp(int(wp.floor(f[1])), 0, grid.res_y[level] - 1),
                    wp.clamp(int(wp.floor(f[2])), 0, grid.res_z[level] - 1))


@wp.func
def cell_exit(grid: MajorantGrid, level: int, c: wp.vec3i, o: wp.vec3, d: wp.vec3) -> float:
    """Ray parameter where o + t d leaves cell c of the level (local coordinates)."""
    size = wp.cw_div(grid.cell_voxels * float(1 << level) * 2.0, grid.voxels)
    lo = wp.vec3(-1.0) + wp.cw_mul(wp.vec3(float(c[0]), float(c[1]), float(c[2])), size)
    q = wp.cw_div(o - lo, size) * 2.0 - wp.vec3(1.0)
    h = box_hit(q, wp.cw_div(d, size) * 2.0)
    return h[1]


@wp.func
def tf_extinction(table: wp.array(dtype=wp.vec4), first: int, size: int, u: float) -> float:
    """Extinction of the lookup table ``table[first : first + size]`` at normalised scalar u (linear, clamped)."""
    x = wp.clamp(u, 0.0, 1.0) * float(size - 1)
    i = wp.min(int(x), size - 2)
    a = x - float(i)
    return (1.0 - a) * table[first + i][0] + a * table[first + i + 1][0]


@wp.func
def track(
    grid: MajorantGrid,
    majorants: wp.array(dtype=float),
    density: wp.array(dtype=float),
    vol: VolumeGPU,
    inv_scale: float,
    table: wp.array(dtype=wp.vec4),
    first: int,
    size: int,
    o: wp.vec3,
    d: wp.vec3,
    t0: float,
    t1: float,
    ratio: int,
    state: wp.uint32,
):
    """Null-collision tracking of local ray o + t d over [t0, t1] (t in world units; d the local image of a unit
    world direction). ratio = 0: delta tracking, returns (collision t or INF, state); ratio = 1: ratio tracking,
    returns (transmittance, state). Counts tentative collisions in the third value."""
    t = t0
    weight = float(1.0)
    lookups = int(0)
    while t < t1:
        p = o + (t + 1.0e-6) * d
        level = int(0)
        mu = float(0.0)
        c = wp.vec3i(0)
        for k in range(grid.levels):
            level = grid.levels - 1 - k
            c = level_cell(grid, level, p)
            mu = majorants[grid.offset[level] + (c[2] * grid.res_y[level] + c[1]) * grid.res_x[level] + c[0]]
            if mu == 0.0:
                break
        # (at least a little progress: a point on a cell face may round into the cell it just left)
        t_exit = wp.min(wp.max(cell_exit(grid, level, c, o, d), t + 1.0e-5), t1)
        if mu == 0.0:
            t = t_exit
            continue
        while True:
            t = t - wp.log(1.0 - wp.randf(state)) / mu
            if t >= t_exit:
                t = t_exit
                break
            lookups += 1
            ext = tf_extinction(table, first, size, sample_density(density, vol, o + t * d) * inv_scale)
            if ratio == 0:
                if wp.randf(state) * mu < ext:
                    return t, state, lookups
            else:
                weight = weight * (1.0 - ext / mu)
                if weight < 1.0e-6:
                    return 0.0, state, lookups
    if ratio == 0:
        return INF, state, lookups
    return weight, state, lookups

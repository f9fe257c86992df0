"""Bricked volumes (issue 41): a page table over a grid of bricks of B^3 trilinear cells, each brick stored in a pool
with a one-voxel apron, (B+1)^3 voxels, so that the 8 corners of every cell lie in one brick: a sample reads the
same 8 values as the dense path (`volren.kernels.common.gather_cell`) and interpolates them the same way, so it is
bit-identical to it, with one page-table load more.

Page table: one int32 per brick, x fastest. An entry ``e >= 0`` is a resident brick, the ``e``-th (B+1)^3 block of the
pool; ``e < 0`` is a brick whose (B+1)^3 voxels all hold one value, ``constants[-1 - e]`` (OpenVDB tiles), with
``constants[0] = 0``, so ``EMPTY`` (-1) costs no pool memory and no pool load. Brick b covers cells [b B, b B + B)
and voxels [b B, b B + B] per axis; at the high border of a grid whose cell count is not a multiple of B the apron
repeats the last voxel (never read: `grid_cell` keeps cells below res - 1).

B is a power of two, so that the brick of a cell is a shift and its place in the brick a mask (no integer division
per sample). Offsets are int32, as the dense path's: a pool holds fewer than 2^31 voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from volren.errors import VolrenError
from volren.kernels.common import (
    brick_cell,
    brick_entry,
    cell_fraction,
    grid_cell,
    grid_coords,
    interpolate_cell,
    vec8,
)

EMPTY = -1
"""page-table entry of a brick whose voxels are all 0 (``constants[0]``)"""
BRICK_SIZES = (8, 16, 32)
"""the brick edges [cells] the bench compares (issue 41: "e.g. 8^3 to 32^3")"""
MAX_POOL_VOXELS = 2**31 - 1


@wp.struct
class BrickVolumeGPU:
    pool: wp.array(dtype=float)
    """resident bricks, (B+1)^3 voxels each, [z, y, x] within a brick"""
    table: wp.array(dtype=wp.int32)
    """one entry per brick, [z, y, x] over the brick grid (module docstring)"""
    constants: wp.array(dtype=float)
    """values of the constant bricks; constants[0] = 0 (`EMPTY`)"""
    res: wp.vec3i
    """voxels per axis (x, y, z) of the grid the bricks tile"""
    bricks: wp.vec3i
    """bricks per axis (x, y, z)"""
    shift: int
    """log2 B"""
    edge: int
    """B + 1: voxels per brick edge, apron included"""


@wp.func
def brick_gather_cell(bv: BrickVolumeGPU, cell: wp.vec3i) -> vec8:
    """The 8 voxels around ``cell`` (its lowest corner), as `gather_cell` returns them from the dense grid."""
    entry = brick_entry(bv.table, 0, bv.bricks, bv.shift, cell)
    if entry < 0:
        c = bv.constants[-1 - entry]
        return vec8(c, c, c, c, c, c, c, c)
    return brick_cell(bv.pool, entry * bv.edge * bv.edge * bv.edge, bv.edge, bv.shift, cell)


@wp.func
def sample_bricks(bv: BrickVolumeGPU, p: wp.vec3) -> float:
    """Trilinear sample at local ``p`` in [-1, 1]^3, clamped at the border: `sample_grid` over bricks."""
    f = grid_coords(bv.res, p)
    cell = grid_cell(bv.res, f)
    return interpolate_cell(brick_gather_cell(bv, cell), cell_fraction(f, cell))


@dataclass(frozen=True)
class BrickVolume:
    """A bricked grid on the host (module docstring): upload with `upload`."""

    pool: np.ndarray
    """float32 (resident, B+1, B+1, B+1)"""
    table: np.ndarray
    """int32 (bricks z, bricks y, bricks x)"""
    constants: np.ndarray
    """float32; constants[0] = 0"""
    res: tuple[int, int, int]
    """voxels (z, y, x) of the grid, as its numpy shape"""
    brick: int
    """B: cells per brick edge"""

    @property
    def nbytes(self) -> int:
        return self.pool.nbytes + self.table.nbytes + self.constants.nbytes

    def upload(self, device: str) -> BrickVolumeGPU:
        bv = BrickVolumeGPU()
        bv.pool = wp.array(self.pool.reshape(-1), dtype=float, device=device)
        bv.table = wp.array(self.table.reshape(-1), dtype=wp.int32, device=device)
        bv.constants = wp.array(self.constants, dtype=float, device=device)
        bv.res = wp.vec3i(self.res[2], self.res[1], self.res[0])
        bv.bricks = wp.vec3i(self.table.shape[2], self.table.shape[1], self.table.shape[0])
        bv.shift = self.brick.bit_length() - 1
        bv.edge = self.brick + 1
        return bv


def apron_reduce(padded: np.ndarray, brick: int, op: np.ufunc) -> np.ndarray:
    """``op`` (np.minimum, np.maximum) over each brick's apron block of a grid of c B + 1 voxels per axis, one axis at
    a time (a box reduction is separable): along each axis the B-voxel blocks reduce through a reshape (a view), then
    meet the apron plane at the next multiple of B. Reducing the strided (B+1)^3 views directly was 14x slower
    (0.18 s against 0.013 s for a 257^3 grid at B = 8)."""
    out = padded
    for axis in (0, 1, 2):  # z first: its blocks are whole slabs; x, where a block is B floats, comes last, B^2 smaller
        count = (out.shape[axis] - 1) // brick
        lead = (slice(None),) * axis
        blocks = out[(*lead, slice(0, count * brick))].reshape(*out.shape[:axis], count, brick, *out.shape[axis + 1:])
        out = op(op.reduce(blocks, axis=axis + 1), out[(*lead, slice(brick, None, brick))])
    return out


def brick_volume(grid: np.ndarray, brick: int) -> BrickVolume:
    """Brick a dense [z, y, x] grid into bricks of ``brick``^3 cells (a power of two) with a one-voxel apron: a brick
    whose apron block holds one value becomes a constant (`EMPTY` for 0), the others go into the pool in brick order."""
    if grid.ndim != 3:
        raise VolrenError(f"bricks need a 3-D grid, got shape {grid.shape}")
    return brick_volume_sparse(grid.shape, [((0, 0, 0), grid)], brick)


def brick_volume_sparse(shape: tuple[int, ...], regions: list[tuple[tuple[int, int, int], np.ndarray]],
                        brick: int) -> BrickVolume:
    """Brick a grid of ``shape`` voxels (z, y, x) that is 0 outside ``regions`` (each its first voxel (z, y, x) and
    a dense block) without a dense copy of the grid: each region is widened to the apron blocks it touches and
    bricked alone (a sparse file's active boxes, an OpenVDB file's leaves in groups). Regions must not share a brick.
    Beyond the grid's high border the apron repeats the last voxel (never read; it keeps a constant brick constant)."""
    if brick < 2 or brick & (brick - 1):
        raise VolrenError(f"brick size must be a power of two >= 2, got {brick}")
    if len(shape) != 3 or min(shape) < 2:
        raise VolrenError(f"bricks need a 3-D grid of at least 2 voxels per axis, got shape {tuple(shape)}")
    counts = tuple(-(-(n - 1) // brick) for n in shape)  # bricks per axis: cells (n - 1) / B, rounded up
    table = np.full(counts, EMPTY, dtype=np.int32)
    claimed = np.zeros(counts, dtype=bool)
    e = brick + 1
    values, pools, kinds = [], [], []  # per region: constant bricks' values, resident blocks, and where they go
    for origin, block in regions:
        block = np.asarray(block, dtype=np.float32)
        # bricks b whose apron voxels [b B, b B + B] meet the region's [o, o + size - 1], per axis
        first = [max(-(-o // brick) - 1, 0) for o in origin]
        last = [min((o + m - 1) // brick, c - 1) for o, m, c in zip(origin, block.shape, counts, strict=True)]
        if any(f > lst for f, lst in zip(first, last, strict=True)):
            continue
        where = tuple(slice(f, lst + 1) for f, lst in zip(first, last, strict=True))
        if claimed[where].any():
            raise VolrenError("regions share a brick: merge them")
        claimed[where] = True
        # the widened region on the voxel grid, [first B, (last + 1) B], edge-padded past the grid
        lo_v = [f * brick for f in first]
        size = [(lst + 1 - f) * brick + 1 for f, lst in zip(first, last, strict=True)]
        inside = [min(s, n - v) for s, n, v in zip(size, shape, lo_v, strict=True)]
        local = np.zeros(inside, dtype=np.float32)
        src = tuple(slice(max(v - o, 0), min(v + s - o, m))
                    for v, s, o, m in zip(lo_v, inside, origin, block.shape, strict=True))
        dst = tuple(slice(max(o - v, 0), max(o - v, 0) + (sl.stop - sl.start))
                    for v, o, sl in zip(lo_v, origin, src, strict=True))
        local[dst] = block[src]
        pad = [(0, s - i) for s, i in zip(size, inside, strict=True)]
        padded = np.pad(local, pad, mode="edge") if any(p for _, p in pad) else local
        lo, hi = apron_reduce(padded, brick, np.minimum), apron_reduce(padded, brick, np.maximum)
        constant = lo == hi
        st = padded.strides
        # every brick's (B+1)^3 apron block as a view: neighbouring blocks share their faces
        blocks = np.lib.stride_tricks.as_strided(padded, shape=(*lo.shape, e, e, e), writeable=False,
                                                 strides=(st[0] * brick, st[1] * brick, st[2] * brick, *st))
        values.append(lo[constant])
        pools.append(blocks[np.nonzero(~constant)])
        kinds.append((where, constant))
    others = np.unique(np.concatenate([np.zeros(0, np.float32), *values]))
    others = others[others != 0.0]
    constants = np.concatenate([np.zeros(1, np.float32), others]).astype(np.float32)
    resident = sum(len(p) for p in pools)
    if resident * e**3 > MAX_POOL_VOXELS:
        raise VolrenError(f"{resident} resident bricks of {e}^3 voxels exceed the int32 pool offsets")
    start = 0
    for (where, constant), value, pool in zip(kinds, values, pools, strict=True):
        entries = np.empty(constant.shape, dtype=np.int32)
        entries[constant] = -1 - np.where(value != 0.0, np.searchsorted(others, value) + 1, 0)
        entries[~constant] = np.arange(start, start + len(pool), dtype=np.int32)
        table[where] = entries
        start += len(pool)
    pool = np.concatenate(pools) if pools else np.zeros((0, e, e, e), np.float32)
    return BrickVolume(pool=pool, table=table, constants=constants, res=tuple(shape), brick=brick)

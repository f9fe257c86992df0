"""Bricked volumes on a Warp device (issue 41): the page table, pool and constants of a `volren.sparse.SparseGrid`
(its docstring has the layout) as a struct, and its trilinear sample, bit-identical to the dense grid's.
"""

from __future__ import annotations

import warp as wp

from volren.kernels.common import (
    brick_cell,
    brick_entry,
    cell_fraction,
    grid_cell,
    grid_coords,
    interpolate_cell,
    vec8,
)
from volren.sparse import SparseGrid

BRICK_SIZES = (8, 16, 32)
"""the brick edges [cells] the bench compares (issue 41: "e.g. 8^3 to 32^3")"""


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


def upload_bricks(grid: SparseGrid, device: str) -> BrickVolumeGPU:
    """``grid``'s bricks on ``device``."""
    bv = BrickVolumeGPU()
    bv.pool = wp.array(grid.pool.reshape(-1), dtype=float, device=device)
    bv.table = wp.array(grid.table.reshape(-1), dtype=wp.int32, device=device)
    bv.constants = wp.array(grid.constants, dtype=float, device=device)
    bv.res = wp.vec3i(grid.shape[2], grid.shape[1], grid.shape[0])
    bv.bricks = wp.vec3i(grid.table.shape[2], grid.table.shape[1], grid.table.shape[0])
    bv.shift = grid.brick.bit_length() - 1
    bv.edge = grid.brick + 1
    return bv

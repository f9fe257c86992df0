"""`volren.sparse`: a grid built voxel by voxel from a sparse source (OpenVDB leaves and tiles, a finer mip level)
holds exactly the bricks of the same grid bricked from a dense copy (issue 41 item 2), without that copy."""

from __future__ import annotations

import numpy as np
import pytest

from volren.errors import VolrenError
from volren.scene import _downsample
from volren.sparse import EMPTY, BrickBuilder, brick_dense

pytestmark = pytest.mark.timeout(60)

SHAPE = (37, 20, 49)
"""[z, y, x]: no axis a multiple of B + 1, one (37 = 2 B + 5) with a short last brick, one (49 = 3 B + 1) whose
last voxel lives only in an apron"""


def sparse_field(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    grid = np.where(rng.random(SHAPE) < 0.03, rng.uniform(0.1, 1.0, SHAPE), 0.0).astype(np.float32)
    grid[4:30, 2:18, 16:33] = 0.5  # a constant box: its inner bricks are constants
    grid[:, :, -1] = np.where(rng.random(SHAPE[:2]) < 0.5, 0.7, 0.0)  # the last x plane: apron-only voxels
    return grid


def built(grid: np.ndarray, brick: int = 16) -> BrickBuilder:
    """The grid's constant box as a `fill` (a tile) and every other non-zero voxel as a `scatter` (leaf voxels)."""
    box = np.zeros(grid.shape, bool)
    box[4:30, 2:18, 16:33] = True
    voxels = np.argwhere((grid != 0) & ~box)
    b = BrickBuilder(grid.shape, brick)
    b.touch(voxels, voxels)
    b.touch(np.array([4, 2, 16]), np.array([29, 17, 32]))
    b.scatter(voxels, grid[tuple(voxels.T)])
    b.fill(np.array([4, 2, 16]), np.array([29, 17, 32]), 0.5)
    return b


@pytest.mark.parametrize("brick", [4, 16])
def test_scattered_voxels_and_filled_boxes_equal_the_dense_bricks(brick):
    grid = sparse_field()
    sparse, dense = built(grid, brick).build(), brick_dense(grid, brick)
    assert np.array_equal(sparse.to_dense(), grid)
    # every brick's apron block the same: a resident brick's values, or the same constant
    for lo_s, lo_d in zip(sparse.brick_ranges, dense.brick_ranges, strict=True):
        assert np.array_equal(lo_s, lo_d)
    assert np.array_equal(sparse.table < 0, dense.table < 0)
    assert len(sparse.pool) == len(dense.pool) and sparse.max() == float(grid.max()) and sparse.min() == 0.0
    resident = dense.table >= 0
    assert np.array_equal(sparse.pool[sparse.table[resident]], dense.pool[dense.table[resident]])
    if brick == 4:  # bricks wholly inside the box, apron included, are constants of its value, in no pool block
        assert sparse.constants[-1 - sparse.table[2, 1, 5]] == 0.5 and sparse.table[2, 1, 5] < EMPTY


def test_background_fills_the_untouched_bricks():
    grid = np.full((20, 18, 17), 0.25, np.float32)
    grid[3, 4, 5] = 1.0
    b = BrickBuilder(grid.shape, 8, background=0.25)
    v = np.array([[3, 4, 5]])
    b.touch(v, v)
    b.scatter(v, [1.0])
    sg = b.build()
    assert np.array_equal(sg.to_dense(), grid) and len(sg.pool) == 1 and sg.min() == 0.25


def test_writes_outside_the_touched_bricks_are_refused():
    b = BrickBuilder((20, 20, 20), 8)
    b.touch(np.array([[0, 0, 0]]), np.array([[1, 1, 1]]))
    with pytest.raises(VolrenError, match="outside the touched bricks"):
        b.scatter(np.array([[17, 17, 17]]), [1.0])


@pytest.mark.parametrize("shape", [SHAPE, (33, 34, 35)])
def test_downsample_is_the_mip_pyramids_next_level(shape):
    rng = np.random.default_rng(5)
    grid = np.zeros(shape, np.float32)
    grid[: shape[0] // 2, 3:, 5:-3] = rng.uniform(0.1, 1.0, grid[: shape[0] // 2, 3:, 5:-3].shape)
    grid[-1, -1, -1] = 2.0  # the last voxel: in an odd axis's padding pair
    coarse = brick_dense(grid, 8).downsample()
    want = _downsample(grid, "mean")
    assert coarse.shape == want.shape
    np.testing.assert_allclose(coarse.to_dense(), want, rtol=1e-6, atol=1e-7)
    assert np.array_equal(coarse.table == EMPTY, brick_dense(want, 8).table == EMPTY)


def test_read_clamps_to_the_grid_as_sampling_does():
    grid = sparse_field()
    sg = brick_dense(grid, 16)
    got = sg.read((-2, 5, 40), (3, 7, 52))
    idx = [np.clip(np.arange(a, b), 0, n - 1) for a, b, n in zip((-2, 5, 40), (3, 7, 52), grid.shape, strict=True)]
    assert np.array_equal(got, grid[np.ix_(*idx)])
    with pytest.raises(VolrenError, match="cannot read"):
        sg.read((0, 0, 0), (1 << 10, 1 << 10, 1 << 10))


def test_cell_ranges_bound_every_sample_of_a_cell_and_its_border():
    """Per cell of B^3 voxels the bricks' ranges hold the cell's voxels and the one-voxel border around it (what a
    trilinear sample there reads): the skip grid's and the majorants' rule, read from the page table."""
    from volren.upload import _block_max

    grid = sparse_field()
    lo, hi = brick_dense(grid, 8).cell_ranges()
    assert hi.shape == tuple(-(-n // 8) for n in grid.shape)
    want = _block_max(grid, 8)  # the max over each cell widened by one voxel
    assert np.all(hi >= want) and np.all((hi == 0) <= (want == 0))
    negated = -_block_max(-grid, 8)  # the min likewise
    assert np.all(lo <= negated)
    # one voxel just below a cell's first one: the cell's range sees it (it is in the brick before)
    one = np.zeros((33, 33, 33), np.float32)
    one[15, 20, 20] = 1.0
    assert brick_dense(one, 16).cell_ranges()[1][1, 1, 1] == 1.0


def test_sum_is_the_dense_copys():
    grid = sparse_field()
    assert brick_dense(grid, 8).sum() == pytest.approx(float(grid.sum(dtype=np.float64)), rel=1e-12)


@pytest.mark.parametrize("cell", [4, 8])
def test_cell_max_bounds_every_sample_of_a_finer_cell(cell):
    """`cell_max` at cells finer than the bricks: at least the dense skip rule's max (the cell and one voxel each
    side), empty exactly where the cell, the cell before and one voxel after are (a voxel in the cell before)."""
    from volren.upload import _block_max

    grid = sparse_field()
    bricks = brick_dense(grid, 16)
    got = bricks.cell_max(cell)
    want = _block_max(grid, cell)
    assert got.shape == want.shape and np.all(got >= want)
    before = want.copy()
    for axis in range(3):  # what the rule covers: the cell before too
        shifted = np.concatenate([np.take(before, [0], axis), np.take(before, range(before.shape[axis] - 1), axis)],
                                 axis)
        before = np.maximum(before, shifted)
    inner = tuple(slice(0, c * 16 // cell) for c in bricks.table.shape)  # past them: the last cell repeated
    assert np.all(got[inner] <= before[inner])

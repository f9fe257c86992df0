"""Bricked volumes (issue 41, `volren.kernels.bricks`) and the ``bricks`` bench suite: the page table reads exactly
what the dense grid holds, at every cell and at clamped positions, its constant bricks cost no pool memory, and the
suite compares the representations on the same samples."""

from __future__ import annotations

import json

import numpy as np
import pytest
import warp as wp

from volren.bench.bricks import SPEED_TOLERANCE, two_balls_field, two_balls_regions
from volren.device import init_warp
from volren.errors import VolrenError
from volren.kernels.bricks import BrickVolumeGPU, brick_gather_cell, sample_bricks, upload_bricks
from volren.kernels.common import gather_cell, sample_grid, vec8
from volren.sparse import EMPTY, brick_dense, brick_regions

init_warp()


@wp.kernel
def gather_every_cell(data: wp.array(dtype=float), res: wp.vec3i, bv: BrickVolumeGPU,
                      dense: wp.array(dtype=vec8), bricked: wp.array(dtype=vec8)):
    x, y, z = wp.tid()
    cell = wp.vec3i(x, y, z)
    i = (z * (res[1] - 1) + y) * (res[0] - 1) + x
    dense[i] = gather_cell(data, 0, res, cell)
    bricked[i] = brick_gather_cell(bv, cell)


@wp.kernel
def sample_both(data: wp.array(dtype=float), res: wp.vec3i, bv: BrickVolumeGPU, points: wp.array(dtype=wp.vec3),
                dense: wp.array(dtype=float), bricked: wp.array(dtype=float)):
    i = wp.tid()
    dense[i] = sample_grid(data, 0, res, points[i])
    bricked[i] = sample_bricks(bv, points[i])


def field_with_every_kind_of_brick() -> np.ndarray:
    """(21, 19, 35) voxels: no axis a whole number of 8-cell bricks; random values, an empty corner region, a constant
    region of 0.75 and a region of -0.0 (a zero that is not +0)."""
    rng = np.random.default_rng(3)
    grid = rng.random((21, 19, 35), dtype=np.float32)
    grid[rng.random(grid.shape) < 0.2] = 0.0  # scattered zeros inside resident bricks
    grid[:10, :10, :10] = 0.0  # the apron block of brick (0, 0, 0): voxels 0..8
    grid[:8, 10:16, :8] = 0.0  # brick (0, 1, 0) is 0 but for its apron planes (x = 8, y = 16, z = 8): resident
    grid[:, :, 24:] = 0.75  # bricks x = 3 and 4 (voxels 24..34) in every row
    return grid


def upload_dense(grid: np.ndarray) -> tuple[wp.array, wp.vec3i]:
    return wp.array(grid.reshape(-1), dtype=float, device="cpu"), wp.vec3i(grid.shape[2], grid.shape[1], grid.shape[0])


@pytest.mark.timeout(60)
@pytest.mark.parametrize("brick", [8, 16, 32])
def test_page_table_gather_equals_the_dense_gather_bit_for_bit_at_every_cell(brick):
    grid = field_with_every_kind_of_brick()
    data, res = upload_dense(grid)
    bv = upload_bricks(brick_dense(grid, brick), "cpu")
    cells = (grid.shape[2] - 1, grid.shape[1] - 1, grid.shape[0] - 1)
    n = int(np.prod(cells))
    dense, bricked = wp.zeros(n, dtype=vec8, device="cpu"), wp.zeros(n, dtype=vec8, device="cpu")
    wp.launch(gather_every_cell, dim=cells, inputs=[data, res, bv, dense, bricked], device="cpu")
    # every cell, so the cells whose +1 corners lie in the apron (x, y or z = k B - 1) and the grid's last cells
    # (corners at res - 1, in a partial brick) are all among them
    assert np.array_equal(bricked.numpy().view(np.uint32), dense.numpy().view(np.uint32))
    assert dense.numpy()[:, 0].reshape(cells[::-1])[10, 10, 10] == grid[10, 10, 10]  # the layout was not a no-op


@pytest.mark.timeout(60)
def test_page_table_samples_equal_dense_bit_for_bit_inside_and_clamped_outside():
    grid = field_with_every_kind_of_brick()
    data, res = upload_dense(grid)
    bv = upload_bricks(brick_dense(grid, 8), "cpu")
    rng = np.random.default_rng(4)
    p = rng.uniform(-1.2, 1.2, (20000, 3)).astype(np.float32)  # a sixth of each axis beyond the box: clamped
    p[:8] = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.2, 1.2, 1.2], [-1.2, 0.0, 1.2], [1.0, -1.0, 0.3],
             [2.0 * 8.5 / 35 - 1.0, 0.0, 0.0], [0.0, 2.0 * 8.5 / 19 - 1.0, 0.0], [0.0, 0.0, 2.0 * 16.5 / 21 - 1.0]]
    points = wp.array(p, dtype=wp.vec3, device="cpu")
    dense, bricked = wp.zeros(len(p), dtype=float, device="cpu"), wp.zeros(len(p), dtype=float, device="cpu")
    wp.launch(sample_both, dim=len(p), inputs=[data, res, bv, points, dense, bricked], device="cpu")
    assert np.array_equal(bricked.numpy().view(np.uint32), dense.numpy().view(np.uint32))
    assert dense.numpy()[1] == grid[-1, -1, -1] and dense.numpy()[2] == grid[-1, -1, -1]  # clamped to the corner
    assert dense.numpy()[0] == grid[0, 0, 0] == 0.0


@pytest.mark.timeout(60)
def test_empty_and_constant_bricks_hold_no_pool_memory_and_read_their_value():
    grid = field_with_every_kind_of_brick()
    bricks = brick_dense(grid, 8)
    assert bricks.table.shape == (3, 3, 5)  # ceil(20 / 8), ceil(18 / 8), ceil(34 / 8) bricks of cells
    assert bricks.table[0, 0, 0] == EMPTY and bricks.constants[0] == 0.0
    constant = bricks.table[:, :, 3:]  # voxels 24..32 and 32..34 (apron repeated): all 0.75
    assert (constant < 0).all() and len(np.unique(constant)) == 1
    assert bricks.constants[-1 - constant[0, 0, 0]] == np.float32(0.75)
    resident = int((bricks.table >= 0).sum())
    assert resident == 3 * 3 * 5 - 1 - 3 * 3 * 2
    assert sorted(bricks.table[bricks.table >= 0]) == list(range(resident))
    assert bricks.pool.shape == (resident, 9, 9, 9)
    assert bricks.nbytes == resident * 9**3 * 4 + bricks.table.size * 4 + bricks.constants.size * 4
    # the first resident brick (0, 0, 1) holds its apron block: cells 8..15 and the voxels 8..16
    first = bricks.table[0, 0, 1]
    assert np.array_equal(bricks.pool[first], grid[0:9, 0:9, 8:17])
    # read through the device function: the empty brick's cells give 0, the constant ones 0.75
    data, res = upload_dense(grid)
    bv = upload_bricks(bricks, "cpu")
    cells = (34, 18, 20)
    out, ref = wp.zeros(34 * 18 * 20, dtype=vec8, device="cpu"), wp.zeros(34 * 18 * 20, dtype=vec8, device="cpu")
    wp.launch(gather_every_cell, dim=cells, inputs=[data, res, bv, ref, out], device="cpu")
    got = out.numpy().reshape(20, 18, 34, 8)
    assert (got[:8, :8, :8] == 0.0).all() and (got[:, :, 24:] == np.float32(0.75)).all()


@pytest.mark.timeout(60)
def test_bricks_built_from_regions_equal_those_of_the_dense_grid_without_a_dense_copy():
    """A grid that is 0 outside three blocks (one at the high corner, one over a brick border, one constant starting
    on a brick border, so that only the apron of the brick before it meets it) bricked
    from the blocks alone: the same table kinds, pool bytes and gathered cells as bricking the dense grid."""
    rng = np.random.default_rng(5)
    shape = (37, 30, 41)
    regions = [((25, 20, 33), rng.random((12, 10, 8), dtype=np.float32)),
               ((3, 12, 18), rng.random((6, 7, 5), dtype=np.float32)),
               ((16, 0, 0), np.full((6, 8, 8), 0.5, np.float32))]  # z = 16: the apron plane of brick z = 1
    grid = np.zeros(shape, np.float32)
    for (z, y, x), block in regions:
        grid[z:z + block.shape[0], y:y + block.shape[1], x:x + block.shape[2]] = block
    dense, sparse = brick_dense(grid, 8), brick_regions(shape, regions, 8)
    assert np.array_equal(dense.table < 0, sparse.table < 0) and dense.nbytes == sparse.nbytes
    assert np.array_equal(dense.constants[sparse.table[sparse.table < 0] * -1 - 1],
                          dense.constants[dense.table[dense.table < 0] * -1 - 1])
    data, res = upload_dense(grid)
    cells = (40, 29, 36)
    n = 40 * 29 * 36
    got = [wp.zeros(n, dtype=vec8, device="cpu") for _ in range(3)]
    for bricks, out in ((sparse, got[1]), (dense, got[2])):
        wp.launch(gather_every_cell, dim=cells, inputs=[data, res, upload_bricks(bricks, "cpu"), got[0], out],
                  device="cpu")
    assert np.array_equal(got[1].numpy(), got[0].numpy()) and np.array_equal(got[2].numpy(), got[0].numpy())
    with pytest.raises(VolrenError, match="share a brick"):
        brick_regions(shape, [((0, 0, 0), np.ones((2, 2, 2), np.float32)),
                                    ((4, 4, 4), np.ones((2, 2, 2), np.float32))], 8)


def test_brick_sizes_must_be_powers_of_two():
    with pytest.raises(VolrenError, match="power of two"):
        brick_dense(np.zeros((9, 9, 9), np.float32), 12)


def balls_200() -> np.ndarray:
    grid = np.zeros((200, 200, 200), np.float32)
    for (z, y, x), block in two_balls_regions(200, 10):
        grid[z:z + block.shape[0], y:y + block.shape[1], x:x + block.shape[2]] = block
    return grid


@pytest.mark.timeout(120)
def test_bricks_suite_compares_the_representations_on_the_same_samples(tmp_path):
    from volren.bench.runner import run_suite

    overrides = {"fields": ["cloud", "two-balls"], "resolution": 24, "sparse_resolution": 64, "rays": 12,
                 "random_points": 1 << 12, "repeats": 1, "check_threads": 1 << 10, "issue_file": [200, 10]}
    json_path, md_path, table = run_suite("bricks", quick=True, device="cpu", out=tmp_path, overrides=overrides)
    doc = json.loads(json_path.read_text())
    rows = doc["rows"]
    assert [(r["method"], r["brick"]) for r in rows[:5]] == [
        ("dense", None), ("bricks", 8), ("bricks", 16), ("bricks", 32), ("wp.Volume", 8)]
    assert len(rows) == 2 * 2 * 5 and {(r["field"], r["pattern"]) for r in rows} == {
        (f, p) for f in ("cloud", "two-balls") for p in ("rays", "random")}
    for f in ("cloud", "two-balls"):
        for p in ("rays", "random"):
            case = [r for r in rows if (r["field"], r["pattern"]) == (f, p)]
            assert len({r["samples"] for r in case}) == 1 and case[0]["samples"] > 1000
            assert case[0]["ratio"] == 1.0
    bricked = [r for r in rows if r["method"] == "bricks"]
    assert all(r["max_abs_diff"] == 0.0 for r in bricked)
    nano = [r for r in rows if r["method"] == "wp.Volume"]
    assert all(0.0 <= r["max_abs_diff"] < 1e-6 for r in nano)  # our convention up to its arithmetic
    assert max(r["max_abs_diff"] for r in nano) > 0.0  # ... which differs (it sums weighted corners)
    balls = {(r["method"], r["brick"]): r for r in rows if r["field"] == "two-balls" and r["pattern"] == "rays"}

    grid = two_balls_field(64)
    active = int(np.count_nonzero(grid))
    assert balls["dense", None]["bytes_per_active"] == pytest.approx(64**3 * 4 / active)
    assert balls["bricks", 8]["bytes_per_active"] == brick_dense(grid, 8).nbytes / active
    assert balls["bricks", 8]["bytes_per_active"] < balls["dense", None]["bytes_per_active"] / 5
    info = {f["field"]: f for f in doc["settings"]["fields_info"]}
    # NanoVDB at unclamped index coordinates fades to its background over the outer half voxel: the cloud is dense
    # up to the border, the balls are not near it
    assert info["cloud"]["nanovdb_unclamped_max_abs_diff"] > 0.05
    assert info["two-balls"]["nanovdb_unclamped_max_abs_diff"] < 1e-6
    assert doc["summary"][-1]["unclamped_max_abs_diff"] == info["cloud"]["nanovdb_unclamped_max_abs_diff"]
    summary = doc["summary"]
    assert [s["choice"] for s in summary].count("chosen") == 1
    chosen = next(s for s in summary if s["choice"] == "chosen")
    assert chosen["method"] != "dense" and chosen["max_abs_diff"] <= 1e-6
    fast = [s for s in summary if s["method"] != "dense" and s["max_abs_diff"] <= 1e-6
            and s["ratio_all"] >= SPEED_TOLERANCE * max(t["ratio_all"] for t in summary if t["method"] != "dense")]
    assert chosen["bpav_mean"] == min(s["bpav_mean"] for s in fast)
    # the issue's file, built from the balls alone: the page table's bytes are the resident bricks' and the table's
    regions = two_balls_regions(200, 10)
    active = sum(int(np.count_nonzero(b)) for _, b in regions)
    b8 = next(s for s in summary if (s["method"], s["brick"]) == ("bricks", 8))
    assert b8["bpav_issue_file"] == pytest.approx(brick_dense(balls_200(), 8).nbytes / active)
    dense = next(s for s in summary if s["method"] == "dense")
    assert dense["bpav_issue_file"] == pytest.approx(4 * 200**3 / active)
    assert "| bricks | 16 |" in table and table in md_path.read_text()

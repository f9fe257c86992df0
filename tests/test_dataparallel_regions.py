"""`volren.dataparallel.regions` (issue 43 item 1): a k-d split of the brick grid into N convex regions that tile it
exactly, balanced by weight in proportion to the regions each side gets, with regions that hold no active brick kept;
their voxel boxes and local clip boxes, which tile [-1, 1]^3 with no gap and no overlap under the half-open rule."""

from __future__ import annotations

import numpy as np
import pytest

from volren.dataparallel import (
    Region,
    Split,
    box_in_voxels,
    bricks_per_axis,
    local_box,
    plane_local,
    split_regions,
)
from volren.errors import VolrenError

pytestmark = pytest.mark.timeout(60)

SHAPE = (37, 20, 49)
"""[voxels] (z, y, x): 3, 2 and 3 bricks of 16, the last of each short (37 = 2 B + 5, 49 = 3 B + 1)"""


def leaves(node: Split | int) -> list[int]:
    return [node] if isinstance(node, int) else leaves(node.low) + leaves(node.high)


def splits(node: Split | int) -> list[Split]:
    return [] if isinstance(node, int) else [node, *splits(node.low), *splits(node.high)]


def coverage(tree) -> np.ndarray:
    count = np.zeros(tree.grid, dtype=np.int64)
    for r in tree.regions:
        count[r.lo[0]:r.hi[0], r.lo[1]:r.hi[1], r.lo[2]:r.hi[2]] += 1
    return count


def test_five_regions_put_two_fifths_of_the_weight_below_the_first_plane():
    tree = split_regions(np.ones((1, 1, 10)), 5)
    assert tree.root == Split(2, 4, Split(2, 2, 0, 1), Split(2, 6, 2, Split(2, 8, 3, 4)))
    assert [(r.lo, r.hi, r.weight) for r in tree.regions] == [
        ((0, 0, 2 * i), (1, 1, 2 * i + 2), 2.0) for i in range(5)]
    # weight, not bricks, decides: the one heavy brick at the end balances the nine light ones
    heavy = split_regions(np.array([[[1, 1, 1, 1, 1, 1, 1, 1, 1, 9]]], dtype=float), 2)
    assert heavy.root == Split(2, 9, 0, 1) and [r.weight for r in heavy.regions] == [9.0, 9.0]


@pytest.mark.parametrize("seed", range(6))
def test_regions_tile_the_grid_and_carry_their_bricks_weight(seed):
    rng = np.random.default_rng(seed)
    grid = tuple(int(g) for g in rng.integers(1, 7, size=3))
    weights = rng.random(grid) * (rng.random(grid) < 0.5)
    n = int(rng.integers(1, weights.size + 1))
    tree = split_regions(weights, n)
    assert len(tree.regions) == n and [r.index for r in tree.regions] == list(range(n))
    assert leaves(tree.root) == list(range(n))
    assert np.array_equal(coverage(tree), np.ones(grid, dtype=np.int64))  # disjoint and complete
    for r in tree.regions:
        assert r.bricks >= 1
        assert r.weight == pytest.approx(weights[r.lo[0]:r.hi[0], r.lo[1]:r.hi[1], r.lo[2]:r.hi[2]].sum(), abs=1e-12)


@pytest.mark.parametrize("n", [2, 3, 5, 7])
def test_each_split_is_on_a_longest_axis_and_balanced_within_half_a_slab(n):
    """Between two neighbouring planes the low side's weight changes by one slab's, so the best plane is within half
    the heaviest slab of the target W n_low / n, wherever every plane leaves both sides room for their regions (each
    slab holds at least n bricks: true of every node here)."""
    rng = np.random.default_rng(n)
    weights = rng.random((9, 12, 10)) ** 3
    tree = split_regions(weights, n)
    for node in splits(tree.root):
        below, above = leaves(node.low), leaves(node.high)
        box = [tree.regions[i] for i in below + above]
        lo = np.min([r.lo for r in box], axis=0)
        hi = np.max([r.hi for r in box], axis=0)
        extent = hi - lo
        assert extent[node.axis] == extent.max()
        assert len(below) == (len(below) + len(above)) // 2
        sub = weights[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        slabs = sub.sum(axis=tuple(a for a in range(3) if a != node.axis))
        target = sub.sum() * len(below) / (len(below) + len(above))
        w_low = sum(tree.regions[i].weight for i in below)
        assert abs(w_low - target) <= slabs.max() / 2 + 1e-9


def test_equally_long_axes_go_to_the_better_balance():
    weights = np.zeros((1, 4, 4))
    weights[0, :, 0] = 1.0  # all weight in one column of x: only a y plane halves it
    assert split_regions(weights, 2).root == Split(1, 2, 0, 1)
    assert split_regions(np.ones((2, 2, 8)), 2).root == Split(2, 4, 0, 1)  # the longest axis, x


def test_regions_with_no_active_brick_are_returned_and_compact():
    weights = np.zeros((4, 4, 4))
    weights[0, 0, 0] = 1.0
    tree = split_regions(weights, 8)
    octants = [((z, y, x), (z + 2, y + 2, x + 2)) for z in (0, 2) for y in (0, 2) for x in (0, 2)]
    assert [(r.lo, r.hi) for r in tree.regions] == octants
    assert [r.weight for r in tree.regions] == [1.0] + [0.0] * 7


def test_one_brick_per_region_where_the_counts_cannot_halve():
    tree = split_regions(np.ones((1, 3, 3)), 9)  # 3 x 3 cut 4 | 5 fits no plane: the counts follow the bricks
    assert sorted(r.lo for r in tree.regions) == [(0, y, x) for y in range(3) for x in range(3)]
    assert all(r.bricks == 1 for r in tree.regions)


def test_more_regions_than_bricks_is_refused():
    with pytest.raises(VolrenError, match=r"cannot split a grid of 8 bricks into 9 regions"):
        split_regions(np.ones((2, 2, 2)), 9)
    with pytest.raises(VolrenError, match=r"into 0 regions"):
        split_regions(np.ones((2, 2, 2)), 0)
    with pytest.raises(VolrenError, match=r">= 0"):
        split_regions(-np.ones((2, 2, 2)), 2)
    with pytest.raises(VolrenError, match=r"do not match"):
        split_regions(np.ones((2, 2, 2)), 2, shape=SHAPE)


def test_voxel_and_local_boxes_of_a_region_by_hand():
    assert bricks_per_axis(SHAPE) == (3, 2, 3) and bricks_per_axis((1, 17, 18)) == (1, 1, 2)
    region = Region(0, (1, 0, 2), (3, 1, 3), 0.0)
    assert box_in_voxels(region, 16, SHAPE) == ((16, 0, 32), (37, 17, 49))
    lo, hi = local_box(region, 16, SHAPE)
    # x: voxel 32's centre to the far face; y: the near face to voxel 16's centre; z: voxel 16's centre to the face
    assert lo.tolist() == [-1 + 32.5 * 2 / 49, -1.0, -1 + 16.5 * 2 / 37]
    assert hi.tolist() == [1.0, -1 + 16.5 * 2 / 20, 1.0]


@pytest.mark.parametrize("n", [3, 5, 18])
def test_local_boxes_tile_the_cube_under_the_half_open_rule(n):
    """Every point of [-1, 1]^3 lies in exactly one region's [lo, hi) (hi included at +1), also points on the shared
    planes and on the faces: the regions' clip boxes meet at the same floats."""
    tree = split_regions(np.ones(bricks_per_axis(SHAPE)), n, shape=SHAPE)
    boxes = [local_box(r, 16, SHAPE) for r in tree.regions]
    assert sum(np.prod(hi - lo) for lo, hi in boxes) == pytest.approx(8.0, abs=1e-12)
    rng = np.random.default_rng(n)
    planes = np.unique(np.concatenate([np.concatenate(b) for b in boxes]))
    points = np.concatenate([rng.uniform(-1, 1, (400, 3)), rng.choice(planes, (400, 3))])
    owners = np.zeros(len(points), dtype=np.int64)
    for lo, hi in boxes:
        owners += np.all((points >= lo) & ((points < hi) | ((points == hi) & (hi == 1.0))), axis=1)
    assert owners.tolist() == [1] * len(points)


@pytest.mark.parametrize("n", [4, 7])
def test_a_region_samples_only_voxels_of_its_voxel_box(n):
    """A sample in a region's clip box reads (trilinear, clamped at the border) voxels of its `box_in_voxels` only, so
    an actor holding those voxels takes the one-process render's samples there. A sample just below a region's high
    plane may round onto voxel B b's centre: it weighs the next voxel by 0, so only the voxels of nonzero weight
    count (the actor's clamped border stands for the one of weight 0)."""
    tree = split_regions(np.ones(bricks_per_axis(SHAPE)), n, shape=SHAPE)
    size = np.array(SHAPE[::-1], dtype=np.float64)  # x, y, z
    rng = np.random.default_rng(n)
    for r in tree.regions:
        lo, hi = local_box(r, 16, SHAPE)
        points = np.concatenate([rng.uniform(lo, hi, (300, 3)), lo[None], np.nextafter(hi, lo)[None]])
        v = np.clip((points + 1) * size / 2 - 0.5, 0, size - 1)
        first = np.floor(v)
        last = np.where(v > first, first + 1, first)
        v_lo, v_end = (np.array(b[::-1]) for b in box_in_voxels(r, 16, SHAPE))
        assert np.all(first >= v_lo) and np.all(last < v_end), r
    assert plane_local(0, 3, 16, 37) == -1.0 and plane_local(3, 3, 16, 37) == 1.0

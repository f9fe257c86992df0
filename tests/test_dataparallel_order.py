"""`volren.dataparallel.order` (issue 43 item 2): the k-d tree's front-to-back order of the regions for a view agrees
with brute force: along every ray from the eye (or, orthographic, along the view direction) the regions' clip boxes,
intersected slab by slab, are met in an order that never puts a later region of the returned order first."""

from __future__ import annotations

import numpy as np
import pytest

from volren.dataparallel import local_box, plane_local, split_regions, visibility_order, visibility_order_direction

pytestmark = pytest.mark.timeout(60)


def random_tree(rng: np.random.Generator):
    grid = tuple(int(g) for g in rng.integers(1, 6, size=3))
    shape = tuple(16 * (g - 1) + int(rng.integers(2, 18)) for g in grid)  # a short last brick, as real grids have
    weights = rng.random(grid) * (rng.random(grid) < 0.6)
    return split_regions(weights, int(rng.integers(1, min(12, weights.size) + 1)), shape=shape)


def met_in_order(tree, origins: np.ndarray, directions: np.ndarray) -> list[list[int]]:
    """Per ray (origin + t direction, t >= 0) the regions whose clip box it passes through for a positive length,
    sorted by where it enters them: slab intersection, box by box."""
    boxes = [local_box(r, tree.brick, tree.shape) for r in tree.regions]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / directions
        enter, leave = [], []
        for lo, hi in boxes:
            t0, t1 = (lo - origins) * inv, (hi - origins) * inv
            # a ray parallel to a slab is inside it for all t or for none
            inside = (origins >= lo) & (origins <= hi)
            near = np.where(directions == 0, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
            far = np.where(directions == 0, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
            enter.append(np.maximum(near.max(axis=1), 0.0))
            leave.append(far.min(axis=1))
    enter, leave = np.array(enter), np.array(leave)
    hit = leave - enter > 1e-9
    return [sorted(np.flatnonzero(hit[:, k]), key=lambda i: enter[i, k]) for k in range(len(origins))]


def assert_consistent(order: list[int], met: list[list[int]]) -> int:
    rank = {region: k for k, region in enumerate(order)}
    for regions in met:
        ranks = [rank[i] for i in regions]
        assert ranks == sorted(ranks), (order, regions)
    return max(len(m) for m in met)


@pytest.mark.parametrize("seed", range(4))
def test_pinhole_order_agrees_with_brute_force_along_every_ray(seed):
    rng = np.random.default_rng(seed)
    deepest = 0
    for _ in range(12):
        tree = random_tree(rng)
        on_planes = [plane_local(r.lo[a], tree.grid[a], tree.brick, tree.shape[a]) for r in tree.regions
                     for a in range(3)]
        eyes = [rng.uniform(-1, 1, 3), rng.uniform(-3, 3, 3), rng.uniform(-3, 3, 3),
                np.array([rng.choice(on_planes), rng.choice(on_planes), rng.choice(on_planes)])[::-1]]
        for eye in eyes:
            order = visibility_order(tree, eye)
            assert sorted(order) == list(range(len(tree.regions)))
            directions = rng.normal(size=(300, 3))
            deepest = max(deepest, assert_consistent(order, met_in_order(tree, np.tile(eye, (300, 1)), directions)))
    assert deepest >= 4  # rays crossed several regions: the check had something to check


@pytest.mark.parametrize("seed", range(3))
def test_orthographic_order_agrees_with_brute_force_along_every_ray(seed):
    rng = np.random.default_rng(100 + seed)
    deepest = 0
    for _ in range(12):
        tree = random_tree(rng)
        axis_aligned = np.zeros(3)
        axis_aligned[rng.integers(3)] = rng.choice([-1.0, 1.0])
        for direction in (rng.normal(size=3), axis_aligned, rng.normal(size=3) * (rng.random(3) < 0.7)):
            if not direction.any():
                continue
            order = visibility_order_direction(tree, direction)
            origins = rng.uniform(-1, 1, (300, 3)) - 4 * direction / np.linalg.norm(direction)
            met = met_in_order(tree, origins, np.tile(direction, (300, 1)))
            deepest = max(deepest, assert_consistent(order, met))
    assert deepest >= 3


def test_orders_of_a_row_of_regions_by_hand():
    """Four regions along x: from beyond either end the order runs from that end; from inside region 2, region 2
    first, then its side of each plane before the other."""
    tree = split_regions(np.ones((1, 1, 4)), 4)
    assert visibility_order(tree, np.array([2.0, 0.0, 0.0])) == [3, 2, 1, 0]
    assert visibility_order(tree, np.array([-2.0, 0.3, -5.0])) == [0, 1, 2, 3]
    assert visibility_order(tree, np.array([0.2, 0.0, 0.0])) == [2, 3, 1, 0]
    assert visibility_order_direction(tree, np.array([-1.0, 0.2, 0.0])) == [3, 2, 1, 0]
    assert visibility_order_direction(tree, np.array([1.0, 0.0, 0.0])) == [0, 1, 2, 3]
    assert visibility_order_direction(tree, np.array([0.0, 1.0, 0.0])) == [0, 1, 2, 3]  # parallel: low first


def test_the_eye_is_placed_by_voxel_centres_and_a_plane_belongs_to_its_high_side():
    """40 voxels along x in 3 bricks: the planes sit at voxels 16 and 32's centres, local -1 + 16.5 / 20 = -0.175 and
    0.625 (not at -1/3 and 1/3, the brick grid's thirds); an eye on a plane is in the high region, which goes first."""
    tree = split_regions(np.ones((1, 1, 3)), 3, shape=(2, 2, 40))
    assert tree.root.plane == 1 and tree.root.high.plane == 2
    assert visibility_order(tree, np.array([-0.18, 0.0, 0.0])) == [0, 1, 2]
    assert visibility_order(tree, np.array([-0.17, 0.0, 0.0])) == [1, 2, 0]
    assert visibility_order(tree, np.array([plane_local(1, 3, 16, 40), 0.0, 0.0])) == [1, 2, 0]
    assert visibility_order(tree, np.array([0.62, 0.0, 0.0])) == [1, 2, 0]
    assert visibility_order(tree, np.array([plane_local(2, 3, 16, 40), 0.0, 0.0])) == [2, 1, 0]
    assert visibility_order(tree, np.array([np.nextafter(plane_local(2, 3, 16, 40), 0), 0.0, 0.0])) == [1, 2, 0]

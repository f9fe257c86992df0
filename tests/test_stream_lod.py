"""The level each brick wants and the order bricks load in (issue 41 item 3, `volren.stream.lod`), against hand
computations: a pixel's footprint 2 d tan(fov / 2) / H, the coarsest level whose voxel fits it (or the march step),
the frustum, and the priority (visible, coarse before fine, near before far)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from volren.camera import Camera
from volren.stream.layout import PyramidLayout
from volren.stream.lod import (
    brick_box,
    frame_needs,
    in_frustum,
    need,
    pixel_footprint,
    voxel_size,
    wanted_level,
)

HALF = 0.64
"""[m] half the edge of the test cube: 64 voxels of 2 cm at level 0, 32 of 4 cm at level 1, 16 of 8 cm at level 2"""
TO_WORLD = np.diag([HALF, HALF, HALF, 1.0])
LAYOUT = PyramidLayout(((64, 64, 64), (32, 32, 32), (16, 16, 16)), ((2, 2, 2), (2, 2, 2)))
FOOT_PER_M = 2 * math.tan(math.radians(30.0)) / 512
"""a pixel's footprint per metre of distance at fov 60 degrees and 512 rows: 0.0022552745"""


def camera_at(distance_to_front: float, **kw) -> Camera:
    """512 x 512, fov 60, on the cube's +z axis, ``distance_to_front`` [m] from its front face (z = HALF)."""
    kw = {"fov_y": 60.0, "width": 512, "height": 512, "look_at": (0.0, 0.0, 0.0), **kw}
    return Camera(position=(0.0, 0.0, HALF + distance_to_front), **kw)


@pytest.mark.timeout(30)
def test_footprint_and_level_by_hand():
    assert pixel_footprint(10.0, 60.0, 512) == pytest.approx(0.022552745, rel=1e-8)
    sizes = [0.005, 0.01, 0.02, 0.04]
    assert wanted_level(sizes, pixel_footprint(10.0, 60.0, 512)) == 2  # 0.02 <= 0.02255 < 0.04
    assert wanted_level(sizes, pixel_footprint(10.0, 60.0, 512), step=0.05) == 3  # the step is coarser
    assert wanted_level(sizes, pixel_footprint(5.0, 60.0, 512)) == 1  # 0.01128
    assert wanted_level(sizes, pixel_footprint(1.0, 60.0, 512)) == 0  # 0.00226: no level fits, the finest
    assert wanted_level(sizes, 0.02) == 2 and wanted_level(sizes, 0.0199) == 1  # the voxel may equal the footprint
    assert wanted_level(sizes, 1.0) == 3


@pytest.mark.timeout(30)
def test_voxel_sizes_and_brick_boxes_by_hand():
    assert [voxel_size(TO_WORLD, s) for s in LAYOUT.shapes] == pytest.approx([0.02, 0.04, 0.08], rel=1e-12)
    # level 1 brick (z 1, y 0, x 0): voxels z 16..31 (+ half a voxel at the border), y and x -0.5..16
    lo, hi = brick_box(TO_WORLD, LAYOUT, 1, (1, 0, 0))
    np.testing.assert_allclose(lo, [-HALF, -HALF, 0.02], atol=1e-12)  # voxel 16's centre: -0.64 + 16.5 * 0.04
    np.testing.assert_allclose(hi, [0.02, 0.02, HALF], atol=1e-12)
    lo, hi = brick_box(TO_WORLD, LAYOUT, 2, (0, 0, 0))  # the one coarsest brick: the whole cube
    np.testing.assert_allclose([lo, hi], [[-HALF] * 3, [HALF] * 3], atol=1e-12)


@pytest.mark.timeout(30)
def test_far_camera_wants_level_1_everywhere_near_first():
    """Front face 20 m away: footprint 0.0451 m, level 1 (0.04 <= 0.0451 < 0.08); the back bricks, 20.62 m away
    (0.0465 m), too. The front four (z brick 1) load first, nearest first."""
    assert wanted_level([0.02, 0.04, 0.08], 20.0 * FOOT_PER_M) == 1
    assert wanted_level([0.02, 0.04, 0.08], 20.62 * FOOT_PER_M) == 1
    needs = frame_needs([camera_at(20.0)], TO_WORLD, LAYOUT)
    assert [n.key for n in needs] == [(1, 1, 0, 0), (1, 1, 0, 1), (1, 1, 1, 0), (1, 1, 1, 1),
                                      (1, 0, 0, 0), (1, 0, 0, 1), (1, 0, 1, 0), (1, 0, 1, 1)]
    assert all(n.visible for n in needs)
    assert needs[0].priority == (0, -1, 20.0)
    assert needs[4].priority[2] == pytest.approx(20.62, abs=1e-12)


@pytest.mark.timeout(30)
def test_nearer_camera_splits_levels_and_coarse_loads_first():
    """Front face 17.5 m away: the front level-1 bricks (17.5 m, footprint 0.03947 m < 0.04) want level 0 and split
    into their 32 level-0 children; the back ones (18.12 m, 0.04087 m) keep level 1 and, coarse before fine, load
    first although they are farther."""
    assert wanted_level([0.02, 0.04, 0.08], 17.5 * FOOT_PER_M) == 0
    assert wanted_level([0.02, 0.04, 0.08], 18.12 * FOOT_PER_M) == 1
    needs = frame_needs([camera_at(17.5)], TO_WORLD, LAYOUT)
    assert [n.key for n in needs[:4]] == [(1, 0, 0, 0), (1, 0, 0, 1), (1, 0, 1, 0), (1, 0, 1, 1)]
    fine = needs[4:]
    assert len(fine) == 32 and {n.level for n in fine} == {0} and {n.brick[0] for n in fine} == {2, 3}
    assert [n.priority[2] for n in fine] == sorted(n.priority[2] for n in fine)  # near before far
    assert fine[0].key == (0, 3, 1, 1) and fine[0].priority[2] == pytest.approx(17.5, abs=1e-12)


@pytest.mark.timeout(30)
def test_step_and_views_that_look_away():
    assert [n.key for n in frame_needs([camera_at(17.5)], TO_WORLD, LAYOUT, step=0.1)] == [(2, 0, 0, 0)]
    away = camera_at(5.0, look_at=(0.0, 0.0, 50.0))
    needs = frame_needs([away], TO_WORLD, LAYOUT)
    assert [(n.key, n.visible) for n in needs] == [((2, 0, 0, 0), False)]
    # two views: the union, each brick at the level of the view that needs it finest
    both = frame_needs([away, camera_at(20.0)], TO_WORLD, LAYOUT)
    assert {n.key for n in both} == {n.key for n in frame_needs([camera_at(20.0)], TO_WORLD, LAYOUT)}


@pytest.mark.timeout(30)
def test_frustum_planes_by_hand():
    """fov 90 (tan 1): at depth d the view spans |x| <= d * aspect, |y| <= d; near 0.01, far 10."""
    cam = Camera(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, -1.0), fov_y=90.0, width=100, height=100, far=10.0)
    box = lambda lo, hi: (np.array(lo, float), np.array(hi, float))  # noqa: E731
    assert in_frustum(cam, *box((-0.1, -0.1, -2.1), (0.1, 0.1, -1.9)))
    assert not in_frustum(cam, *box((2.5, -0.1, -2.1), (3.0, 0.1, -1.9)))  # right of |x| <= 2.1
    assert in_frustum(cam, *box((1.9, -0.1, -2.1), (3.0, 0.1, -1.9)))  # straddles the right plane
    assert not in_frustum(cam, *box((-0.1, 2.5, -2.1), (0.1, 3.0, -1.9)))  # above
    assert not in_frustum(cam, *box((-0.1, -0.1, 1.0), (0.1, 0.1, 2.0)))  # behind the eye
    assert not in_frustum(cam, *box((-0.1, -0.1, -12.0), (0.1, 0.1, -11.0)))  # past the far plane
    wide = Camera(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, -1.0), fov_y=90.0, width=200, height=100)
    assert in_frustum(wide, *box((2.5, -0.1, -2.1), (3.0, 0.1, -1.9)))  # aspect 2: |x| <= 4.2


@pytest.mark.timeout(30)
def test_priority_order():
    needs = [need((0, 0, 0, 0), True, 1.0), need((2, 0, 0, 0), False, 0.0), need((1, 0, 0, 0), True, 9.0),
             need((1, 0, 0, 1), True, 3.0), need((0, 0, 0, 1), False, 0.5)]
    assert [n.key for n in sorted(needs)] == [(1, 0, 0, 1), (1, 0, 0, 0), (0, 0, 0, 0), (2, 0, 0, 0), (0, 0, 0, 1)]


@pytest.mark.timeout(30)
def test_layout_parents_and_children():
    """z not downsampled (as ome-zarr's writer leaves it): brick b's parent is (bz, by // 2, bx // 2)."""
    layout = PyramidLayout(((40, 40, 40), (40, 20, 20), (40, 10, 10)), ((1, 2, 2), (1, 2, 2)))
    assert [layout.bricks(k) for k in range(3)] == [(3, 3, 3), (3, 2, 2), (3, 1, 1)]
    assert layout.parent(0, (2, 2, 1)) == (2, 1, 0)
    assert list(layout.ancestors(0, (2, 2, 1))) == [(0, (2, 2, 1)), (1, (2, 1, 0)), (2, (2, 0, 0))]
    assert layout.children(1, (1, 1, 0)) == [(1, 2, 0), (1, 2, 1)]  # the last y brick takes brick 2, alone
    for level in (1, 2):
        for b in np.ndindex(*layout.bricks(level)):
            assert all(layout.parent(level - 1, c) == b for c in layout.children(level, b))
        assert sum(len(layout.children(level, b)) for b in np.ndindex(*layout.bricks(level))) == \
            math.prod(layout.bricks(level - 1))


@pytest.mark.timeout(30)
def test_the_descent_takes_every_child_of_a_level_at_once_as_the_layout_lists_them():
    """66^3 over 33^3: level 1's last brick covers level-0 bricks 2, 3 and 4 (its clamped overflow); the
    vectorised descent's children of every brick are `PyramidLayout.children`'s."""
    from volren.stream.lod import _children

    layout = PyramidLayout(((66, 66, 66), (33, 33, 33)), ((2, 2, 2),))
    bricks = np.array(list(np.ndindex(*layout.bricks(1))))
    got = sorted(map(tuple, _children(layout, 1, bricks).tolist()))
    want = sorted(c for b in bricks for c in layout.children(1, tuple(int(v) for v in b)))
    assert got == want and len(want) == 5**3 and (4, 4, 4) in want


@pytest.mark.timeout(60)
def test_the_needs_fit_the_budget_the_nearest_refined_first():
    """A close-up of a 2048^3 pyramid wants more bricks (106 K) than a budget of 3,000 or 100,000 holds: the descent
    refines, level by level (coarse before fine), the nearest bricks while the needs and their ancestors below the
    coarsest level fit, and leaves the rest at their level; under a limit that holds them all, the needs are the
    unlimited ones."""
    layout = PyramidLayout(tuple((n, n, n) for n in (2048, 1024, 512, 256, 128)), ((2, 2, 2),) * 4)
    to_world = np.diag([1.0, 1.0, 1.0, 1.0])
    cam = Camera(position=(0.2, 0.1, 1.3), look_at=(0.0, 0.0, 0.0), fov_y=50.0, width=640, height=360, near=1e-3,
                 far=10.0)
    unlimited = frame_needs([cam], to_world, layout)

    def held(needs):  # what the streamer holds beside the coarsest level: the needs and their ancestors
        return {(level, *brick) for n in needs for level, brick in layout.ancestors(n.level, n.brick)
                if level < layout.coarsest}

    assert len(held(unlimited)) > 100_000
    for limit, finest in ((3000, 2), (100_000, 0)):
        needs = frame_needs([cam], to_world, layout, limit=limit)
        assert limit - 8 < len(held(needs)) <= limit
        levels = {n.level for n in needs}
        assert min(levels) == finest
        for level in levels - {finest}:  # a level's bricks left unrefined are no nearer than the refined ones
            refined = [n.priority[2] for n in needs if n.level < level]
            kept = [n.priority[2] for n in needs if n.level == level and n.visible]
            assert not kept or min(kept) >= min(refined) - 1e-12
    whole = frame_needs([cam], to_world, layout, limit=len(held(unlimited)))
    assert [n.key for n in whole] == [n.key for n in unlimited]

"""Convex regions of a brick grid for data-parallel, sort-last rendering (issue 43 item 1): a k-d tree splits the
volume's grid of bricks (`volren.sparse`: B^3 cells each, a dense grid of n voxels has max(1, ceil((n - 1) / B))
bricks per axis) into N disjoint boxes of whole bricks that tile it, balanced by a per-brick cost, so that each Ray
actor holds and renders one box and the partial images composite in an order the tree gives per view
(`volren.dataparallel.order`).

**Split rule.** A node of the box [lo, hi) (bricks, z, y, x) that gets n regions gives n // 2 to its low child and
n - n // 2 to its high one (n = 5: 2 and 3). It splits along its longest axis (in bricks; among equally long axes,
the one whose best plane balances best) at the plane whose low side holds the weight nearest to ``W n_low / n`` (W the
node's weight); among equally good planes, the one whose brick counts are nearest that proportion (so a box of zero
weight is halved geometrically, and regions without an active brick stay compact), then the lowest plane. Each side
keeps at least as many bricks as regions it gets (never zero). Where no plane of the longest axis leaves both sides
enough bricks for n // 2 and n - n // 2 regions (a 3 x 3 brick box cut into 9), the counts move towards the side with
more bricks as little as needed. Weights may leave regions with no active brick (n above what they balance): those
are regions too, and are returned.

**Voxels.** Region bricks [a, b) per axis hold cells [B a, B b) and need voxels [B a, B b] (a cell's 8 corners), so
`box_in_voxels` is [B a, min(B b + 1, n)): adjacent regions share one voxel plane, as bricks share their aprons.

**Local coordinates** (DESIGN.md: voxel i of n sits at local -1 + (i + 0.5) 2 / n, x, y, z). Along each axis the
region of bricks [a, b) owns the local interval [u(a), u(b)) with u(p) = -1 + (B p + 0.5) 2 / n, the centre of voxel
B p, except that u(0) = -1 and u(bricks) = +1: the first region reaches the box face and the last one the far face
(where the samples between the outer voxel centres and the faces are taken, clamped at the border). The rule is
half-open, low face in, high face out, with the grid's high face +1 owned by the last region: every point of
[-1, 1]^3 belongs to exactly one region, and adjacent regions' clip boxes meet at the same float (both computed by
`plane_local`), no gap and no overlap. A region's cells span from voxel B a's centre to voxel B b's, so the samples
its clipped render takes in [u(a), u(b)) are the ones the one-process render takes there, read from the same voxels
(a sample that rounds onto voxel B b's centre weighs voxel B b + 1 by 0: the region's sub-grid, clamped at its border,
gives the same value).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from volren.errors import VolrenError
from volren.sparse.grid import BRICK

Box = tuple[int, int, int]
"""bricks (z, y, x)"""


@dataclass(frozen=True)
class Region:
    """One leaf of the k-d tree: a box of whole bricks."""

    index: int
    """the leaf's number: leaves are numbered depth-first, low child before high"""
    lo: Box
    """[bricks] (z, y, x), first brick"""
    hi: Box
    """[bricks] (z, y, x), last brick + 1"""
    weight: float
    """the sum of the weights of the region's bricks"""

    @property
    def bricks(self) -> int:
        return int(np.prod(np.subtract(self.hi, self.lo)))


@dataclass(frozen=True)
class Split:
    """An internal node: bricks below ``plane`` along ``axis`` are in ``low``, the others in ``high``."""

    axis: int
    """0 z, 1 y, 2 x (the brick grid's numpy axes)"""
    plane: int
    """[bricks] the first brick of the high child along ``axis``"""
    low: Split | int
    """a subtree or a leaf's `Region.index`"""
    high: Split | int


@dataclass(frozen=True)
class RegionTree:
    """N regions that tile a brick grid, and the k-d tree that made them (module docstring)."""

    regions: tuple[Region, ...]
    """the leaves, ``regions[i].index == i``"""
    root: Split | int
    grid: Box
    """[bricks] (z, y, x) of the whole grid"""
    shape: Box
    """[voxels] (z, y, x) of the volume the bricks cover: what `volren.dataparallel.order` places the planes by"""
    brick: int
    """B: cells per brick edge"""


def bricks_per_axis(shape: Box, brick: int = BRICK) -> Box:
    """The brick grid (z, y, x) of a dense grid of ``shape`` voxels: max(1, ceil((n - 1) / B)) per axis."""
    return _box(max(1, -(-(int(n) - 1) // brick)) for n in shape)


def split_regions(weights: np.ndarray, n: int, *, shape: Box | None = None, brick: int = BRICK) -> RegionTree:
    """Split the brick grid whose per-brick costs are ``weights`` [z, y, x] (>= 0: 1 per active brick, 0 per empty
    one, or estimated costs) into ``n`` regions (module docstring). ``shape``: the volume's voxels (z, y, x), whose
    bricks must be ``weights``'s; by default a grid of full bricks, B per brick + 1."""
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 3 or w.size == 0:
        raise VolrenError(f"region weights must be a 3-D grid of bricks (z, y, x), got shape {list(w.shape)}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise VolrenError("region weights must be finite and >= 0")
    grid = _box(w.shape)
    voxels = _box(g * brick + 1 for g in grid) if shape is None else _box(shape)
    if bricks_per_axis(voxels, brick) != grid:
        raise VolrenError(f"region weights of {list(grid)} bricks do not match a grid of {list(voxels)} voxels "
                          f"({list(bricks_per_axis(voxels, brick))} bricks of {brick}^3)")
    if not 1 <= n <= w.size:
        raise VolrenError(f"cannot split a grid of {w.size} bricks into {n} regions (1 to {w.size}: a region holds "
                          "at least one brick)")
    regions: list[Region] = []
    root = _split(w, (0, 0, 0), grid, n, regions)
    return RegionTree(tuple(regions), root, grid, voxels, brick)


def _box(values: Iterable[int]) -> Box:
    z, y, x = (int(v) for v in values)
    return z, y, x


def _split(w: np.ndarray, lo: Box, hi: Box, n: int, regions: list[Region]) -> Split | int:
    box = w[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    if n == 1:
        regions.append(Region(len(regions), lo, hi, float(box.sum())))
        return len(regions) - 1
    axis, offset, n_low = _best_plane(box, n)
    plane = lo[axis] + offset
    low_hi = _box(plane if a == axis else hi[a] for a in range(3))
    high_lo = _box(plane if a == axis else lo[a] for a in range(3))
    low = _split(w, lo, low_hi, n_low, regions)
    return Split(axis, plane, low, _split(w, high_lo, hi, n - n_low, regions))


def _best_plane(box: np.ndarray, n: int) -> tuple[int, int, int]:
    """(axis, plane offset in the box, regions below it) by the split rule (module docstring)."""
    total, size = float(box.sum()), box.size
    longest = max(box.shape)
    best: tuple | None = None
    for axis in (a for a in range(3) if box.shape[a] == longest):
        cross = size // box.shape[axis]
        below = np.cumsum(box.sum(axis=tuple(a for a in range(3) if a != axis)))
        for offset in range(1, box.shape[axis]):
            low_bricks = offset * cross
            # the counts each side can hold: n // 2 where both sides have room, else the nearest that fits
            n_low = min(max(n // 2, n - (size - low_bricks)), low_bricks)
            score = (abs(n_low - n // 2), abs(float(below[offset - 1]) - total * n_low / n),
                     abs(low_bricks - size * n_low / n), axis, offset)
            if best is None or score < best[0]:
                best = (score, axis, offset, n_low)
    assert best is not None  # the longest axis of a box of >= 2 bricks has >= 2
    return best[1], best[2], best[3]


def box_in_voxels(region: Region, brick: int, shape: Box) -> tuple[Box, Box]:
    """The voxels (z, y, x) [first, last + 1) that ``region``'s cells read in a grid of ``shape`` voxels: [B a,
    min(B b + 1, n)) per axis (module docstring)."""
    first = _box(brick * a for a in region.lo)
    end = _box(min(brick * b + 1, int(n)) for b, n in zip(region.hi, shape, strict=True))
    return first, end


def plane_local(plane: int, bricks: int, brick: int, n: int) -> float:
    """The local coordinate u(p) of brick plane ``plane`` along an axis of ``bricks`` bricks and ``n`` voxels: the
    centre of voxel B p, the faces -1 and +1 at the grid's ends (module docstring)."""
    if plane <= 0:
        return -1.0
    if plane >= bricks:
        return 1.0
    return -1.0 + (brick * plane + 0.5) * 2.0 / n


def local_box(region: Region, brick: int, shape: Box) -> tuple[np.ndarray, np.ndarray]:
    """``region``'s box in the volume's local coordinates, (lo, hi) as float64 (x, y, z): it owns [lo, hi) per axis,
    and hi where hi is +1 (module docstring)."""
    grid = bricks_per_axis(shape, brick)
    lo = [plane_local(region.lo[a], grid[a], brick, shape[a]) for a in range(3)]
    hi = [plane_local(region.hi[a], grid[a], brick, shape[a]) for a in range(3)]
    return np.array(lo[::-1]), np.array(hi[::-1])

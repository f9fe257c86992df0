"""The brick grids of a pyramid (issue 41 item 3): which bricks each level has, and which brick of the next coarser
level covers a brick (its parent), with no I/O, so that the level choice (`volren.stream.lod`), the cache and the
streamer share one definition.

A level of n voxels per axis is tiled as `volren.kernels.bricks` tiles a grid: brick b covers cells [b B, b B + B) and
voxels [b B, b B + B] (a one-voxel apron), max(1, ceil((n - 1) / B)) bricks per axis (one for a level one voxel
thick, whose single voxel the apron repeats). Level k + 1 is level k shrunk by a whole factor f >= 1 per axis (2 for
a halving, 1 where an axis is not downsampled, as ome-zarr's writer leaves z), so brick b of level k lies inside brick
b // f of level k + 1: its cells [b B, b B + B) are the coarser level's [b B / f, (b + 1) B / f), within
[(b // f) B, (b // f + 1) B).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from itertools import product

from volren.sparse import BRICK

Brick = tuple[int, int, int]
"""(bz, by, bx): a brick's place in its level's brick grid"""
BrickKey = tuple[int, int, int, int]
"""(level, bz, by, bx)"""


def brick_count(voxels: int, brick: int = BRICK) -> int:
    """Bricks along an axis of ``voxels`` voxels: the cells (voxels - 1) / B rounded up, at least one."""
    return max(1, -(-(voxels - 1) // brick))


@dataclass(frozen=True)
class PyramidLayout:
    """The voxel shapes of a pyramid's levels, finest first, and the whole downsampling factor from each level to
    the next (module docstring)."""

    shapes: tuple[tuple[int, int, int], ...]
    """voxels (z, y, x) per level, finest first"""
    factors: tuple[tuple[int, int, int], ...]
    """(z, y, x) factor from level k to level k + 1, one fewer than the levels"""
    brick: int = BRICK

    def __post_init__(self) -> None:
        if not self.shapes:
            raise ValueError("a pyramid needs at least one level")
        if len(self.factors) != len(self.shapes) - 1:
            raise ValueError(f"{len(self.factors)} downsampling factors for {len(self.shapes)} levels")
        if any(f < 1 for fs in self.factors for f in fs):
            raise ValueError(f"downsampling factors must be whole numbers >= 1, got {self.factors}")

    @property
    def count(self) -> int:
        """levels"""
        return len(self.shapes)

    @property
    def coarsest(self) -> int:
        return len(self.shapes) - 1

    def bricks(self, level: int) -> Brick:
        """Bricks (z, y, x) of ``level``'s grid."""
        return tuple(brick_count(n, self.brick) for n in self.shapes[level])  # type: ignore[return-value]

    def contains(self, level: int, brick: Brick) -> bool:
        return 0 <= level < self.count and all(0 <= b < c for b, c in zip(brick, self.bricks(level), strict=True))

    def parent(self, level: int, brick: Brick) -> Brick:
        """The brick of level + 1 that covers ``brick`` of ``level`` (module docstring)."""
        counts = self.bricks(level + 1)
        return tuple(min(b // f, c - 1) for b, f, c in zip(brick, self.factors[level], counts, strict=True))  # type: ignore[return-value]

    def ancestors(self, level: int, brick: Brick) -> Iterator[tuple[int, Brick]]:
        """(level, brick) of ``brick`` itself, then of each coarser level's brick covering it, up to the coarsest."""
        yield level, brick
        while level < self.coarsest:
            brick = self.parent(level, brick)
            level += 1
            yield level, brick

    def children(self, level: int, brick: Brick) -> list[Brick]:
        """The bricks of level - 1 whose parent is ``brick`` of ``level``."""
        counts, own = self.bricks(level - 1), self.bricks(level)
        ranges = [range(b * k, c if b == n - 1 else min(b * k + k, c))  # the last also takes a clamped overflow
                  for b, k, c, n in zip(brick, self.factors[level - 1], counts, own, strict=True)]
        return [tuple(c) for c in product(*ranges)]  # type: ignore[misc]

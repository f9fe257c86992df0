"""A volume cut to one data-parallel region (issue 43 item 1): the bricks a region's samples read, and nothing else.

A region of bricks [a, b) owns the trilinear cells [B a, B b) (`volren.kernels.common.owns_sample`: a sample is the
region's whose cell it reads), and each cell's 8 voxels lie in its brick's (B+1)^3 apron block, so a `SparseGrid` of
the whole grid's shape holding only those bricks (the rest `EMPTY`) reads, at every sample the region takes, the
voxels the whole grid reads there: the same values bit for bit, at the same positions (the region keeps the volume's
``to_world`` and the march's steps, `volren.kernels.common.region_steps`). Iso's crossing search and gradient read up
to a step and a voxel outside the cell of the step that found the surface: ``halo`` bricks around the region are held
too (read, never owned).

The grid is read from what the volume holds: a dense array (sliced, so only the region's box is bricked), a
`SparseGrid` (its bricks copied), or a streamed OME-Zarr pyramid (`volren.stream.StreamedDensity`: the region's level-0
bricks read from the file or store, mapped as the stream maps them; the whole level is never read). ``peak`` keeps the
whole volume's largest density, which MIP and MIDA normalise by.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from volren.dataparallel.regions import Region, RegionTree, box_in_voxels, bricks_per_axis
from volren.errors import VolrenError
from volren.scene import Volume
from volren.sparse.grid import EMPTY, SparseGrid, apron_reduce, brick_regions


def brick_weights(density: Any, brick: int) -> np.ndarray:
    """float64 [z, y, x] per brick of ``density``: 1 where a sample in its cells can read a density > 0, else 0
    (what `volren.dataparallel.split_regions` balances). A streamed pyramid's are judged from its coarsest level,
    which is at hand (a brick is active where the coarse voxels over its box are)."""
    grid = bricks_per_axis(density.shape, brick)
    if isinstance(density, SparseGrid):
        return (density.brick_ranges[1] > 0).astype(np.float64)
    if getattr(density, "streamed", False):
        # level-0 voxels [b B, b B + B] of brick b lie in coarse voxels [floor(b B / s), ceil((b B + B) / s)]; a box
        # maximum is separable, so it is taken one axis at a time (a 4096^3 level has 256^3 bricks)
        peak = density.coarsest
        for axis, g in enumerate(grid):
            s = density.shape[axis] / peak.shape[axis]
            peak = np.stack([np.take(peak, range(int(b * brick // s), min(int(np.ceil((b * brick + brick) / s)) + 1,
                                                                             peak.shape[axis])), axis).max(axis)
                             for b in range(g)], axis)
        return (peak > 0).astype(np.float64)
    a = np.asarray(density)
    pad = [(0, g * brick + 1 - n) for g, n in zip(grid, a.shape, strict=True)]
    return (apron_reduce(np.pad(a, pad, mode="edge"), brick, np.maximum) > 0).astype(np.float64)


def _held_bricks(region: Region, tree: RegionTree, halo: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    lo = tuple(max(a - halo, 0) for a in region.lo)
    hi = tuple(min(b + halo, g) for b, g in zip(region.hi, tree.grid, strict=True))
    return lo, hi


def _keep(grid: SparseGrid, lo: tuple[int, ...], hi: tuple[int, ...], peak: float) -> SparseGrid:
    """``grid`` with only bricks [lo, hi) kept: the others `EMPTY`, the pool compacted to the kept resident ones."""
    table = np.full(grid.table.shape, EMPTY, np.int32)
    box = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
    entries = grid.table[box]
    resident = entries >= 0
    kept = np.where(resident, -1, entries).astype(np.int32)
    kept[resident] = np.arange(int(resident.sum()), dtype=np.int32)
    table[box] = kept
    pool = np.ascontiguousarray(grid.pool[entries[resident]])
    return SparseGrid(pool=pool, table=table, constants=grid.constants, shape=grid.shape, brick=grid.brick, peak=peak)


def region_grid(density: Any, region: Region, tree: RegionTree, halo: int = 0) -> SparseGrid:
    """The bricks of ``region`` (and ``halo`` bricks around it) of ``density`` (dense, a `SparseGrid` or streamed) in
    a grid of the whole shape (module docstring)."""
    if tuple(density.shape) != tuple(tree.shape):
        raise VolrenError(f"a volume of {list(density.shape)} voxels is not the one the regions split "
                          f"({list(tree.shape)})")
    peak = float(np.max(density))
    lo, hi = _held_bricks(region, tree, halo)
    if isinstance(density, SparseGrid):
        return _keep(density, lo, hi, peak)
    if getattr(density, "streamed", False):
        return _streamed_region(density, lo, hi, tree, peak)
    first, end = box_in_voxels(Region(region.index, lo, hi, region.weight), tree.brick, tree.shape)
    block = np.asarray(density[tuple(slice(a, b) for a, b in zip(first, end, strict=True))], np.float32)
    return _keep(brick_regions(tree.shape, [(first, block)], tree.brick), lo, hi, peak)


def _streamed_region(density: Any, lo: tuple[int, ...], hi: tuple[int, ...], tree: RegionTree,
                     peak: float) -> SparseGrid:
    """The level-0 bricks [lo, hi) of a streamed pyramid, read one by one from its source (the stream's bricks are
    volren's: B^3 cells with a one-voxel apron), constant ones kept as constants."""
    if density.brick != tree.brick:
        raise VolrenError(f"the stream's bricks of {density.brick}^3 are not the regions' {tree.brick}^3")
    table = np.full(tree.grid, EMPTY, np.int32)
    pool: list[np.ndarray] = []
    constants = [0.0]
    for z in range(lo[0], hi[0]):
        for y in range(lo[1], hi[1]):
            for x in range(lo[2], hi[2]):
                raw = density.source.read_brick(0, z, y, x)
                if raw is None:
                    raise VolrenError(f"{density.source.name}: brick {(z, y, x)} of level 0 cannot be read (a bad "
                                      "chunk): a data-parallel region renders the finest level only")
                block = density.mapped(raw)
                low, high = float(block.min()), float(block.max())
                if low == high:
                    if low != 0.0:
                        constants.append(low)
                    table[z, y, x] = EMPTY if low == 0.0 else -len(constants)
                else:
                    table[z, y, x] = len(pool)
                    pool.append(block)
    e = tree.brick + 1
    return SparseGrid(pool=np.stack(pool) if pool else np.zeros((0, e, e, e), np.float32), table=table,
                      constants=np.array(constants, np.float32), shape=tuple(tree.shape), brick=tree.brick, peak=peak)


def owned_cells(region: Region, tree: RegionTree) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """The trilinear cells (z, y, x) [first, last + 1) ``region`` owns: [B a, B b), the last brick's clipped to the
    grid's n - 1 cells."""
    lo = tuple(tree.brick * a for a in region.lo)
    hi = tuple(min(tree.brick * b, n - 1) for b, n in zip(region.hi, tree.shape, strict=True))
    return lo, hi  # type: ignore[return-value]


def region_volume(volume: Volume, region: Region, tree: RegionTree, halo: int = 0) -> Volume:
    """``volume`` as region ``region`` of ``tree`` renders it: its density (and fire's emission grid) cut to the
    region's bricks (`region_grid`), its cells owned (`volren.scene.Volume.owned_cells`), all else the same."""
    emission = volume.emission_grid
    if emission is not None:
        emission = region_grid(emission, region, tree, halo)
    return replace(volume, density=region_grid(volume.density, region, tree, halo), emission_grid=emission,
                   owned_cells=owned_cells(region, tree))

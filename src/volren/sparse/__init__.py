"""Sparse, bricked density grids on the host (issue 41): `SparseGrid` and the ways to build one."""

from volren.sparse.grid import BRICK, EMPTY, BrickBuilder, SparseGrid, brick_dense, brick_regions

__all__ = ["BRICK", "EMPTY", "BrickBuilder", "SparseGrid", "brick_dense", "brick_regions"]

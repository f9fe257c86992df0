"""OpenVDB ``.vdb`` files (Houdini, Blender, EmberGen smoke and fire) through tinyvdb: ZIP / Blosc, half precision.

A grid is densified over its active voxels' index bounding box (OpenVDB's ``file_bbox_min`` / ``file_bbox_max``
stats, which ``openvdb::io::File::write`` stores for every grid; else the box of its active leaves), inactive voxels
reading as the background value. Placement is the grid's index-to-world map (OpenVDB's row-vector convention,
world = [i j k 1] M): translation, non-unit and non-uniform voxel sizes, or a general affine map. OpenVDB states no
length unit; volren reads it as metres (Blender and Houdini work in metres) unless ``units`` says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from volren.errors import VolrenError

MAX_DENSE_VOXELS = 1 << 30
"""A dense copy of a sparse grid larger than this (4 GiB of float32) is refused before anything is allocated."""
_FLOAT_TREES = ("Tree_float_", "Tree_double_", "Tree_half_")
"""tinyvdb type names of the scalar grids volren reads (half is stored as float with ``is_saved_as_half_float``)."""
_SCALE_TRANSLATE = ("scale", "translation", "scale_translate", "uniform_scale", "uniform_scale_translate")
"""tinyvdb map types whose ``scale`` and ``translation`` are the whole map (their ``matrix`` is the identity)."""


@dataclass(frozen=True)
class VdbGrid:
    """One grid densified over an index box."""

    data: np.ndarray
    """float32 ``[z, y, x]``: dense index (0, 0, 0) is file index ``lo``."""
    lo: tuple[int, int, int]
    """inclusive index bounds (x, y, z) of the box."""
    hi: tuple[int, int, int]
    index_to_world: np.ndarray
    """4x4, column convention: dense index (x, y, z) to the file's world (OpenVDB units)."""


def _open(path: Path):
    import tinyvdb  # lazy: only .vdb users pay for the import

    try:
        vdb = tinyvdb.open(str(path))
        vdb.read_grids()  # tinyvdb decompresses all grids at once; there is no per-grid read
    except tinyvdb.VDBError as exc:
        raise VolrenError(f"{path}: not a readable OpenVDB file, truncated or corrupt ({exc})") from None
    return vdb


def _grid_names(vdb) -> list[tuple[str, str]]:
    return [(vdb.grid_name(i), vdb.grid_type_name(i)) for i in range(vdb.grid_count)]


def _describe(names: list[tuple[str, str]]) -> str:
    return ", ".join(f"{n} ({t.removeprefix('Tree_').split('_')[0]})" for n, t in names) or "(none)"


def _find_grid(path: Path, vdb, name: str | None, flag: str) -> int:
    """Index of the grid ``name``; None picks ``density``, else the only float grid."""
    names = _grid_names(vdb)
    floats = [i for i, (_, t) in enumerate(names) if t.startswith(_FLOAT_TREES)]
    if name is None:
        named = [i for i in floats if names[i][0] == "density"]
        if named or len(floats) == 1:
            return (named or floats)[0]
        reason = "no float grid" if not floats else "several float grids and none named 'density'"
        raise VolrenError(f"{path}: {reason}; pick one with {flag} NAME: {_describe(names)}")
    match = [i for i, (n, _) in enumerate(names) if n == name]
    if not match:
        raise VolrenError(f"{path}: no grid named {name!r} ({flag}); the file holds {_describe(names)}")
    if match[0] not in floats:
        raise VolrenError(f"{path}: grid {name!r} is of type {names[match[0]][1]}; {flag} needs a float grid")
    return match[0]


def _index_to_world(path: Path, grid) -> np.ndarray:
    """4x4 (column convention) from the file's voxel index (i, j, k) to its world."""
    transform = grid.transform
    kind = transform["type"]
    m = np.eye(4)
    if kind in _SCALE_TRANSLATE:
        m[:3, :3] = np.diag(transform["scale"])
        m[:3, 3] = transform["translation"]
    elif kind == "affine":
        m = np.array(transform["matrix"], dtype=np.float64).T  # OpenVDB: row vectors, translation in the last row
    else:
        raise VolrenError(f"{path}: grid {grid.name!r} has a {kind!r} transform; volren reads linear (affine) maps")
    if not np.all(np.isfinite(m)) or abs(np.linalg.det(m[:3, :3])) < 1e-30:
        raise VolrenError(f"{path}: grid {grid.name!r} has a degenerate or non-finite index-to-world transform")
    return m


def _active_box(path: Path, grid) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive index bounds of the active voxels: the stats OpenVDB writes, if they lie within the active leaves
    (tinyvdb's ``active_bbox``, leaf-aligned, exclusive max), else the leaves' box."""
    leaves = grid.active_bbox()
    if leaves is None or grid.active_voxel_count() == 0:
        raise VolrenError(f"{path}: grid {grid.name!r} has no active voxels")
    leaf_lo, leaf_hi = np.array(leaves[0]), np.array(leaves[1]) - 1
    meta = grid.metadata
    lo, hi = np.array(meta.get("file_bbox_min", leaf_lo)), np.array(meta.get("file_bbox_max", leaf_hi))
    if lo.shape != (3,) or hi.shape != (3,) or np.any(lo < leaf_lo) or np.any(hi > leaf_hi) or np.any(hi < lo):
        lo, hi = leaf_lo, leaf_hi
    return lo.astype(np.int64), hi.astype(np.int64)


def _densify(path: Path, grid, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """float32 ``[z, y, x]`` over the inclusive box; tinyvdb's DenseGrid buffer is already x-fastest."""
    try:
        dense = grid.materialize_dense(tuple(int(v) for v in lo), tuple(int(v) + 1 for v in hi))
    except Exception as exc:  # tinyvdb.VDBError: a grid whose nodes it cannot decode
        raise VolrenError(f"{path}: cannot densify grid {grid.name!r} ({exc})") from None
    return np.asarray(memoryview(dense), dtype=np.float32)  # zero-copy: the array keeps the DenseGrid alive


def _check_size(path: Path, lo: np.ndarray, hi: np.ndarray, grids: int) -> None:
    size = hi - lo + 1
    if grids * int(np.prod(size)) > MAX_DENSE_VOXELS:
        raise VolrenError(f"{path}: a dense copy of {grids} grid(s) of {size[0]}x{size[1]}x{size[2]} voxels is too "
                          f"large to load (limit {MAX_DENSE_VOXELS} voxels)")


def read_vdb(path: str | Path, grid: str | None = None, emission_grid: str | None = None
             ) -> tuple[VdbGrid, np.ndarray | None]:
    """The density grid (``grid``, see ``_find_grid``) densified over its active box, and ``emission_grid`` (e.g.
    ``temperature``, raw values) densified over the same index box, or None. The emission grid must share the
    density grid's transform, so that voxel (i, j, k) of both is the same place."""
    path = Path(path)
    vdb = _open(path)
    try:
        density_grid = vdb.grid(_find_grid(path, vdb, grid, "--grid"))
        to_world = _index_to_world(path, density_grid)
        lo, hi = _active_box(path, density_grid)
        emission = None
        if emission_grid is not None:
            other = vdb.grid(_find_grid(path, vdb, emission_grid, "--emission-grid"))
            if not np.allclose(_index_to_world(path, other), to_world, rtol=1e-9, atol=0.0):
                raise VolrenError(f"{path}: grid {emission_grid!r} (--emission-grid) has another index-to-world "
                                  f"transform than the density grid {density_grid.name!r}")
        _check_size(path, lo, hi, 1 if emission_grid is None else 2)
        data = _densify(path, density_grid, lo, hi)
        if emission_grid is not None:
            emission = _densify(path, other, lo, hi)
            if not np.all(np.isfinite(emission)):
                raise VolrenError(f"{path}: grid {emission_grid!r} (--emission-grid) holds NaN/Inf values")
    finally:
        vdb.close()  # the sparse trees go before the caller validates (and copies) the dense grid
    placed = to_world.copy()
    placed[:3, 3] = to_world[:3, :3] @ lo + to_world[:3, 3]  # dense index 0 is file index lo
    return VdbGrid(data, tuple(int(v) for v in lo), tuple(int(v) for v in hi), placed), emission


def read_vdb_grid_like(path: str | Path, name: str, like: str | None = None) -> np.ndarray:
    """Grid ``name`` of the file as float32 ``[z, y, x]``, densified over the index box of the density grid ``like``
    (chosen as ``read_vdb`` does when None), so that it lines up voxel for voxel with ``load_volume``'s density."""
    _, emission = read_vdb(path, like, name)
    return emission

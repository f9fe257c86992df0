"""OpenVDB ``.vdb`` files (Houdini, Blender, EmberGen smoke and fire, C++ simulations) through tinyvdb: ZIP / Blosc,
float, double (read as float32) and half precision.

A grid is read as bricks (`volren.sparse.SparseGrid`, issue 41 item 2) over its active voxels' index bounding box
(OpenVDB's ``file_bbox_min`` / ``file_bbox_max`` stats, which ``openvdb::io::File::write`` stores for every grid; else
the box of its active leaves and tiles), without a dense copy: memory goes with the active voxels, not the box.
Inactive voxels read as the background value. Active tiles (the constant regions ``prune()`` stores in the internal
nodes and the root instead of leaves: 8^3, 128^3 and 4096^3 voxels) fill their region with their value: constant
bricks, no pool memory. Placement is the
grid's index-to-world map (OpenVDB's row-vector convention, world = [i j k 1] M): translation, non-unit and
non-uniform voxel sizes, or a general affine map. OpenVDB states no length unit; volren reads it as metres (Blender
and Houdini work in metres) unless ``units`` says otherwise.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from volren.device import check_allocation
from volren.errors import VolrenError
from volren.sparse import BRICK, BrickBuilder, SparseGrid

BRICK_BYTES = (BRICK + 1) ** 3 * 4
"""[bytes] of a brick in the pool: B^3 cells with a one-voxel apron, float32"""

MAX_TABLE_BRICKS = 1 << 30
"""[bricks] of the page table over a grid's active box: 4 GiB of int32 entries (a 16384^3 box at B = 16)"""
_SCALAR_TREES = {"Tree_float_": np.dtype("<f4"), "Tree_double_": np.dtype("<f8")}
"""type-name prefixes of the scalar grids volren reads, and the values tinyvdb decodes their leaves to: float (half
precision is a float grid stored with ``is_saved_as_half_float``, as OpenVDB 10 writes it) and double (C++
simulations' ``DoubleGrid``), which volren reads as float32. Only these are ever offered as ``--grid`` choices."""
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_MAGIC = 0x56444220
_MIN_FILE_VERSION = 222
"""OPENVDB_FILE_VERSION_NODE_MASK_COMPRESSION: per-grid compression, instancing and mask metadata are all present."""
_COMPRESS_ZIP, _COMPRESS_ACTIVE_MASK, _COMPRESS_BLOSC = 0x1, 0x2, 0x4
_MAP_BYTES = {"AffineMap": 128, "UnitaryMap": 128, "ScaleMap": 120, "UniformScaleMap": 120, "TranslationMap": 24,
              "ScaleTranslateMap": 144, "UniformScaleTranslateMap": 144}
"""bytes each linear map writes after its type name (Mat4d, or 5-6 Vec3d of scale, voxel size and their inverses)"""
_LEAF_CHUNK = 128
"""leaves (256 KiB of values) scattered into the bricks at once: their index arrays (5 MiB) bound the load's working
set (512: 123 MiB peak rise against 106 for a 29 MiB pool, and no faster)"""
_TILE_EXTENT = {4: 8, 5: 128}
"""voxels along an edge of a tile of the lower (log2dim 4) and upper (log2dim 5) internal node: its child's extent"""
_ROOT_TILE_EXTENT = 4096
_NO_MASK_AND_ALL_VALS = 6
"""``io::readCompressedValues`` metadata byte: every value is stored, even with active-mask compression"""
_SCALE_TRANSLATE = ("scale", "translation", "scale_translate", "uniform_scale", "uniform_scale_translate")
"""tinyvdb map types whose ``scale`` and ``translation`` are the whole map (their ``matrix`` is the identity)."""


@dataclass(frozen=True)
class _Tiles:
    """A grid's active tiles: constant cubes stored in its internal nodes and root instead of leaves."""

    origins: np.ndarray
    """(T, 3) int64 index (x, y, z) of each tile's first voxel"""
    extents: np.ndarray
    """(T,) int64 edge in voxels: 8 (lower internal node), 128 (upper) or 4096 (root)"""
    values: np.ndarray
    """(T,) float64 (a double grid's tiles exactly; float32 ones widened)"""


@dataclass(frozen=True)
class VdbGrid:
    """One grid over an index box, as bricks."""

    data: SparseGrid
    """float32 ``[z, y, x]``: index (0, 0, 0) is file index ``lo``"""
    lo: tuple[int, int, int]
    """inclusive index bounds (x, y, z) of the box."""
    hi: tuple[int, int, int]
    index_to_world: np.ndarray
    """4x4, column convention: dense index (x, y, z) to the file's world (OpenVDB units)."""


def _map(path: Path) -> mmap.mmap:
    """The file's bytes for the header and topology reads (mapped: only the pages read are loaded)."""
    try:
        with open(path, "rb") as f:
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError) as exc:  # ValueError: an empty file
        raise VolrenError(f"{path}: cannot read the file ({exc})") from None


def _open(path: Path):
    import tinyvdb  # lazy: only .vdb users pay for the import

    try:
        vdb = tinyvdb.open(str(path))
        vdb.read_grids()  # tinyvdb decompresses all grids at once; there is no per-grid read
    except tinyvdb.VDBError as exc:
        halves = _half_doubles(path)
        if halves:  # say why, rather than "corrupt"
            raise VolrenError(f"{path}: grid {halves[0]!r} is a double grid saved as half precision, which tinyvdb "
                              f"cannot decode ({exc}); save it at full precision (or as a float grid)") from None
        raise VolrenError(f"{path}: not a readable OpenVDB file, truncated or corrupt ({exc})") from None
    return vdb


def _half_doubles(path: Path) -> list[str]:
    """The file's double grids saved as half precision (``Tree_double_5_4_3_HalfFloat``): tinyvdb 0.9.0 fails on
    the whole file with one of them. [] when the header does not parse."""
    try:
        with open(path, "rb") as f:
            grids = _grid_offsets(f.read(1 << 20))  # the descriptors lie at the start
    except (OSError, struct.error, VolrenError):
        return []
    return [name for name, _, _, half, type_name in grids if half and type_name.startswith("Tree_double_")]


def _grid_names(vdb) -> list[tuple[str, str]]:
    return [(vdb.grid_name(i), vdb.grid_type_name(i)) for i in range(vdb.grid_count)]


def _value_type(type_name: str) -> np.dtype | None:
    """The values tinyvdb decodes a grid of this type name to, None for a grid volren cannot read as a density."""
    return next((dt for prefix, dt in _SCALAR_TREES.items() if type_name.startswith(prefix)), None)


def _describe(names: list[tuple[str, str]]) -> str:
    return ", ".join(f"{n} ({t.removeprefix('Tree_').split('_')[0]})" for n, t in names) or "(none)"


def _find_grid(path: Path, names: list[tuple[str, str]], name: str | None, option: str) -> int:
    """Index of the grid ``name`` among ``names`` ((name, type name) per grid); None picks ``density``, else the
    only scalar (float or double) grid. A refusal offers as choices only the grids that can be read; the others are
    named as such; it names the ``option`` (``grid``, ``emission_grid``) as a keyword and as the CLI's flag."""
    cli = "--" + option.replace("_", "-")
    scalar = [i for i, (_, t) in enumerate(names) if _value_type(t) is not None]
    readable = _describe([names[i] for i in scalar])
    others = [names[i] for i in range(len(names)) if i not in scalar]
    rest = f"; its other grids, {_describe(others)}, are not scalar float or double grids" if others else ""
    if name is None:
        named = [i for i in scalar if names[i][0] == "density"]
        if named or len(scalar) == 1:
            return (named or scalar)[0]
        if not scalar:
            raise VolrenError(f"{path}: no scalar float or double grid to read as the density; the file holds "
                              f"{_describe(names)}")
        raise VolrenError(f"{path}: several scalar grids and none named 'density'; pick one with {option}=NAME (CLI: "
                          f"{cli} NAME): "
                          f"{readable}")
    match = [i for i, (n, _) in enumerate(names) if n == name]
    choices = f"pick one of {readable}" if scalar else "the file has no scalar float or double grid"
    if not match:
        raise VolrenError(f"{path}: no grid named {name!r} ({option}=, CLI: {cli}); {choices}{rest}")
    if match[0] not in scalar:
        raise VolrenError(f"{path}: grid {name!r} is of type {names[match[0]][1]}; {option}= (CLI: {cli}) needs a "
                          "scalar float or "
                          f"double grid: {choices}")
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


class _Reader:
    """Little-endian reads from the file's bytes at a position."""

    def __init__(self, data: bytes | mmap.mmap, pos: int = 0):
        self.data, self.pos = data, pos

    def take(self, fmt: str):
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += struct.calcsize("<" + fmt)
        return values if len(values) > 1 else values[0]

    def raw(self, size: int) -> bytes:
        if size < 0 or self.pos + size > len(self.data):
            raise struct.error("read past the end of the file")
        self.pos += size
        return self.data[self.pos - size : self.pos]

    def string(self) -> str:
        return self.raw(self.take("I")).decode("utf-8", "replace")

    def skip_metadata(self) -> None:
        for _ in range(self.take("i")):  # MetaMap: name, type name, size-prefixed value
            self.string(), self.string()
            self.raw(self.take("I"))


def _grid_offsets(data: bytes | mmap.mmap) -> list[tuple[str, int, int, bool, str]]:
    """(name, grid position, buffers position, saved as half, type name) of each grid, from the file header's
    descriptors."""
    r = _Reader(data)
    if r.take("q") != _MAGIC:
        raise VolrenError("no OpenVDB magic number")
    version = r.take("I")
    if version < _MIN_FILE_VERSION:
        raise VolrenError(f"OpenVDB file format version {version} is older than volren reads ({_MIN_FILE_VERSION}+, "
                          "OpenVDB 3.2 and later)")
    r.take("II")  # library major, minor
    if not r.take("?"):
        raise VolrenError("the file has no grid offsets (an old streamed file)")
    r.raw(36)  # UUID
    r.skip_metadata()
    grids = []
    for _ in range(r.take("i")):
        name, type_name, _parent = r.string(), r.string(), r.string()
        grid_pos, block_pos, end_pos = r.take("qqq")
        grids.append((name.split("\x1e")[0], grid_pos, block_pos, type_name.endswith("_HalfFloat"), type_name))
        r.pos = end_pos
    return grids


def _compressed_values(r: _Reader, count: int, value_mask: np.ndarray, compression: int, half: bool,
                       decode: bool, dtype: np.dtype = _SCALAR_TREES["Tree_float_"]) -> np.ndarray | None:
    """``io::readCompressedValues`` (an internal node's tile values): the mask-compression metadata byte, inactive
    values and selection mask, then the data, size-prefixed when ZIP / Blosc compressed. Values are ``dtype`` (the
    grid's: float32 or float64), or half precision when ``half``. Decoded (float64, all ``count`` places, inactive
    ones 0) when ``decode``, else stepped over."""
    metadata = r.take("b")
    r.raw(dtype.itemsize * ((metadata in (2, 4, 5)) + (metadata == 5)))  # one or two inactive values, full width
    r.raw(count // 8 * (metadata in (3, 4, 5)))  # selection mask between the two inactive values
    masked = bool(compression & _COMPRESS_ACTIVE_MASK) and metadata != _NO_MASK_AND_ALL_VALS
    stored = int(value_mask.sum()) if masked else count  # mask compression keeps the active values only
    if half and stored == 0:  # io::HalfReader reads (and HalfWriter writes) nothing for no values
        return None
    width = 2 if half else dtype.itemsize
    if compression & (_COMPRESS_BLOSC | _COMPRESS_ZIP):
        size = r.take("q")  # the compressed size; <= 0: stored uncompressed, -size bytes
        raw = r.raw(abs(size))
        if decode and size > 0:
            raw = _decompress(raw, compression)
    else:
        raw = r.raw(stored * width)
    if not decode:
        return None
    if len(raw) != stored * width:
        raise VolrenError(f"tile values decode to {len(raw)} bytes, not the {stored * width} of {stored} values")
    values = np.frombuffer(raw, np.float16 if half else dtype).astype(np.float64)
    if not masked:
        return values
    out = np.zeros(count, np.float64)
    out[value_mask] = values
    return out


def _decompress(raw: bytes, compression: int) -> bytes:
    """One ``io::bloscToStream`` / ``zipToStream`` chunk (Blosc takes precedence, as in ``io::readData``)."""
    import zlib

    from numcodecs import blosc  # zarr's Blosc; lazy: only grids with active tiles decode any

    try:
        return blosc.decompress(raw) if compression & _COMPRESS_BLOSC else zlib.decompress(raw)
    except (RuntimeError, ValueError, zlib.error) as exc:
        raise VolrenError(f"its tile values do not decompress ({exc})") from None


def _leaf_origins(path: Path, data: mmap.mmap, index: int, name: str, dtype: np.dtype
                  ) -> tuple[np.ndarray, np.ndarray, _Tiles]:
    """Origins (L, 3) (x, y, z) of the grid's leaves in file order, their active voxel counts and the grid's active
    tiles, read from the tree topology (root tiles and children, then per internal node its child and value masks
    and tile values), which ends where the leaf buffers begin. tinyvdb 0.9.0 decodes every leaf's values (not the
    tiles') but places at most 64 leaves per lower internal node in its own index (so its ``materialize_dense`` /
    ``to_sparse`` drop the rest of any larger grid); volren places the leaves itself. ``dtype``: the grid's values
    (float32 or float64: the background, root tiles and tile values are stored at that width)."""
    offsets = _grid_offsets(data)
    if index >= len(offsets) or offsets[index][0] != name:
        raise VolrenError(f"grid {name!r} is not where the file header puts it")
    _, grid_pos, block_pos, half, _ = offsets[index]
    r = _Reader(data, grid_pos)
    compression = r.take("I")
    r.skip_metadata()
    map_type = r.string()
    if map_type not in _MAP_BYTES:
        raise VolrenError(f"grid {name!r} has a {map_type} transform; volren reads linear (affine) maps")
    r.raw(_MAP_BYTES[map_type])
    r.take("i")  # buffer count (1)
    value = dtype.char  # "f" or "d"
    r.take(value)  # background
    tiles, children = r.take("II")
    root = [r.take(f"iii{value}?") for _ in range(tiles)]  # RootNode::readTopology: origin, value, active
    root = [t for t in root if t[4]]
    origins, counts = [], []
    tile_origins = [np.array([t[:3] for t in root], np.int64).reshape(-1, 3)]
    tile_extents = [np.full(len(root), _ROOT_TILE_EXTENT, np.int64)]
    tile_values = [np.array([t[3] for t in root], np.float64)]

    def node(origin: np.ndarray, log2dim: int, child_extent: int) -> None:
        size = 1 << (3 * log2dim)
        child_mask = np.unpackbits(np.frombuffer(r.raw(size // 8), np.uint8), bitorder="little").astype(bool)
        value_mask = np.unpackbits(np.frombuffer(r.raw(size // 8), np.uint8), bitorder="little").astype(bool)
        active = np.flatnonzero(value_mask & ~child_mask)
        values = _compressed_values(r, size, value_mask, compression, half, decode=len(active) > 0, dtype=dtype)
        dim = (1 << log2dim) - 1

        def place(index: np.ndarray) -> np.ndarray:  # table index (x slowest) to the child's or tile's origin
            return origin + np.stack([index >> (2 * log2dim), (index >> log2dim) & dim, index & dim], 1) * child_extent

        if len(active):
            tile_origins.append(place(active))
            tile_extents.append(np.full(len(active), _TILE_EXTENT[log2dim], np.int64))
            tile_values.append(values[active])
        index = np.flatnonzero(child_mask)
        children = place(index)
        if log2dim == 4:  # the lower internal node's children are leaves: their 512-bit value masks, one after another
            origins.append(children)
            masks = np.frombuffer(r.raw(64 * len(index)), np.uint8).reshape(-1, 64)
            # bits counted per byte (NumPy 2): unpacked, the masks took 8x their bytes, what a refused load peaked at
            counts.append(np.bitwise_count(masks).sum(axis=1) if hasattr(np, "bitwise_count")
                          else np.unpackbits(masks, axis=1).sum(axis=1))
        else:
            for child in children:
                node(child, 4, 8)

    for _ in range(children):
        node(np.array(r.take("iii"), dtype=np.int64), 5, 128)
    if block_pos > grid_pos and r.pos != block_pos:  # tinyvdb's own writer leaves the buffer position unset
        raise VolrenError(f"grid {name!r}: its tree topology does not end where the file says ({r.pos} != "
                          f"{block_pos})")
    tiles_found = _Tiles(np.concatenate(tile_origins), np.concatenate(tile_extents), np.concatenate(tile_values))
    if not origins:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), tiles_found
    return np.concatenate(origins).astype(np.int64), np.concatenate(counts).astype(np.int64), tiles_found


def _leaves_box(origins: np.ndarray, tiles: _Tiles) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive index bounds (x, y, z) of a grid's 8^3 leaves and active tiles together."""
    starts = np.concatenate([origins, tiles.origins])
    ends = np.concatenate([origins + 7, tiles.origins + tiles.extents[:, None] - 1])
    return starts.min(axis=0), ends.max(axis=0)


def _active_box(path: Path, grid, origins: np.ndarray, tiles: _Tiles) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive index bounds of the active voxels: the stats OpenVDB writes (``file_bbox_min`` / ``max``,
    ``evalActiveVoxelBoundingBox``: tiles included), if they lie within the leaves and active tiles, else the box of
    those."""
    leaf_lo, leaf_hi = _leaves_box(origins, tiles)
    meta = grid.metadata
    lo, hi = np.array(meta.get("file_bbox_min", leaf_lo)), np.array(meta.get("file_bbox_max", leaf_hi))
    if lo.shape != (3,) or hi.shape != (3,) or np.any(lo < leaf_lo) or np.any(hi > leaf_hi) or np.any(hi < lo):
        lo, hi = leaf_lo, leaf_hi
    return lo.astype(np.int64), hi.astype(np.int64)


def _leaves(path: Path, data: mmap.mmap, vdb, index: int) -> tuple[list, np.ndarray, _Tiles, np.dtype]:
    """tinyvdb's decoded leaves of grid ``index`` in file order, their origins, the grid's active tiles and its
    values' dtype; refused unless every leaf's active count matches the topology's, so that a leaf is never put in
    another's place."""
    grid = vdb.grid(index)
    tree = grid.tree
    dtype = _value_type(vdb.grid_type_name(index))
    leaves = [n for n in (tree.node(i) for i in range(tree.num_nodes)) if n.level == 3]
    try:
        origins, counts, tiles = _leaf_origins(path, data, index, grid.name, dtype)
    except struct.error:
        raise VolrenError(f"{path}: not a readable OpenVDB file, truncated or corrupt (grid {grid.name!r})") from None
    except VolrenError as exc:
        raise VolrenError(f"{path}: {exc}") from None
    if len(leaves) != len(origins) or not np.array_equal([n.active_voxel_count for n in leaves], counts):
        raise VolrenError(f"{path}: grid {grid.name!r}: tinyvdb decoded {len(leaves)} leaves, the file's topology "
                          f"lists {len(origins)} (or their active voxels differ)")
    if not counts.any() and not len(tiles.values):
        raise VolrenError(f"{path}: grid {grid.name!r} has no active voxels")
    return leaves, origins, tiles, dtype


def _float32(values: np.ndarray, what: str) -> np.ndarray:
    """A double grid's values as float32 (rounded to nearest); refused, naming the grid, where one lies beyond
    float32's range (it would become Inf). NaN stays NaN for ``validate_density`` to count."""
    if values.dtype != np.float32 and values.size and np.nanmax(np.abs(values), initial=0.0) > _FLOAT32_MAX:
        huge = int(np.count_nonzero(np.abs(values) > _FLOAT32_MAX))
        raise VolrenError(f"{what} (double) holds {huge} value(s) beyond the range of float32, which volren reads it "
                          f"as (up to {np.nanmax(np.abs(values)):.3g}); rescale the grid")
    return values.astype(np.float32, copy=False)


def _declared(origins: np.ndarray, tiles: _Tiles, lo: np.ndarray, hi: np.ndarray, background: float, what: str
              ) -> tuple[BrickBuilder, np.ndarray, np.ndarray]:
    """A `BrickBuilder` over the inclusive index box [lo, hi] with the bricks the leaves and tiles touch declared
    (from the topology alone: no pool yet, so `BrickBuilder.declared_bytes` is what `_brickify` will take), and
    each 8^3 block's first voxel (z, y, x) in the box and whether it meets the box."""
    builder = BrickBuilder(tuple(int(n) for n in (hi - lo + 1)[::-1]), BRICK, background)
    small = tiles.extents == 8
    big = (tiles.origins[~small] - lo)[:, ::-1]
    builder.tiles(big, big + tiles.extents[~small, None] - 1, _float32(tiles.values, what)[~small])
    corners = np.concatenate([origins, tiles.origins[small]]) - lo  # (x, y, z) of every 8^3 block, in the box
    keep = np.all((corners + 7 >= 0) & (corners <= hi - lo), axis=1)
    first = corners[:, ::-1]
    builder.touch(first[keep], first[keep] + 7)
    return builder, first, keep


def _brickify(leaves: list, origins: np.ndarray, tiles: _Tiles, dtype: np.dtype, lo: np.ndarray, hi: np.ndarray,
              background: float, what: str) -> SparseGrid:
    """The grid over the inclusive index box [lo, hi] as bricks (`volren.sparse.BrickBuilder`), without a dense copy
    (issue 41 item 2): each 8^3 leaf (tinyvdb's values of ``dtype``, x slowest, z fastest) and each leaf-sized tile
    scattered into the bricks that hold its voxels, in chunks; a larger tile (128^3, 4096^3) a constant box, whose
    inner bricks become constants and only its border bricks take pool memory; inactive voxels the background. A
    double grid's values are rounded to float32 (``_float32``; ``what`` names the grid). Memory: the bricks the
    leaves and tiles touch, (B+1)^3 / B^3 of their voxels and the bricks' unfilled part."""
    builder, first, keep = _declared(origins, tiles, lo, hi, background, what)
    small = tiles.extents == 8
    tile_values = _float32(tiles.values, what)
    offsets = np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(8), indexing="ij"), -1).reshape(-1, 3)
    inside = np.flatnonzero(keep)
    count = len(origins)
    for chunk in np.array_split(inside, max(1, len(inside) // _LEAF_CHUNK)):
        is_leaf = chunk < count
        values = np.empty((len(chunk), 8, 8, 8), np.float32)  # [block, x, y, z] as the file stores a leaf
        if is_leaf.any():
            raw = np.frombuffer(b"".join(leaves[i].data for i in chunk[is_leaf]), dtype)
            values[is_leaf] = _float32(raw, what).reshape(-1, 8, 8, 8)
        values[~is_leaf] = tile_values[small][chunk[~is_leaf] - count, None, None, None]
        voxels = (first[chunk][:, None, :] + offsets[None]).reshape(-1, 3)  # [block, z, y, x] order
        # voxels outside the box (a leaf across its border) fall in no brick: `scatter` drops them
        builder.scatter(voxels, values.transpose(0, 3, 2, 1).reshape(-1))
    return builder.build()


def _check_size(path: Path, lo: np.ndarray, hi: np.ndarray) -> None:
    """The page table over the index box must stay addressable (int32 entries, one per brick of `BRICK`^3 cells)."""
    bricks = int(np.prod(-(-(hi - lo) // BRICK), dtype=np.int64))
    if bricks > MAX_TABLE_BRICKS:
        size = hi - lo + 1
        raise VolrenError(f"{path}: the active box of {size[0]}x{size[1]}x{size[2]} voxels needs {bricks} bricks' "
                          f"page table, more than {MAX_TABLE_BRICKS}")


def _check_budget(path: Path, data: mmap.mmap, grids: list[tuple[str | None, str]],
                  box: tuple[np.ndarray, np.ndarray] | None, budget: float | None) -> None:
    """Refuse, in one line naming the file, the estimate and the budget, a file whose bricks (the density grid's
    and the emission grid's, ``grids`` as (name, option)) would take more than ``budget`` bytes (None: more than the
    machine's free memory, `volren.device.check_allocation`): estimated from the
    tree topology alone (`_declared` over the box of the density grid's leaves and tiles, which holds its active
    box, or ``box``), before tinyvdb decodes any leaf (`_open` decodes every grid at once). A file whose header or
    topology does not parse is left to tinyvdb to name what is wrong."""
    try:
        offsets = _grid_offsets(data)
    except (struct.error, VolrenError):
        return
    names = [(o[0], o[4]) for o in offsets]
    total, lo, hi = 0, None, None
    for name, option in grids:
        try:
            index = _find_grid(path, names, name, option)
            origins, _, tiles = _leaf_origins(path, data, index, names[index][0], _value_type(names[index][1]))
        except (struct.error, VolrenError):  # refused as before, in tinyvdb's names
            return
        if lo is None:
            if not len(origins) and not len(tiles.origins):
                return  # no active voxels: `_leaves` says so
            lo, hi = _leaves_box(origins, tiles) if box is None else (np.asarray(box[0], np.int64),
                                                                        np.asarray(box[1], np.int64))
            if np.prod(-(-(hi - lo) // BRICK), dtype=np.int64) > MAX_TABLE_BRICKS:
                return  # `_check_size` refuses it over the active box
        total += _declared(origins, tiles, lo, hi, 0.0, f"{path}: grid {names[index][0]!r}")[0].declared_bytes
    if budget is None:  # no budget given: what this machine can hold
        check_allocation(total, "cpu", f"{path}: its bricks (estimated from the tree topology)")
    elif total > budget:
        raise VolrenError(f"{path}: its bricks would take {total / 2**20:.3g} MiB (estimated from the tree topology: "
                          f"{total // BRICK_BYTES} bricks of {BRICK + 1}^3 float32), over the memory budget of "
                          f"{budget / 2**20:.3g} MiB; raise memory_budget (CLI: --memory-budget GIB)")


def index_box(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive index bounds (x, y, z) of every scalar grid's leaves and active tiles together, from the file's tree
    topology alone (no leaf is decompressed: milliseconds for a 30 MB frame): a box that holds whichever grid is read
    as the density, for placing the frames of a sequence whose active box moves or grows in their union
    (`volren.data.sequence`; issue 41 item 2)."""
    path = Path(path)
    data = _map(path)
    try:
        los, his = [], []
        for index, (name, *_, type_name) in enumerate(_grid_offsets(data)):
            dtype = _value_type(type_name)
            if dtype is None:
                continue
            origins, _, tiles = _leaf_origins(path, data, index, name, dtype)
            if len(origins) or len(tiles.origins):
                lo, hi = _leaves_box(origins, tiles)
                los.append(lo)
                his.append(hi)
    except (struct.error, VolrenError) as exc:
        raise VolrenError(f"{path}: not a readable OpenVDB file, truncated or corrupt ({exc})") from None
    finally:
        data.close()
    if not los:
        raise VolrenError(f"{path}: no scalar grid with active voxels")
    return np.min(los, axis=0), np.max(his, axis=0)


def read_vdb(path: str | Path, grid: str | None = None, emission_grid: str | None = None,
             box: tuple[np.ndarray, np.ndarray] | None = None, memory_budget: float | None = None
             ) -> tuple[VdbGrid, SparseGrid | None]:
    """The density grid (``grid``, see ``_find_grid``) over its active box, and ``emission_grid`` (e.g.
    ``temperature``, raw values) over the same index box, or None: bricks (`_brickify`). The emission grid must share
    the density grid's transform, so that voxel (i, j, k) of both is the same place. Given ``memory_budget``
    [bytes], their bricks must fit it, checked before any leaf is read (`_check_budget`); without it, the machine's
    free memory (not OME-Zarr's 1 GiB default, which picks a level: a .vdb has no coarser one to fall back to, and
    smoke of several GiB loads as before)."""
    if memory_budget is not None and not (np.isfinite(memory_budget) and memory_budget > 0):
        raise VolrenError(f"memory_budget must be a positive number of bytes, got {memory_budget!r} "
                          "(CLI: --memory-budget GIB)")
    path = Path(path)
    data = _map(path)
    try:
        wanted = [(grid, "grid")] + ([(emission_grid, "emission_grid")] if emission_grid is not None else [])
        _check_budget(path, data, wanted, box, None if memory_budget is None else float(memory_budget))
        vdb = _open(path)
    except BaseException:
        data.close()
        raise
    try:
        index = _find_grid(path, _grid_names(vdb), grid, "grid")
        density_grid = vdb.grid(index)
        to_world = _index_to_world(path, density_grid)
        leaves, origins, tiles, dtype = _leaves(path, data, vdb, index)
        lo, hi = _active_box(path, density_grid, origins, tiles)
        if box is not None:
            if np.any(np.asarray(box[0]) > lo) or np.any(np.asarray(box[1]) < hi):
                raise VolrenError(f"{path}: grid {density_grid.name!r}'s active box {lo.tolist()}..{hi.tolist()} "
                                  f"is not inside the box asked for, {box[0].tolist()}..{box[1].tolist()}")
            lo, hi = np.asarray(box[0], np.int64), np.asarray(box[1], np.int64)
        emission = None
        if emission_grid is not None:
            other_index = _find_grid(path, _grid_names(vdb), emission_grid, "emission_grid")
            other = vdb.grid(other_index)
            if not np.allclose(_index_to_world(path, other), to_world, rtol=1e-9, atol=0.0):
                raise VolrenError(f"{path}: grid {emission_grid!r} (emission_grid=, CLI: --emission-grid) has another "
                                  f"index-to-world transform than the density grid {density_grid.name!r}")
        _check_size(path, lo, hi)
        values = _brickify(leaves, origins, tiles, dtype, lo, hi, density_grid.float_background(),
                           f"{path}: grid {density_grid.name!r}")
        if emission_grid is not None:
            emission = _brickify(*_leaves(path, data, vdb, other_index), lo, hi, other.float_background(),
                                 f"{path}: grid {emission_grid!r} (emission_grid=, CLI: --emission-grid)")
            if not (np.isfinite(emission.min()) and np.isfinite(emission.max())):
                raise VolrenError(f"{path}: grid {emission_grid!r} (emission_grid=, CLI: --emission-grid) holds "
                                  "NaN/Inf values")
    finally:
        vdb.close()
        data.close()
    placed = to_world.copy()
    placed[:3, 3] = to_world[:3, :3] @ lo + to_world[:3, 3]  # dense index 0 is file index lo
    return VdbGrid(values, tuple(int(v) for v in lo), tuple(int(v) for v in hi), placed), emission


def read_vdb_grid_like(path: str | Path, name: str, like: str | None = None) -> SparseGrid:
    """Grid ``name`` of the file as float32 ``[z, y, x]`` bricks over the index box of the density grid ``like``
    (chosen as ``read_vdb`` does when None), so that it lines up voxel for voxel with ``load_volume``'s density."""
    _, emission = read_vdb(path, like, name)
    return emission

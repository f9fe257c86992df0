"""A bricked, sparse density grid on the host (issue 41): a page table over a grid of bricks of B^3 trilinear cells,
each resident brick stored in a pool with a one-voxel apron, (B+1)^3 voxels, so that the 8 corners of every cell lie
in one brick: a sample reads the same 8 values as the dense path (`volren.kernels.common.gather_cell`) and
interpolates them the same way, so it is bit-identical to it, with one page-table load more.

Page table: one int32 per brick, x fastest. An entry ``e >= 0`` is a resident brick, the ``e``-th (B+1)^3 block of the
pool; ``e < 0`` is a brick whose (B+1)^3 voxels all hold one value, ``constants[-1 - e]`` (OpenVDB tiles), with
``constants[0] = 0``, so ``EMPTY`` (-1) costs no pool memory and no pool load. Brick b covers cells [b B, b B + B)
and voxels [b B, b B + B] per axis; at the high border of a grid whose cell count is not a multiple of B the apron
repeats the last voxel (never read: `grid_cell` keeps cells below res - 1; it keeps a constant brick constant and the
grid's maximum the data's).

B is a power of two, so that the brick of a cell is a shift and its place in the brick a mask (no integer division
per sample). Offsets are int32, as the dense path's: a pool holds fewer than 2^31 voxels.

A `SparseGrid` stands wherever a volume's dense ``[z, y, x]`` array does (`volren.scene.Volume.density`): it has the
array's ``shape``, ``size``, ``dtype``, ``min`` and ``max``, and everything a renderer derives from the density
(empty-space skipping, culling, majorants, mip levels) is derived from its bricks (`brick_ranges`, `downsample`),
never from a dense copy. It is built from a dense array (`brick_dense`), from dense regions (`brick_regions`), or voxel
by voxel from a sparse source (`BrickBuilder`: OpenVDB leaves and tiles).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from volren.errors import VolrenError

BRICK = 16
"""[cells] edge B of the bricks volren stores densities in: the choice of docs/bench/bricks-decision.md (issue 41
item 1)"""
EMPTY = -1
"""page-table entry of a brick whose voxels are all 0 (``constants[0]``)"""
MAX_POOL_VOXELS = 2**31 - 1
MAX_DENSE_READ = 1 << 28
"""[voxels] the largest box `SparseGrid.read` returns (1 GiB of float32): a dense copy of a big sparse grid is the
thing bricks avoid"""


@dataclass(frozen=True, eq=False)
class SparseGrid:
    """A bricked grid on the host (module docstring)."""

    pool: np.ndarray
    """float32 (resident, B+1, B+1, B+1)"""
    table: np.ndarray
    """int32 (bricks z, bricks y, bricks x)"""
    constants: np.ndarray
    """float32; constants[0] = 0"""
    shape: tuple[int, int, int]
    """voxels (z, y, x) of the grid, as a dense array's shape"""
    brick: int
    """B: cells per brick edge"""
    peak: float | None = None
    """the largest density of the whole grid this one holds a part of (a data-parallel region's,
    `volren.dataparallel.region_grid`), which `max` reports; None: its own"""

    ndim = 3
    dtype = np.dtype(np.float32)

    def __repr__(self) -> str:
        return (f"SparseGrid({'x'.join(map(str, self.shape[::-1]))} voxels (x, y, z), {len(self.pool)} resident of "
                f"{self.table.size} bricks of {self.brick}^3, {self.nbytes / 2**20:.1f} MiB)")

    @property
    def size(self) -> int:
        """Voxels of the index box (as a dense array's ``size``), not the stored ones."""
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        return self.pool.nbytes + self.table.nbytes + self.constants.nbytes

    @property
    def edge(self) -> int:
        """B + 1: voxels per brick edge, apron included."""
        return self.brick + 1

    @cached_property
    def brick_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """Per brick (z, y, x) the min and max over its (B+1)^3 apron block: every trilinear sample in its cells
        lies between them (a constant brick: its value twice)."""
        values = self.constants[np.clip(-1 - self.table, 0, None)]
        lo, hi = values.copy(), values.copy()
        resident = self.table >= 0
        flat = self.pool.reshape(len(self.pool), self.edge**3)
        lo[resident] = flat.min(axis=1)[self.table[resident]] if len(flat) else 0.0
        hi[resident] = flat.max(axis=1)[self.table[resident]] if len(flat) else 0.0
        return lo, hi

    def max(self, axis: None = None, out: None = None) -> np.float32:
        """The largest voxel (``np.max(grid)`` calls this; only the whole grid's)."""
        return np.float32(self.brick_ranges[1].max() if self.peak is None else self.peak)

    def min(self, axis: None = None, out: None = None) -> np.float32:
        return np.float32(self.brick_ranges[0].min())

    def sum(self, dtype: np.dtype | type = np.float64) -> float:
        """The sum of the grid's voxels (as a dense copy's ``sum``), read in slabs of the index box: memory bounded
        by a slab, time by the box (a check of a reader, not a renderer's path)."""
        nz, ny, nx = self.shape
        step = max(1, (1 << 24) // (ny * nx))
        return float(sum(self.read((z, 0, 0), (min(z + step, nz), ny, nx)).sum(dtype=dtype)
                         for z in range(0, nz, step)))

    def stored_values(self) -> np.ndarray:
        """Every value the grid holds, flat: its resident bricks' voxels (aprons repeat their neighbours', so the set
        is the grid's, with repeats) and its constant bricks' values (for a range or a test of the values, not a
        histogram)."""
        used = np.unique(-1 - self.table[self.table < 0])
        return np.concatenate([self.pool.reshape(-1), self.constants[used]])

    def take(self, iz: np.ndarray, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
        """float32 ``[z, y, x]`` voxels at the outer product of the index arrays (clamped to the grid, as sampling
        clamps), gathered brick by brick: each voxel from the brick whose cells start at it (the grid's last voxel
        from the apron of the last brick)."""
        size = (len(iz), len(iy), len(ix))
        if int(np.prod(size, dtype=np.int64)) > MAX_DENSE_READ:
            raise VolrenError(f"cannot read a box of {list(size)} voxels from a sparse grid (at most {MAX_DENSE_READ})")
        out = np.empty(size, np.float32)
        per_axis = []
        for idx, n, count in zip((iz, iy, ix), self.shape, self.table.shape, strict=True):
            idx = np.clip(np.asarray(idx, np.int64), 0, n - 1)
            b = np.minimum(idx // self.brick, count - 1)
            per_axis.append([(int(c), np.flatnonzero(b == c), idx[b == c] - c * self.brick) for c in np.unique(b)])
        for cz, dz, pz in per_axis[0]:
            for cy, dy, py in per_axis[1]:
                for cx, dx, px in per_axis[2]:
                    e = int(self.table[cz, cy, cx])
                    out[np.ix_(dz, dy, dx)] = self.pool[e][np.ix_(pz, py, px)] if e >= 0 else self.constants[-1 - e]
        return out

    def read(self, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> np.ndarray:
        """float32 ``[z, y, x]`` voxels of the box [lo, hi) (z, y, x), indices clamped to the grid (`take`)."""
        if any(h <= low for low, h in zip(lo, hi, strict=True)):
            raise VolrenError(f"cannot read the empty box {lo}..{hi} from a sparse grid")
        return self.take(*(np.arange(low, h) for low, h in zip(lo, hi, strict=True)))

    def __getitem__(self, key: tuple[slice, slice, slice]) -> np.ndarray:
        """``grid[::s, ::s, ::s]`` (and any three slices) as a dense array, as numpy slices a dense grid: the
        strided reads of the code that looks at a grid's values (Otsu's threshold, the flame's brightness)."""
        if not (isinstance(key, tuple) and len(key) == 3 and all(isinstance(k, slice) for k in key)):
            raise TypeError(f"a SparseGrid takes three slices, got {key!r}")
        return self.take(*(np.arange(*k.indices(n)) for k, n in zip(key, self.shape, strict=True)))

    def cell_max(self, cell: int) -> np.ndarray:
        """Per cell of ``cell``^3 voxels (a power of two dividing B; ceil(n / cell) per axis, z, y, x) a bound on
        every trilinear sample in it and up to half a voxel beyond: the max over its voxels and the one after each
        (from the brick's block and its apron), then over the cell before along each axis (which holds the voxel
        before). The rule of `volren.upload.skip_grid` at a finer cell than `cell_ranges`' bricks, from the bricks."""
        b, e = self.brick, self.brick + 1
        if cell < 1 or cell & (cell - 1) or b % cell:
            raise VolrenError(f"a sparse grid's cells must divide its bricks of {b}: got {cell}")
        per = b // cell
        counts = np.array(self.table.shape)
        out = np.zeros(tuple(counts * per), np.float32)
        const = self.constants[np.clip(-1 - self.table, 0, None)]
        const[self.table >= 0] = 0.0
        out[...] = np.repeat(np.repeat(np.repeat(const, per, 0), per, 1), per, 2)
        resident = np.argwhere(self.table >= 0)
        for start in range(0, len(resident), 4096):  # the pool in chunks: a working set of 4096 bricks
            chunk = resident[start : start + 4096]
            m = self.pool[self.table[tuple(chunk.T)]]
            for axis in (1, 2, 3):  # [c j, c j + c] per axis: the blocks of c, then the plane after each
                lead = (slice(None),) * axis
                blocks = m[(*lead, slice(0, b))].reshape(*m.shape[:axis], per, cell, *m.shape[axis + 1:])
                m = np.maximum(blocks.max(axis=axis + 1), m[(*lead, slice(cell, e, cell))])
            zz, yy, xx = (chunk[:, a, None] * per + np.arange(per)[None] for a in range(3))
            out[zz[:, :, None, None], yy[:, None, :, None], xx[:, None, None, :]] = m
        out = _with_the_cell_before(out, np.maximum)  # the cell before holds the voxel before
        # cells past the grid's last voxel: ceil(n / cell) of them per axis; the last voxel's own cell may be one
        # past the bricks' (n - 1 a multiple of B): it repeats the last
        want = [-(-n // cell) for n in self.shape]
        pad = [(0, max(w - s, 0)) for w, s in zip(want, out.shape, strict=True)]
        out = np.pad(out, pad, mode="edge") if any(p for _, p in pad) else out
        return out[: want[0], : want[1], : want[2]]

    def map(self, op) -> SparseGrid:
        """The grid with ``op`` (a float32 array -> array, element-wise, e.g. a normalisation) applied to every voxel:
        to the pool and the constants, so the bricks and page table stay (an EMPTY brick must stay 0: op(0) = 0)."""
        constants = np.asarray(op(self.constants), np.float32)
        if constants[0] != 0:
            raise VolrenError("SparseGrid.map: the operation must keep 0 at 0 (empty bricks stay empty)")
        return SparseGrid(pool=np.asarray(op(self.pool), np.float32), table=self.table, constants=constants,
                          shape=self.shape, brick=self.brick)

    def cell_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """Per cell of B^3 voxels (ceil(n / B) per axis, z, y, x) the min and max of every trilinear sample in it and
        up to half a voxel beyond (its voxels and a one-voxel border: the rule of `volren.scene.Volume.max_pyramid`
        and of the majorants' macrocells): a brick's range covers voxels [c B, c B + B], and the voxel before is in
        the brick before, so each range meets its lower neighbours' along each axis. The last cell of an axis whose
        last voxel is an apron's (n - 1 a multiple of B) repeats its brick's range. Read from the page table and the
        pool's blocks, never a dense copy."""
        out = []
        for rng, op in zip(self.brick_ranges, (np.minimum, np.maximum), strict=True):
            rng = _with_the_cell_before(rng, op)
            for axis in range(3):
                cells = -(-self.shape[axis] // self.brick)
                if cells > rng.shape[axis]:
                    rng = np.concatenate([rng, np.take(rng, [-1], axis)], axis)
            out.append(rng.astype(np.float32))
        return out[0], out[1]

    def to_dense(self) -> np.ndarray:
        """The whole grid as a dense array (for tests and small grids; `read` refuses big ones)."""
        return self.read((0, 0, 0), self.shape)

    def downsample(self) -> SparseGrid:
        """The next mip level: every axis longer than 1 halved by a 2x2x2 mean, an odd axis repeating its last voxel
        (`volren.scene.Volume.mip_pyramid`'s rule), built brick by brick from the bricks under each coarse brick
        (no dense copy): a coarse brick is stored only where a brick under it (or under its apron) is not EMPTY."""
        shape = tuple(max(-(-n // 2), 1) if n > 1 else 1 for n in self.shape)
        if min(shape) < 2:
            raise VolrenError(f"a sparse grid of {self.shape} voxels has no coarser level with a trilinear cell")
        builder = BrickBuilder(shape, self.brick)
        b = self.brick
        occupied = np.argwhere(self.table != EMPTY)
        # coarse brick c covers fine voxels [2 c B, 2 c B + 2 B]: fine bricks 2c - ... 2c + 2 (with the apron's)
        shifts = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)])
        coarse = np.unique(np.maximum(occupied[:, None, :] - shifts[None], 0).reshape(-1, 3) // 2, axis=0)
        coarse = coarse[np.all(coarse < builder.counts, axis=1)]
        for c in coarse:
            first = 2 * c * b
            block = self.read(tuple(first), tuple(first + 2 * b + 2))
            # level-1 voxel j: mean of fine voxels 2j and 2j + 1, clamped to the fine grid (read clamps)
            pairs = [slice(0, 2 * b + 2, 2), slice(1, 2 * b + 2, 2)]
            mean = sum(block[z, y, x] for z in pairs for y in pairs for x in pairs) / np.float32(8)
            builder.put(tuple(c), mean.astype(np.float32))
        return builder.build()


def _with_the_cell_before(cells: np.ndarray, op: np.ufunc) -> np.ndarray:
    """``op`` (np.minimum, np.maximum) of each cell and the cell before it along each axis (the first its own),
    separably: every cell then also bounds the voxel just before it (a trilinear sample's lower neighbour)."""
    for axis in range(3):
        before = np.concatenate([np.take(cells, [0], axis), np.take(cells, range(cells.shape[axis] - 1), axis)], axis)
        cells = op(cells, before)
    return cells


def apron_reduce(padded: np.ndarray, brick: int, op: np.ufunc) -> np.ndarray:
    """``op`` (np.minimum, np.maximum) over each brick's apron block of a grid of c B + 1 voxels per axis, one axis at
    a time (a box reduction is separable): along each axis the B-voxel blocks reduce through a reshape (a view), then
    meet the apron plane at the next multiple of B. Reducing the strided (B+1)^3 views directly was 14x slower
    (0.18 s against 0.013 s for a 257^3 grid at B = 8)."""
    out = padded
    for axis in (0, 1, 2):  # z first: its blocks are whole slabs; x, where a block is B floats, comes last, B^2 smaller
        count = (out.shape[axis] - 1) // brick
        lead = (slice(None),) * axis
        blocks = out[(*lead, slice(0, count * brick))].reshape(*out.shape[:axis], count, brick, *out.shape[axis + 1:])
        out = op(op.reduce(blocks, axis=axis + 1), out[(*lead, slice(brick, None, brick))])
    return out


def brick_counts(shape: tuple[int, ...], brick: int) -> tuple[int, int, int]:
    """Bricks per axis (z, y, x) of a grid of ``shape`` voxels: its cells (n - 1) / B, rounded up."""
    if brick < 2 or brick & (brick - 1):
        raise VolrenError(f"brick size must be a power of two >= 2, got {brick}")
    if len(shape) != 3 or min(shape) < 2:
        raise VolrenError(f"bricks need a 3-D grid of at least 2 voxels per axis, got shape {tuple(shape)}")
    return tuple(-(-(n - 1) // brick) for n in shape)


def brick_dense(grid: np.ndarray, brick: int) -> SparseGrid:
    """Brick a dense [z, y, x] grid into bricks of ``brick``^3 cells (a power of two) with a one-voxel apron: a brick
    whose apron block holds one value becomes a constant (`EMPTY` for 0), the others go into the pool in brick order."""
    if grid.ndim != 3:
        raise VolrenError(f"bricks need a 3-D grid, got shape {grid.shape}")
    return brick_regions(grid.shape, [((0, 0, 0), grid)], brick)


def _finish(table: np.ndarray, pools: list[np.ndarray], kinds: list, values: list[np.ndarray], shape, brick: int,
            ) -> SparseGrid:
    """The grid from per group the constant bricks' ``values`` and the resident ``pools``, written into ``table`` at
    ``kinds`` ((where, constant mask) per group): constants deduplicated, pool slots in group order."""
    e = brick + 1
    others = np.unique(np.concatenate([np.zeros(0, np.float32), *values]))
    others = others[others != 0.0]
    constants = np.concatenate([np.zeros(1, np.float32), others]).astype(np.float32)
    resident = sum(len(p) for p in pools)
    if resident * e**3 > MAX_POOL_VOXELS:
        raise VolrenError(f"{resident} resident bricks of {e}^3 voxels exceed the int32 pool offsets")
    start = 0
    for (where, constant), value, pool in zip(kinds, values, pools, strict=True):
        entries = np.empty(constant.shape, dtype=np.int32)
        entries[constant] = -1 - np.where(value != 0.0, np.searchsorted(others, value) + 1, 0)
        entries[~constant] = np.arange(start, start + len(pool), dtype=np.int32)
        table[where] = entries
        start += len(pool)
    pool = pools[0] if len(pools) == 1 else np.concatenate(pools) if pools else np.zeros((0, e, e, e), np.float32)
    return SparseGrid(pool=pool, table=table, constants=constants, shape=tuple(int(n) for n in shape), brick=brick)


def brick_regions(shape: tuple[int, ...], regions: list[tuple[tuple[int, int, int], np.ndarray]],
                  brick: int) -> SparseGrid:
    """Brick a grid of ``shape`` voxels (z, y, x) that is 0 outside ``regions`` (each its first voxel (z, y, x) and
    a dense block) without a dense copy of the grid: each region is widened to the apron blocks it touches and
    bricked alone. Regions must not share a brick. Beyond the grid's high border the apron repeats the last voxel."""
    counts = brick_counts(shape, brick)
    table = np.full(counts, EMPTY, dtype=np.int32)
    claimed = np.zeros(counts, dtype=bool)
    e = brick + 1
    values, pools, kinds = [], [], []  # per region: constant bricks' values, resident blocks, and where they go
    for origin, block in regions:
        block = np.asarray(block, dtype=np.float32)
        # bricks b whose apron voxels [b B, b B + B] meet the region's [o, o + size - 1], per axis
        first = [max(-(-o // brick) - 1, 0) for o in origin]
        last = [min((o + m - 1) // brick, c - 1) for o, m, c in zip(origin, block.shape, counts, strict=True)]
        if any(f > lst for f, lst in zip(first, last, strict=True)):
            continue
        where = tuple(slice(f, lst + 1) for f, lst in zip(first, last, strict=True))
        if claimed[where].any():
            raise VolrenError("regions share a brick: merge them")
        claimed[where] = True
        # the widened region on the voxel grid, [first B, (last + 1) B], edge-padded past the grid
        lo_v = [f * brick for f in first]
        size = [(lst + 1 - f) * brick + 1 for f, lst in zip(first, last, strict=True)]
        inside = [min(s, n - v) for s, n, v in zip(size, shape, lo_v, strict=True)]
        local = np.zeros(inside, dtype=np.float32)
        src = tuple(slice(max(v - o, 0), min(v + s - o, m))
                    for v, s, o, m in zip(lo_v, inside, origin, block.shape, strict=True))
        dst = tuple(slice(max(o - v, 0), max(o - v, 0) + (sl.stop - sl.start))
                    for v, o, sl in zip(lo_v, origin, src, strict=True))
        local[dst] = block[src]
        pad = [(0, s - i) for s, i in zip(size, inside, strict=True)]
        padded = np.pad(local, pad, mode="edge") if any(p for _, p in pad) else local
        lo, hi = apron_reduce(padded, brick, np.minimum), apron_reduce(padded, brick, np.maximum)
        constant = lo == hi
        st = padded.strides
        # every brick's (B+1)^3 apron block as a view: neighbouring blocks share their faces
        blocks = np.lib.stride_tricks.as_strided(padded, shape=(*lo.shape, e, e, e), writeable=False,
                                                 strides=(st[0] * brick, st[1] * brick, st[2] * brick, *st))
        values.append(lo[constant])
        pools.append(blocks[np.nonzero(~constant)])
        kinds.append((where, constant))
    return _finish(table, pools, kinds, values, shape, brick)


class BrickBuilder:
    """A `SparseGrid` written voxel by voxel, for sources that are sparse themselves (OpenVDB leaves and tiles, a
    coarser mip level): declare the bricks data will touch (`touch`), write voxels (`scatter`, each voxel into every
    brick whose apron block holds it), constant boxes (`fill`) and whole apron blocks (`put`), then `build`: bricks
    whose block holds one value become constants, the rest the pool, and untouched bricks read ``background``.
    Memory: the touched bricks' blocks, once; no dense copy of the grid."""

    def __init__(self, shape: tuple[int, ...], brick: int, background: float = 0.0) -> None:
        self.shape = tuple(int(n) for n in shape)
        self.brick = brick
        self.counts = np.array(brick_counts(self.shape, brick))
        self.background = np.float32(background)
        self._keys = np.zeros(0, np.int64)
        self._pool: np.ndarray | None = None
        self._boxes: list[tuple[np.ndarray, np.ndarray, float]] = []
        """constant boxes whose bricks lie wholly inside them: (first brick, last brick + 1, value)"""
        self._put: dict[tuple[int, int, int], np.ndarray] = {}
        self._constant_bricks: list[tuple[np.ndarray, np.ndarray]] = []
        """bricks (K, 3) found constant without a block, and their values"""
        self._tile_boxes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        """the `tiles` boxes, written into the declared bricks at `build`"""

    def _key(self, c: np.ndarray) -> np.ndarray:
        return (c[..., 0] * self.counts[1] + c[..., 1]) * self.counts[2] + c[..., 2]

    def touched(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per axis the first and last brick (inclusive, clipped to the grid) whose apron voxels [c B, c B + B] meet
        the voxel box [lo, hi] (inclusive): c from ceil(lo / B) - 1 to floor(hi / B)."""
        b = self.brick
        first = np.maximum(-(-np.asarray(lo) // b) - 1, 0)
        last = np.minimum(np.asarray(hi) // b, self.counts - 1)
        return first, last

    def touch(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Declare that data will be written into the voxel boxes [lo, hi] (inclusive; (N, 3) z, y, x): the bricks
        they meet get a block (allocated at the first write, filled with the background). Call before writing."""
        if self._pool is not None:
            raise VolrenError("BrickBuilder: touch every box before the first write")
        first, last = self.touched(np.atleast_2d(lo), np.atleast_2d(hi))
        span = last - first + 1
        keep = np.all(span > 0, axis=1)
        first, span = first[keep], span[keep]
        keys = [self._keys]
        for extent in np.unique(span, axis=0):  # boxes of one size (leaves: few sizes) enumerate at once
            group = first[np.all(span == extent, axis=1)]
            offsets = np.stack(np.meshgrid(*[np.arange(n) for n in extent], indexing="ij"), -1).reshape(-1, 3)
            keys.append(self._key(group[:, None, :] + offsets[None]).reshape(-1))
        self._keys = np.unique(np.concatenate(keys))

    def _blocks(self) -> np.ndarray:
        if self._pool is None:
            e = self.brick + 1
            self._pool = np.full((len(self._keys), e, e, e), self.background, np.float32)
        return self._pool

    def scatter(self, voxels: np.ndarray, values: np.ndarray) -> None:
        """Write ``values`` at ``voxels`` ((N, 3) int, z, y, x) into every touched brick whose apron block holds each:
        the brick whose cells start there, and on a plane that is a multiple of B also the bricks before it along
        those axes (their apron). A voxel outside the grid falls in no brick (below) or only where `build` repeats
        the border (above): dropped. Per axis on flat int32 arrays, the apron copies only for the voxels on a
        brick's first plane (3/B of them): 8 passes over (N, 3) arrays took 3.3 s of a 3.4 s load of 3.5 M voxels."""
        pool = self._blocks()
        flat = pool.reshape(len(pool), (self.brick + 1) ** 3)
        values = np.asarray(values, np.float32)
        shift, mask = self.brick.bit_length() - 1, self.brick - 1
        v = [np.ascontiguousarray(voxels[:, a], dtype=np.int64) for a in range(3)]
        keep = (v[0] >= 0) & (v[1] >= 0) & (v[2] >= 0)
        c = [(w >> shift)[keep] for w in v]
        r = [(w & mask)[keep] for w in v]
        values = values[keep]
        inside = (c[0] < self.counts[0]) & (c[1] < self.counts[1]) & (c[2] < self.counts[2])
        self._write_voxels([a[inside] for a in c], [a[inside] for a in r], values[inside])
        first = [(ra == 0) & (ca >= 1) for ra, ca in zip(r, c, strict=True)]  # on a brick's first plane, per axis
        on = np.flatnonzero(first[0] | first[1] | first[2])
        c, r, first, values = [a[on] for a in c], [a[on] for a in r], [f[on] for f in first], values[on]
        for sub in range(1, 8):  # bit a set: the copy in the apron of the brick before along axis a
            axes = [(sub >> (2 - a)) & 1 for a in range(3)]
            sel = np.ones(len(on), bool)
            for a in range(3):
                if axes[a]:
                    sel &= first[a]
            cs = [c[a][sel] - axes[a] for a in range(3)]
            sel_inside = (cs[0] < self.counts[0]) & (cs[1] < self.counts[1]) & (cs[2] < self.counts[2])
            rs = [np.full(int(sel.sum()), self.brick) if axes[a] else r[a][sel] for a in range(3)]
            self._write_voxels([x[sel_inside] for x in cs], [x[sel_inside] for x in rs], values[sel][sel_inside])
        del flat

    def _write_voxels(self, c: list[np.ndarray], r: list[np.ndarray], values: np.ndarray) -> None:
        """Voxels at place ``r`` (z, y, x arrays) of the bricks ``c`` (z, y, x arrays, all touched)."""
        if not len(values):
            return
        e = self.brick + 1
        keys = (c[0] * self.counts[1] + c[1]) * self.counts[2] + c[2]
        slots = np.searchsorted(self._keys, keys)
        if slots.max() >= len(self._keys) or np.any(self._keys[slots] != keys):
            raise VolrenError("BrickBuilder: a write outside the touched bricks")
        self._pool.reshape(len(self._pool), e**3)[slots, (r[0] * e + r[1]) * e + r[2]] = values

    def tiles(self, lo: np.ndarray, hi: np.ndarray, values: np.ndarray) -> None:
        """Constant boxes of voxels [lo, hi] (inclusive, (T, 3) z, y, x; OpenVDB's 128^3 and 4096^3 tiles, which do
        not overlap), declared before any other `touch`: a brick whose apron block lies inside one box, or inside
        boxes of one value together (tiles side by side), is a constant and takes no pool memory; only the bricks on
        their outer border are declared, and `build` writes the boxes into them (a 4096^3 root tile: 390 K of its
        16.7 M bricks, and none where tiles of its value surround it)."""
        lo = np.maximum(np.atleast_2d(lo), 0)
        hi = np.minimum(np.atleast_2d(hi), np.array(self.shape) - 1)
        values = np.asarray(values, np.float32).reshape(-1)
        live = np.all(hi >= lo, axis=1)
        lo, hi, values = lo[live], hi[live], values[live]
        b, top = self.brick, np.array(self.shape) - 1
        border = []
        for t in range(len(lo)):
            first, last = self.touched(lo[t], hi[t])
            # inner bricks: apron block [c B, c B + B] within the box, or past the grid's border (edge repeats)
            inner_first = -(-lo[t] // b)
            inner_last = np.where(hi[t] >= top, last, (hi[t] - b) // b)
            if np.all(inner_last >= inner_first):
                self._boxes.append((inner_first, inner_last + 1, float(values[t])))
            for axis in range(3):  # the slabs below and above the inner range along each axis
                for a, z in ((first[axis], min(inner_first[axis] - 1, last[axis])),
                             (max(inner_last[axis] + 1, first[axis]), last[axis])):
                    if a <= z:
                        f, e = first.copy(), last.copy()
                        f[axis], e[axis] = a, z
                        grid = np.meshgrid(*[np.arange(i, j + 1) for i, j in zip(f, e, strict=True)], indexing="ij")
                        border.append(np.stack(grid, -1).reshape(-1, 3))
        if not border:
            return
        coords = np.unique(np.concatenate(border), axis=0)
        # a border brick wholly covered by boxes of one value is a constant: voxels of its apron block (clipped to
        # the grid, as the edge repeats) that each value's boxes cover
        blo, bhi = coords * b, np.minimum(coords * b + b, top)
        need = np.prod(bhi - blo + 1, axis=1)
        covered = np.zeros(len(coords), bool)
        for v in np.unique(values):
            got = np.zeros(len(coords), np.int64)
            for t in np.flatnonzero(values == v):
                got += np.prod(np.clip(np.minimum(bhi, hi[t]) - np.maximum(blo, lo[t]) + 1, 0, None), axis=1)
            full = got == need
            if full.any():
                self._constant_bricks.append((coords[full], np.full(full.sum(), v, np.float32)))
            covered |= full
        self._tile_boxes = (lo, hi, values)
        self._keys = np.unique(np.concatenate([self._keys, self._key(coords[~covered])]))

    def touch_bricks(self, first: np.ndarray, last: np.ndarray) -> None:
        """Declare the bricks first..last (inclusive, z, y, x)."""
        if self._pool is not None:
            raise VolrenError("BrickBuilder: touch every box before the first write")
        c = np.stack(np.meshgrid(*[np.arange(f, t + 1) for f, t in zip(first, last, strict=True)], indexing="ij"), -1)
        self._keys = np.unique(np.concatenate([self._keys, self._key(c.reshape(-1, 3))]))

    def fill(self, lo: np.ndarray, hi: np.ndarray, value: float) -> None:
        """Write a constant box of voxels [lo, hi] (inclusive, z, y, x) into the declared bricks it meets (`tiles`
        declares a tile's border bricks and writes its inner ones as constants)."""
        lo, hi = np.maximum(np.asarray(lo), 0), np.minimum(np.asarray(hi), np.array(self.shape) - 1)
        if np.any(hi < lo):
            return
        b = self.brick
        pool = self._blocks()
        first, last = self.touched(lo, hi)
        coords = np.stack(np.unravel_index(self._keys, tuple(self.counts)), -1)
        # the declared bricks the box meets (`tiles` declares only its border ones)
        for slot in np.flatnonzero(np.all((coords >= first) & (coords <= last), axis=1)):
            c = coords[slot]
            a = np.maximum(lo - c * b, 0)
            z = np.minimum(hi - c * b, b) + 1
            pool[slot, a[0]:z[0], a[1]:z[1], a[2]:z[2]] = value

    def put(self, c: tuple[int, int, int], block: np.ndarray) -> None:
        """Brick ``c``'s whole (B+1)^3 apron block (declared now: `put` needs no `touch`)."""
        if self._pool is not None or len(self._keys):
            raise VolrenError("BrickBuilder: put whole blocks or scatter voxels, not both")
        self._put[tuple(int(v) for v in c)] = block

    @property
    def declared_bytes(self) -> int:
        """[bytes] the pool of the bricks declared so far takes at the first write: (B+1)^3 float32 each."""
        return len(self._keys) * (self.brick + 1) ** 3 * 4

    def build(self) -> SparseGrid:
        b, e = self.brick, self.brick + 1
        if self._tile_boxes is not None:
            for lo, hi, value in zip(*self._tile_boxes, strict=True):
                self.fill(lo, hi, float(value))
        if self._put:
            keys = self._key(np.array(list(self._put), np.int64).reshape(-1, 3))
            order = np.argsort(keys)
            self._keys = keys[order]
            blocks = list(self._put.values())
            self._pool = np.stack([blocks[i] for i in order]).astype(np.float32, copy=False)
            self._put = {}
        pool = self._blocks()
        coords = np.stack(np.unravel_index(self._keys, tuple(self.counts)), -1)
        for axis in range(3):  # past the high border the apron repeats the grid's last voxel
            limit = self.shape[axis] - (self.counts[axis] - 1) * b  # voxels of the last brick inside the grid
            if limit < e:
                last = np.flatnonzero(coords[:, axis] == self.counts[axis] - 1)
                view = np.moveaxis(pool, axis + 1, 1)
                view[last, limit:] = view[last, limit - 1 : limit]
        table = np.full(tuple(self.counts), EMPTY, np.int32)
        values, kinds, pools = [], [], []
        for first, stop, value in self._boxes:
            where = tuple(slice(f, s) for f, s in zip(first, stop, strict=True))
            constant = np.ones(tuple(stop - first), bool)
            values.append(np.full(constant.sum(), value, np.float32))
            kinds.append((where, constant))
            pools.append(np.zeros((0, e, e, e), np.float32))
        for c, value in self._constant_bricks:
            values.append(value)
            kinds.append((tuple(c.T), np.ones(len(c), bool)))
            pools.append(np.zeros((0, e, e, e), np.float32))
        if self.background != 0:
            whole = tuple(slice(0, n) for n in self.counts)
            values.insert(0, np.full(table.size, self.background, np.float32))
            kinds.insert(0, (whole, np.ones(table.shape, bool)))
            pools.insert(0, np.zeros((0, e, e, e), np.float32))
        flat = pool.reshape(len(pool), (self.brick + 1) ** 3)
        lo, hi = flat.min(axis=1, initial=np.inf), flat.max(axis=1, initial=-np.inf)
        constant = lo == hi
        resident = np.flatnonzero(~constant)
        # the resident blocks moved to the front in place, chunk by chunk (slots only decrease), then the pool shrunk
        # in place (a view of its front would keep the constant bricks' blocks alive: 49 MiB for 29 MiB resident)
        for start in range(0, len(resident), 4096):
            chunk = resident[start : start + 4096]
            pool[start : start + len(chunk)] = pool[chunk]
        del flat
        self._pool = None
        pool.resize((len(resident), e, e, e), refcheck=False)  # nothing else refers to it
        where = tuple(coords.T)
        values.append(lo[constant])
        kinds.append((where, constant))
        pools.append(pool)
        self._pool = None
        return _finish(table, pools, kinds, values, self.shape, b)

"""Upload a `Scene` and `Camera`s to a Warp device: packed density grids, per-volume structs, lights.

Several volumes of different resolutions share one flat density array (each ``VolumeGPU`` holds its offset), so a
kernel can walk every volume of the scene in one launch. Densities are uploaded as bricks (issue 41 item 1): each
level's brick pool and constant-brick values go into the density array, its page table into one packed int32 table
(`volren.kernels.bricks`, `volren.kernels.common.gather_density`). After every density level the density array
holds each fire volume's emission grid and blackbody table (`pack_emission`), dense: every kernel that reads
densities can then read them too.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import check_allocation
from volren.errors import VolrenError
from volren.kernels.common import (
    LIGHT_DIRECTIONAL,
    LIGHT_POINT,
    LIGHT_RECT,
    LIGHT_SPOT,
    NOT_RESIDENT,
    OPAQUE_PLANE,
    OPAQUE_SPHERE,
    STREAM_INTS,
    CameraGPU,
    LightGPU,
    Medium,
    OpaqueGPU,
    VolumeGPU,
)
from volren.scene import (
    SPOT_FALLOFFS,
    DirectionalLight,
    RectLight,
    Scene,
    Sphere,
    SpotLight,
    TriangleMesh,
    Volume,
    _downsample,
)
from volren.sparse import BRICK, SparseGrid, brick_dense

MAX_PACKED = 2**31 - 1
"""Kernels index the packed arrays with 32-bit ints."""
MAX_LIGHT_GRID = 1024


def opaque_structs(scene: Scene) -> list[OpaqueGPU]:
    """The analytic objects (spheres, planes); triangle meshes go to `wp.Mesh` BVHs instead."""
    out = []
    for o in scene.opaque:
        if isinstance(o, TriangleMesh):
            continue
        s = OpaqueGPU()
        if isinstance(o, Sphere):
            s.kind, s.position, s.radius = OPAQUE_SPHERE, wp.vec3(*o.center), o.radius
            s.normal = wp.vec3(0.0, 1.0, 0.0)
        else:
            s.kind, s.position, s.normal, s.radius = OPAQUE_PLANE, wp.vec3(*o.point), wp.vec3(*o.normal), 0.0
        s.albedo = wp.vec3(*o.albedo)
        out.append(s)
    return out


MIN_LIGHT_NODES = 8
"""A thin axis keeps this many light-map nodes (issue 47 item 1): the 16 x 2 x 1 m slab of 48 x 12 x 8 voxels had
4 nodes across its 8 (half its resolution), and linear interpolation across them missed the density's curvature:
DSSRM 1.024 of the reference; 8 nodes: 1.007."""


SPARSE_LIGHT_GRID = 256
"""[nodes] on the longest axis of a sparse grid's default light map: half its resolution would make a 2000^3 index
box's map 1000^3 nodes (8 GB per light), dense over the box where the density is not"""


def light_grid_resolution(res: tuple[int, int, int], light_grid: int | None, sparse: bool = False
                          ) -> tuple[int, int, int]:
    """Light-map nodes per axis (x, y, z; `volren.render.lightmap`): ``light_grid`` on the longest axis (aspect
    kept), or half the density resolution when None (the papers' 128^3 light grid for 256^3 density; for a
    ``sparse`` grid at most `SPARSE_LIGHT_GRID`), and on every
    axis at least `MIN_LIGHT_NODES` (or one per voxel where it has fewer, and never more than ``light_grid``) and 2
    (the two faces)."""
    if light_grid is not None and not 2 <= light_grid <= MAX_LIGHT_GRID:
        raise VolrenError(f"light grid resolution must lie in [2, {MAX_LIGHT_GRID}], got {light_grid}")
    longest = max(res)
    if light_grid is None and sparse and longest > 2 * SPARSE_LIGHT_GRID:
        light_grid = SPARSE_LIGHT_GRID
    wanted = [(n + 1) // 2 if light_grid is None else round(n * light_grid / longest) for n in res]
    floor = MIN_LIGHT_NODES if light_grid is None else min(light_grid, MIN_LIGHT_NODES)
    return tuple(max(2, min(n, floor), w) for n, w in zip(res, wanted, strict=True))


def _mat44(m: np.ndarray) -> wp.mat44:
    return wp.mat44(*np.asarray(m, dtype=np.float32).reshape(-1))


def camera_struct(cam: Camera) -> CameraGPU:
    right, up, forward = cam.basis()
    s = CameraGPU()
    s.origin = wp.vec3(*cam.position)
    s.right = wp.vec3(*right)
    s.up = wp.vec3(*up)
    s.forward = wp.vec3(*forward)
    s.tan_half_fov = cam.tan_half_fov
    s.aspect = cam.width / cam.height
    s.width = cam.width
    s.height = cam.height
    s.near = cam.near
    s.far = cam.far
    return s


BrickKey = tuple[int, int, int, int]
"""(level, bz, by, bx) of a streamed brick"""


@dataclass
class StreamState:
    """One streamed volume's device pool and page tables (`volren.upload.pack_stream`)."""

    volume: int
    """its index in the scene"""
    density: Any
    """its `volren.stream.density.StreamedDensity`"""
    pool_offset: int
    """first float of its pool in the packed density array"""
    capacity: int
    """brick slots in the pool"""
    table_offset: int
    """first entry of its level tables (level 0 first) in the packed table array"""
    level_starts: list[int]
    """per level, its table's first entry relative to ``table_offset``"""
    tables: np.ndarray
    """the host copy of every level's table, written to the device when it changes"""
    slots: OrderedDict[BrickKey, int] = field(default_factory=OrderedDict)
    """brick -> slot, least recently wanted first"""
    empty: set[BrickKey] = field(default_factory=set)
    """resident bricks whose voxels are all 0: `EMPTY`, no slot"""
    maxima: dict[BrickKey, float] = field(default_factory=dict)
    """the largest density of each brick placed in the pool (`volren.render.stream_bounds`)"""
    skips: list[int] = field(default_factory=list)
    """per uploaded level (0 and, for the cube-map methods, each coarser), its skip grid's offset in
    ``DeviceScene.max_density``"""
    cull: int | None = None
    """the offset of its culling level in ``DeviceScene.max_density`` (uploaded with mip levels), else None"""
    bounds: list[np.ndarray] = field(default_factory=list)
    """per level, the bounds of the densities its bricks draw now (`volren.render.stream_bounds.drawn_bounds`)"""


@dataclass
class DeviceScene:
    """A scene's data on one device, plus its light-map storage (filled by the light-map pass)."""

    scene: Scene
    device: str
    density: wp.array
    """packed floats: per volume and level its brick pool and constant-brick values (or its dense grid), then the
    emission grids and blackbody tables"""
    volumes: wp.array
    lights: wp.array
    light_res: list[tuple[int, int, int]]
    lightmap: wp.array
    ambient: wp.vec3
    """the environment's mean radiance: the constant ambient without GI"""
    volume_bvh: wp.Bvh
    """BVH over the volumes' world boxes, for marches that cross every volume (GI, cross-volume shadows)"""
    opaque: wp.array
    """the scene's opaque spheres and planes (`OpaqueGPU`)"""
    meshes: list[wp.Mesh]
    """the scene's triangle meshes with their BVHs (kept alive here; kernels see ``mesh_ids``). One BVH per mesh, not
    one merged per scene: measured on the fog scenes (16 viewers, 192x108, CPU), a merged SAH BVH made shadow rays
    and primary rays 10-40% slower, as a few large triangles (floors, walls) overlap every subtree of a merged
    tree."""
    mesh_ids: wp.array
    mesh_albedo: wp.array
    max_density: wp.array
    """packed conservative max-density cells: per volume one coarse level of its max-density pyramid (for
    empty-tile culling, with ``mip_levels``), then per volume and uploaded mip level its `skip_grid` (for empty-space
    skipping; each `VolumeGPU` holds its ``skip_offset``)"""
    max_grids: list[tuple[int, tuple[int, int, int]]]
    """per volume (offset into ``max_density``, resolution (x, y, z)) of its culling level"""
    levels: list[list[VolumeGPU]]
    """per volume, its struct at each uploaded mip level (level 0 only unless uploaded with ``mip_levels``);
    levels differ only in where their density lies (``offset``, ``res``, their bricks): same box, material and
    light map"""
    ambient_grid: wp.array
    """packed per-voxel ambient radiance (vec3) of the GI passes (`volren.render.gi.ambient`); read only when ``gi``"""
    table: wp.array | None = None
    """packed int32 brick page tables of every bricked volume and level (each `VolumeGPU` holds its ``table``
    slice: ``table_offset``, ``bricks``)"""
    pool_bytes: int = 0
    """[bytes] resident bricks of every volume and level in ``density`` (apron included): what density costs
    beyond the page tables and constants; 0 for dense uploads"""
    active_bricks: int = 0
    """resident (non-constant) bricks of every volume and level; empty and constant bricks hold no pool memory"""
    streams: list[StreamState] = field(default_factory=list)
    """the streamed volumes' device pools and page tables (`volren.render.streaming`), filled frame by frame"""
    stream_generation: int = 0
    """changes of the streamed volumes' device bricks so far: what derives from the densities (the light map) is
    recomputed when it moves"""
    gi: bool = False
    skip_empty: bool = True
    """marches skip steps in empty max-density cells (set from the renderer's config each frame)"""

    def medium(self) -> Medium:
        m = Medium()
        m.density, m.lightmap, m.lights = self.density, self.lightmap, self.lights
        m.ambient, m.gi = self.ambient_grid, int(self.gi)
        m.max_density, m.skip = self.max_density, int(self.skip_empty)
        return m

    @property
    def light_voxels(self) -> list[int]:
        """Voxels of each volume's light (and ambient) grid."""
        return [int(np.prod(r)) for r in self.light_res]

    @property
    def volume_count(self) -> int:
        return len(self.scene.volumes)

    @property
    def light_count(self) -> int:
        return len(self.scene.lights)


CULL_GRID = 16
"""Empty-tile culling reads the max-density pyramid level with at most this many cells per axis."""


def coarse_max_level(vol: Volume) -> np.ndarray:
    """The finest max-pyramid level with at most CULL_GRID cells on every axis (a sparse grid's from its bricks'
    `SparseGrid.cell_ranges`, the pyramid's level log2 B, max-pooled on; a streamed volume's from the bounds of
    what its bricks draw, written frame by frame by `volren.render.stream_bounds`: every cell occupied until then)."""
    if getattr(vol.density, "streamed", False):
        return cull_level(skip_grid(vol.density)[0])
    if isinstance(vol.density, SparseGrid):
        return cull_level(vol.density.cell_ranges()[1])
    for level in vol.max_pyramid:
        if max(level.shape) <= CULL_GRID:
            return level
    return vol.max_pyramid[-1]


def cull_level(bounds: np.ndarray) -> np.ndarray:
    """Bounds per brick max-pooled by 2 until at most `CULL_GRID` cells on every axis."""
    while max(bounds.shape) > CULL_GRID:
        bounds = _downsample(bounds, "max")
    return bounds


SKIP_CELL = 4
"""[voxels] edge of an empty-space-skipping cell (`skip_grid`): smaller cells hug the density closer but cost more
cell lookups per ray and memory. Measured on the smoke 64^3 at 480x270, DSSRM:160:48, CPU time per frame on one
thread: cells of 2, 4, 8, 16 voxels took 44.6, 46.6, 47.0, 50.1 ms (docs/BENCHMARKS.md, "interactive"); 4 keeps the
grid at 1/64 of the density's size."""
MAX_SKIP_RADIUS = 8
"""[cells] cap on an empty cell's radius: one lookup skips at most 17 cells, and building the grid takes at most this
many dilation passes (a 512^3 volume's 128^3 cells)."""


def neighbourhood_max(grid: np.ndarray) -> np.ndarray:
    """Max over each cell's 3x3x3 neighbourhood (cells outside count as False/0), separably: three passes of 3."""
    for axis in range(3):
        n = grid.shape[axis]
        padded = np.pad(grid, [(1, 1) if a == axis else (0, 0) for a in range(3)])
        grid = np.maximum(np.maximum(padded.take(range(n), axis), padded.take(range(1, n + 1), axis)),
                          padded.take(range(2, n + 2), axis))
    return grid


def _block_max(grid: np.ndarray, cell: int) -> np.ndarray:
    """Per block of ``cell`` voxels on each axis, the max over the block widened by one voxel each side (clamped to the
    grid): the block max of the grid dilated by one voxel, computed axis by axis on the shrinking array."""
    for axis in range(3):
        n = grid.shape[axis]
        blocks = -(-n // cell)
        if blocks * cell != n:
            grid = np.pad(grid, [(0, blocks * cell - n) if a == axis else (0, 0) for a in range(3)], mode="edge")
        split = grid.reshape(*grid.shape[:axis], blocks, cell, *grid.shape[axis + 1:])
        out = split.max(axis=axis + 1)
        first, last = split.take(0, axis + 1), split.take(cell - 1, axis + 1)
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(1, None), slice(None, -1)
        out[tuple(lo)] = np.maximum(out[tuple(lo)], last[tuple(hi)])  # the left neighbour's last voxel
        out[tuple(hi)] = np.maximum(out[tuple(hi)], first[tuple(lo)])  # the right neighbour's first voxel
        grid = out
    return grid


MAX_SPARSE_SKIP_CELLS = 1 << 24
"""[cells] a sparse grid's skip grid at `SKIP_CELL` voxels if it has at most this many cells (64 MiB), else at its
bricks': cells of 16 voxels made the sparse smoke of `bench bigdata` (339x431x317) march 2.1x slower than dense"""


MAX_STREAM_SKIP_CELLS = 1 << 21
"""[cells] a streamed level's skip grid has cells of 2^j bricks, j the smallest that keeps it within this many cells:
it is rewritten whenever the device's bricks change (`volren.render.stream_bounds`), and its empty cells' radii
(`skip_cells`) took 0.6 s over the 256^3 bricks of a 4096^3 level on this 2-core CPU, 0.02 s over 128^3 cells"""


def stream_skip_group(bricks: tuple[int, ...]) -> tuple[int, tuple[int, ...]]:
    """Bricks per axis in a streamed level's skip cell (`MAX_STREAM_SKIP_CELLS`), and the cells per axis."""
    group = 1
    while np.prod([-(-b // group) for b in bricks], dtype=np.int64) > MAX_STREAM_SKIP_CELLS:
        group *= 2
    return group, tuple(-(-b // group) for b in bricks)


def skip_grid(density: np.ndarray | SparseGrid, cell: int = SKIP_CELL) -> tuple[np.ndarray, int]:
    """The empty-space-skipping grid of a [z, y, x] density: one value per block of ``cell``^3 voxels.

    A non-empty block holds its max density dilated by one voxel (edges clamped): a trilinear sample reads the 2x2x2
    voxels around it, all within one voxel of the voxel holding the point, so a block whose value is 0 reads zero
    density anywhere in its footprint and up to half a voxel beyond it (the rule of `Volume.max_pyramid`). An empty
    block holds -r, r >= 0 the chessboard radius of the cube of empty blocks centred on it (blocks outside the grid
    count as empty; r <= `MAX_SKIP_RADIUS`): a ray may leave that whole cube at once (proximity clouds, Cohen and
    Sheffer 1994), so one lookup skips a long empty run.

    Returns the grid and its cell [voxels]: ``cell``; for a `SparseGrid` the cells' bounds come from its bricks
    (`SparseGrid.cell_max`), never a dense copy, and where ``cell`` would make more than `MAX_SPARSE_SKIP_CELLS`
    cells the cell is its brick edge B (`SparseGrid.cell_ranges`): 1/B^3 of its index box (2000^3 voxels: 2 M cells
    at B = 16, 125 M at 4). A streamed level's cells are its bricks (2^j a side beyond `MAX_STREAM_SKIP_CELLS`),
    every one occupied until the first frame's bounds (`volren.render.stream_bounds`) are written."""
    if getattr(density, "streamed", False):
        group, shape = stream_skip_group(density.layout.bricks(density.level))
        return np.ones(shape, np.float32), density.brick * group
    if isinstance(density, SparseGrid):
        cells = np.prod([-(-n // cell) for n in density.shape], dtype=np.int64)
        if cells > MAX_SPARSE_SKIP_CELLS:  # cells of one brick: 1/B^3 of the box
            peak, cell = density.cell_ranges()[1], density.brick
        else:
            peak = density.cell_max(cell)
    else:
        peak = _block_max(density, cell)
    return skip_cells(peak), cell


def skip_cells(peak: np.ndarray) -> np.ndarray:
    """`skip_grid`'s values from the cells' bounds ``peak``: the bound where > 0, else -r (its docstring)."""
    occupied = peak > 0
    radius = np.zeros(peak.shape, np.int32)
    for r in range(1, min(max(peak.shape), MAX_SKIP_RADIUS + 1)):
        occupied = neighbourhood_max(occupied)
        if occupied.all():
            break
        radius[~occupied] = r
    return np.where(peak > 0, peak, -radius).astype(np.float32)


def volume_struct(
    vol: Volume, offset: int, res: tuple[int, int, int], light_offset: int, light_res: tuple[int, int, int],
    ambient_offset: int = 0,
) -> VolumeGPU:
    """The device description of ``vol`` whose (mip level of the) grid of ``res`` voxels (x, y, z) starts at
    ``offset`` in the packed density array (its light grids at ``light_offset``, its ambient grid at
    ``ambient_offset``)."""
    s = VolumeGPU()
    s.to_local = _mat44(vol.to_local)
    s.to_world = _mat44(vol.to_world)
    s.offset = offset
    s.res = wp.vec3i(*res)
    s.light_offset = light_offset
    s.light_res = wp.vec3i(*light_res)
    s.ambient_offset = ambient_offset
    s.density_scale = vol.density_scale
    s.albedo = wp.vec3(*vol.albedo)
    s.g = vol.g
    s.emission = wp.vec3(*vol.emission)
    s.diagonal = vol.diagonal
    s.emission_grid_offset, s.emission_grid_res = 0, wp.vec3i(*vol.resolution)
    s.emission_brick_shift, s.emission_bricks, s.emission_brick_table = 0, wp.vec3i(0), 0
    s.emission_constants_offset = 0
    s.emission_table_offset, s.emission_table_size = 0, 0  # no emission grid until `pack_emission` sets one
    s.brick_shift, s.bricks, s.table_offset, s.constants_offset = 0, wp.vec3i(0), 0, 0  # dense
    s.stream_levels, s.stream_header, s.stream_map = 0, 0, 0  # not streamed
    s.region, s.owned_lo, s.owned_hi, s.region_lo, s.region_hi = 0, wp.vec3i(0), wp.vec3i(0), wp.vec3(0.0), wp.vec3(0.0)
    if vol.owned_cells is not None and tuple(res) == vol.resolution:  # a data-parallel region (its level 0)
        lo, hi = (np.array(c[::-1], np.float64) for c in vol.owned_cells)
        n = np.array(res, np.float64)
        s.region, s.owned_lo, s.owned_hi = 1, wp.vec3i(*vol.owned_cells[0][::-1]), wp.vec3i(*vol.owned_cells[1][::-1])
        # the cells' span, centre of voxel lo to centre of voxel hi, one voxel to spare (and the border's clamp)
        s.region_lo, s.region_hi = wp.vec3(*(-1.0 + (lo - 0.5) * 2.0 / n)), wp.vec3(*(-1.0 + (hi + 1.5) * 2.0 / n))
    return s


@dataclass
class DensityPacking:
    """The density array and page tables `upload_scene` fills, level by level (`pack_density`)."""

    grids: list[np.ndarray | int]
    """flat float32 pieces of the density array, or a count of floats reserved (`packed_density`)"""
    tables: list[np.ndarray]
    offset: int = 0
    """floats in ``grids`` so far"""
    table_offset: int = 0
    """entries in ``tables`` so far"""
    pool_voxels: int = 0
    active_bricks: int = 0


def pack_grid(grid: np.ndarray | SparseGrid, packing: DensityPacking, bricked: bool) -> BrickPlace:
    """Append ``grid`` (a [z, y, x] density level or emission grid) to ``packing``: bricked (`BRICK`^3 cells with an
    apron; pool, then the constant bricks' values, the table into ``packing.tables``; a `SparseGrid` as it is), or
    dense where ``bricked`` is False or the grid has under 2 voxels on an axis (a mip level near the top: no trilinear
    cell to brick). Returns where it went."""
    offset = packing.offset
    if isinstance(grid, SparseGrid):
        bv = grid
    elif not bricked or min(grid.shape) < 2:
        packing.grids.append(grid.reshape(-1))
        packing.offset += grid.size
        return BrickPlace(offset, 0, 0, (0, 0, 0), 0)
    else:
        bv = brick_dense(grid, BRICK)
    place = BrickPlace(offset, bv.brick.bit_length() - 1, packing.table_offset, bv.table.shape[::-1],
                       offset + bv.pool.size)
    packing.grids += [bv.pool.reshape(-1), bv.constants]
    packing.tables.append(bv.table.reshape(-1))
    packing.offset += bv.pool.size + bv.constants.size
    packing.table_offset += bv.table.size
    packing.pool_voxels += bv.pool.size
    packing.active_bricks += len(bv.pool)
    return place


@dataclass(frozen=True)
class BrickPlace:
    """Where `pack_grid` put a grid in the packed arrays."""

    offset: int
    """first float of its pool (a dense grid: its first voxel)"""
    shift: int
    """log2 B; 0: dense"""
    table_offset: int
    bricks: tuple[int, int, int]
    """bricks per axis (x, y, z)"""
    constants_offset: int


def pack_stream(structs: list[VolumeGPU], density, volume: int, packing: DensityPacking) -> StreamState:
    """Reserve a streamed volume's device pool (`StreamedDensity.device_bricks` slots), its constants (0, for the
    bricks found empty), its level maps, and its levels' page tables, every entry `NOT_RESIDENT` until the first
    frame places its bricks (`volren.render.streaming`); point ``structs`` at them: ``structs[k]`` samples the pyramid
    from level k on (the mip levels of the cube-map methods share the pool: level k's missing bricks come from
    levels k + 1 and coarser)."""
    layout, e3 = density.layout, (density.brick + 1) ** 3
    capacity = density.device_bricks
    pool, constants = packing.offset, packing.offset + capacity * e3
    packing.grids += [capacity * e3, np.zeros(1, np.float32)]  # the pool: reserved, not written
    packing.offset += capacity * e3 + 1
    sizes = [int(np.prod(layout.bricks(k))) for k in range(layout.count)]
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int).tolist()
    header_offset = packing.table_offset
    first = packing.table_offset + STREAM_INTS * layout.count
    header = [v for k in range(layout.count) for v in (*layout.shapes[k][::-1], *layout.bricks(k)[::-1],
                                                      first + starts[k])]
    for k, s in enumerate(structs):
        maps = density.level_maps(k)  # index maps from level k to each coarser level
        s.offset, s.brick_shift, s.constants_offset = pool, density.brick.bit_length() - 1, constants
        s.stream_levels, s.stream_map = layout.count - k, packing.offset
        s.stream_header = header_offset + STREAM_INTS * k
        s.table_offset, s.bricks = first + starts[k], wp.vec3i(*layout.bricks(k)[::-1])
        packing.grids.append(maps.reshape(-1))
        packing.offset += maps.size
    tables = np.full(sum(sizes), NOT_RESIDENT, np.int32)
    packing.tables += [np.array(header, np.int32), tables]
    packing.table_offset = first + tables.size
    packing.pool_voxels += capacity * e3
    return StreamState(volume, density, pool, capacity, first, starts, tables.copy())


def pack_density(s: VolumeGPU, grid: np.ndarray | SparseGrid, packing: DensityPacking, bricked: bool) -> None:
    """Append ``grid`` (a density level) to ``packing`` (`pack_grid`) and point ``s`` at it."""
    place = pack_grid(grid, packing, bricked)
    s.offset, s.brick_shift = place.offset, place.shift
    s.bricks, s.table_offset = wp.vec3i(*place.bricks), place.table_offset
    s.constants_offset = place.constants_offset


def pack_emission(vol: Volume, structs: list[VolumeGPU], packing: DensityPacking, bricked: bool) -> None:
    """Append ``vol``'s normalised emission grid (bricked as the density, `pack_grid`) and blackbody table to
    ``packing`` and point every one of its mip levels' ``structs`` at them (a fire grid is sampled at full resolution
    whatever the level). Nothing for a volume without an emission grid."""
    if vol.emission_u is None:
        return
    place = pack_grid(vol.emission_u, packing, bricked)
    table = vol.emission_table.reshape(-1)
    for s in structs:
        s.emission_grid_offset, s.emission_brick_shift = place.offset, place.shift
        s.emission_bricks, s.emission_brick_table = wp.vec3i(*place.bricks), place.table_offset
        s.emission_constants_offset = place.constants_offset
        s.emission_table_offset, s.emission_table_size = packing.offset, len(vol.emission_table)
    packing.grids.append(table)
    packing.offset += table.size


def volume_bvh(scene: Scene, device: str) -> wp.Bvh:
    """A BVH over the world-space bounding boxes of the scene's volumes (one item per volume)."""
    corners = [v.corners_world for v in scene.volumes] or [np.zeros((1, 3))]
    lo = np.array([c.min(axis=0) for c in corners], np.float32)
    hi = np.array([c.max(axis=0) for c in corners], np.float32)
    return wp.Bvh(wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device))


NOT_UPLOADED = ("lights", "background", "name")
"""Scene fields `upload_lights` does not compare: the lights it uploads, and what no kernel reads"""


def light_structs(scene: Scene, device: str) -> wp.array:
    """``scene``'s lights as a `LightGPU` array on ``device``."""
    lights = []
    for light in scene.lights:
        s = LightGPU()
        s.axis, s.cos_inner, s.cos_outer, s.falloff = wp.vec3(0.0, -1.0, 0.0), 1.0, 0.0, 0
        s.edge_u, s.edge_v = wp.vec3(0.0), wp.vec3(0.0)
        if isinstance(light, DirectionalLight):
            s.kind, s.vector, s.power = LIGHT_DIRECTIONAL, wp.vec3(*light.direction), wp.vec3(*light.irradiance)
        elif isinstance(light, RectLight):
            s.kind, s.vector, s.power = LIGHT_RECT, wp.vec3(*light.position), wp.vec3(*light.radiance)
            s.edge_u, s.edge_v = wp.vec3(*light.edge_u), wp.vec3(*light.edge_v)
        elif isinstance(light, SpotLight):
            s.kind, s.vector, s.power = LIGHT_SPOT, wp.vec3(*light.position), wp.vec3(*light.intensity)
            s.axis = wp.vec3(*light.direction)
            s.cos_inner, s.cos_outer = (float(np.cos(np.radians(a))) for a in (light.inner_angle, light.outer_angle))
            s.falloff = SPOT_FALLOFFS.index(light.falloff)
        else:
            s.kind, s.vector, s.power = LIGHT_POINT, wp.vec3(*light.position), wp.vec3(*light.intensity)
        lights.append(s)
    return wp.array(lights, dtype=LightGPU, device=device)


def only_lights_differ(old: Scene, new: Scene) -> bool:
    """Whether ``new`` can reuse ``old``'s upload but for the lights (`upload_lights`)."""
    return len(old.lights) == len(new.lights) and all(
        getattr(old, f.name) is getattr(new, f.name) for f in fields(new) if f.name not in NOT_UPLOADED)


def upload_lights(ds: DeviceScene, scene: Scene) -> DeviceScene | None:
    """``ds`` for ``scene`` when it differs from ``ds.scene`` only in its lights (as many; every field that is
    uploaded the same object, as ``dataclasses.replace(scene, lights=...)`` leaves them; background and name are not
    uploaded): a new DeviceScene sharing the densities, volume structs, BVHs, meshes and light-map storage, with only
    ``lights`` uploaded. Being a new object, it misses every cache keyed on the upload (the light map is recomputed
    into the shared storage). None when more changed."""
    if not only_lights_differ(ds.scene, scene):
        return None
    return replace(ds, scene=scene, lights=light_structs(scene, ds.device))


def packed_density(grids: list[np.ndarray | int], device: str) -> wp.array:
    """The packed density array of ``grids`` (flat float32 pieces, or an int: that many floats reserved and left
    unwritten, a streamed volume's pool), written piece by piece into one device array: no concatenated host copy
    (which, with the device copy on the CPU, held a streamed pool three times over)."""
    total = sum(g if isinstance(g, int) else g.size for g in grids)
    out = wp.empty(max(total, 1), dtype=float, device=device)
    offset = 0
    for g in grids:
        if not isinstance(g, int):
            write_device(out, offset, g)
        offset += g if isinstance(g, int) else g.size
    return out


def write_device(array: wp.array, offset: int, values: np.ndarray) -> None:
    """``values`` into the device array at ``offset``: through the host view on the CPU, a copy on CUDA."""
    if not values.size:
        return
    if array.device.is_cpu:
        array.numpy()[offset : offset + values.size] = values.reshape(-1)
    else:
        staged = wp.array(np.ascontiguousarray(values).reshape(-1), dtype=array.dtype, device=array.device)
        wp.copy(array, staged, offset, 0, values.size)


def upload_scene(scene: Scene, device: str, light_grid: int | None = None, mip_levels: bool = False, *,
                 bricked: bool = True) -> DeviceScene:
    """Pack and copy ``scene`` to ``device``; light grids get ``light_grid`` voxels on their longest axis. With
    ``mip_levels`` every level of each volume's mip pyramid is packed too (for LOD marching). Densities go up as
    bricks (`pack_density`); ``bricked=False`` uploads them dense, the path before issue 41, kept only so that tests
    and benchmarks can compare the two (the images are equal)."""
    n_lights = len(scene.lights)
    structs = []
    packing = DensityPacking(grids=[], tables=[])
    grids = packing.grids
    levels = []
    light_offset = 0
    ambient_offset = 0
    light_res = []
    streams = []
    for index, vol in enumerate(scene.volumes):
        streamed = getattr(vol.density, "streamed", False)
        lres = light_grid_resolution(vol.resolution, light_grid,
                                     sparse=streamed or isinstance(vol.density, SparseGrid))
        per_level = []
        for grid in vol.mip_pyramid if mip_levels else [vol.density]:
            per_level.append(volume_struct(vol, 0, grid.shape[::-1], light_offset, lres, ambient_offset))
            if not streamed:
                pack_density(per_level[-1], grid, packing, bricked)
        if streamed:
            streams.append(pack_stream(per_level, vol.density, index, packing))
        levels.append(per_level)
        structs.append(per_level[0])
        light_res.append(lres)
        light_offset += 2 * n_lights * int(np.prod(lres))  # sigma_bar and tau_in per light (render/lightmap.py)
        ambient_offset += int(np.prod(lres))
    for vol, per_level in zip(scene.volumes, levels, strict=True):
        pack_emission(vol, per_level, packing, bricked)
    offset = packing.offset
    if offset > MAX_PACKED or light_offset > MAX_PACKED:
        raise VolrenError(f"scene too large: {offset} voxels (at most {MAX_PACKED} in all volumes together)")
    # what is uploaded: bricks (pool, constants, page tables) where bricked, not the dense grids
    check_allocation(4 * (offset + packing.table_offset + light_offset), device,
                     f"scene '{scene.name}' (density and light maps)")
    max_levels = [coarse_max_level(v) for v in scene.volumes] if mip_levels else []
    max_grids, max_offset = [], 0
    for grid in max_levels:
        max_grids.append((max_offset, grid.shape[::-1]))
        max_offset += grid.size
    for state in streams:
        state.cull = max_grids[state.volume][0] if mip_levels else None
    for index, (vol, per_level) in enumerate(zip(scene.volumes, levels, strict=True)):
        for level, s in zip(vol.mip_pyramid if mip_levels else [vol.density], per_level, strict=False):
            cells, cell = skip_grid(level)
            s.skip_offset, s.skip_res, s.skip_cell = max_offset, wp.vec3i(*cells.shape[::-1]), cell
            for state in (st for st in streams if st.volume == index):
                state.skips.append(max_offset)
            max_levels.append(cells)
            max_offset += cells.size
    try:
        density = packed_density(grids, device)
        table = wp.array(np.concatenate(packing.tables) if packing.tables else np.zeros(1, np.int32),
                         dtype=wp.int32, device=device)
        lightmap = wp.zeros(max(light_offset, 1), dtype=float, device=device)  # no extinction: T = 1
    except (RuntimeError, MemoryError) as exc:
        raise VolrenError(f"cannot allocate the scene on {device}: {exc}") from exc
    for s in (s for per_level in levels for s in per_level):
        s.table = table
    analytic = opaque_structs(scene)
    meshes = [wp.Mesh(points=wp.array(o.vertices, dtype=wp.vec3, device=device),
                      indices=wp.array(o.faces.reshape(-1), dtype=wp.int32, device=device))
              for o in scene.opaque if isinstance(o, TriangleMesh)]
    return DeviceScene(
        scene=scene,
        device=device,
        density=density,
        volumes=wp.array(structs, dtype=VolumeGPU, device=device),
        lights=light_structs(scene, device),
        light_res=light_res,
        lightmap=lightmap,
        ambient=wp.vec3(*scene.environment.mean_radiance()),
        volume_bvh=volume_bvh(scene, device),
        max_density=wp.array(np.concatenate([g.reshape(-1) for g in max_levels]) if max_levels else np.zeros(1),
                             dtype=float, device=device),
        max_grids=max_grids,
        opaque=wp.array(analytic, dtype=OpaqueGPU, device=device) if analytic else wp.zeros(0, dtype=OpaqueGPU,
                                                                                             device=device),
        meshes=meshes,
        mesh_ids=wp.array([m.id for m in meshes], dtype=wp.uint64, device=device),
        mesh_albedo=wp.array([o.albedo for o in scene.opaque if isinstance(o, TriangleMesh)], dtype=wp.vec3,
                             device=device),
        levels=levels,
        ambient_grid=wp.zeros(1, dtype=wp.vec3, device=device),
        table=table,
        pool_bytes=4 * packing.pool_voxels,
        active_bricks=packing.active_bricks,
        streams=streams,
    )

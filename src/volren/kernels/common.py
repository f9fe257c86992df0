"""Shared Warp structs and device functions. Every renderer uses these; none keeps its own copy.

Ray parameters are world-space distances: a world ray ``o + t d`` with unit ``d`` maps to the local ray
``M^-1 o + t M^-1 d`` of a volume (``M`` = to_world), so ``t`` is the same number in both spaces and the
extinction integral needs no rescaling, even for non-uniformly scaled boxes.
"""

from __future__ import annotations

import warp as wp

INF = wp.constant(1.0e30)
LIGHT_DIRECTIONAL = wp.constant(0)
LIGHT_POINT = wp.constant(1)
LIGHT_SPOT = wp.constant(2)
LIGHT_RECT = wp.constant(3)
SPOT_SMOOTHSTEP = wp.constant(0)
SPOT_LINEAR = wp.constant(1)
OPAQUE_SPHERE = wp.constant(0)
OPAQUE_PLANE = wp.constant(1)


@wp.struct
class CameraGPU:
    origin: wp.vec3
    right: wp.vec3
    up: wp.vec3
    forward: wp.vec3
    tan_half_fov: float
    aspect: float
    width: int
    height: int
    near: float
    far: float


NOT_RESIDENT = -(2**31)
"""page-table entry of a streamed brick not resident at its level (`gather_density` draws it from its ancestor)"""
STREAM_INTS = 7
STREAM_FLOATS = 6


@wp.struct
class VolumeGPU:
    to_local: wp.mat44
    to_world: wp.mat44
    offset: int
    """first float of this volume's brick pool in the packed density array (a dense grid: its first voxel)"""
    res: wp.vec3i
    """voxels per axis (x, y, z)"""
    table: wp.array(dtype=wp.int32)
    """the scene's packed brick page tables (`volren.kernels.bricks`; issue 41 item 1), shared by its volumes"""
    table_offset: int
    """first entry of this volume's page table in ``table``"""
    bricks: wp.vec3i
    """bricks per axis (x, y, z) of its page table"""
    brick_shift: int
    """log2 B of its bricks of B^3 cells; 0: a dense [z, y, x] grid at ``offset`` (`gather_density`)"""
    constants_offset: int
    """first value of its constant bricks in the packed density array (page-table entry -1 - k reads value k)"""
    stream_levels: int
    """a streamed pyramid's levels (`volren.stream`, issue 41 item 3); 0: the grid is all there. A streamed
    volume's level-0 page-table entry `NOT_RESIDENT` is drawn from its finest resident ancestor (`ancestor_voxel`)"""
    stream_header: int
    """first of `STREAM_INTS` ints per level (res x, y, z; bricks x, y, z; first table entry) in ``table``"""
    stream_map: int
    """first of `STREAM_FLOATS` floats per level (a x, y, z; b x, y, z: level-k index = a v + b for level-0 index v,
    from the file's scales and translations) in the packed density array"""
    light_offset: int
    """first voxel of this volume's light grids in the packed light-map array (one grid per light)"""
    light_res: wp.vec3i
    ambient_offset: int
    """first voxel of this volume's ambient (GI) grid in the packed ambient array; same resolution as its light grid"""
    density_scale: float
    albedo: wp.vec3
    g: float
    emission: wp.vec3
    diagonal: float
    """[m] longest world-space box diagonal: uniform steps put at most V samples across it"""
    skip_offset: int
    """first cell of this volume's empty-space-skipping level (of its max-density pyramid) in the packed
    ``Medium.max_density`` array"""
    skip_res: wp.vec3i
    """cells per axis (x, y, z) of that level"""
    skip_cell: int
    """voxels per cell edge of that level (a power of 2)"""
    emission_grid_offset: int
    """first voxel of this volume's normalised emission grid u (`volren.scene.Volume.emission_u`, full resolution at
    every mip level) in the packed density array"""
    emission_grid_res: wp.vec3i
    emission_brick_shift: int
    """log2 B of the emission grid's bricks (its page table at ``emission_brick_table`` in ``table``, its constants
    at ``emission_constants_offset``); 0: dense at ``emission_grid_offset``"""
    emission_bricks: wp.vec3i
    emission_brick_table: int
    emission_constants_offset: int
    emission_table_offset: int
    """first float of its blackbody table (3 per entry) in the packed density array"""
    emission_table_size: int
    """entries of that table; 0: the volume has no emission grid"""
    region: int
    """1: a data-parallel region (`volren.dataparallel`, issue 43): its marches sample only the steps whose trilinear
    cell lies in [owned_lo, owned_hi), and look only at those between ``region_lo`` and ``region_hi``; 0: all"""
    owned_lo: wp.vec3i
    """[cells] (x, y, z) the first cell the region owns"""
    owned_hi: wp.vec3i
    """[cells] (x, y, z) the last cell it owns + 1"""
    region_lo: wp.vec3
    """local (x, y, z) corner of a box holding every point whose cell the region owns, one voxel to spare"""
    region_hi: wp.vec3


@wp.struct
class LightGPU:
    kind: int
    vector: wp.vec3
    """unit direction of travel (directional) or position (point, spot)"""
    power: wp.vec3
    """irradiance [W/m^2] (directional) or intensity [W/sr] (point, spot)"""
    axis: wp.vec3
    """spot: unit cone axis"""
    cos_inner: float
    """spot: cosine of the full-intensity half-angle"""
    cos_outer: float
    """spot: cosine of the cut-off half-angle"""
    falloff: int
    """spot: the profile between the cones, SPOT_SMOOTHSTEP or SPOT_LINEAR (`spot_profile`)"""
    edge_u: wp.vec3
    """rect: half-edge vectors (it emits towards edge_u x edge_v)"""
    edge_v: wp.vec3


@wp.struct
class Medium:
    """What a light-map-lit march reads: the packed density grids, the packed light maps and the lights, and with
    ambient GI on (``gi`` = 1) the packed per-voxel ambient radiance grids that replace the constant ambient."""

    density: wp.array(dtype=float)
    lightmap: wp.array(dtype=float)
    lights: wp.array(dtype=LightGPU)
    ambient: wp.array(dtype=wp.vec3)
    gi: int
    max_density: wp.array(dtype=float)
    """packed conservative max-density cells (each volume's ``skip_offset``): zero where every sample is zero"""
    skip: int
    """1: marches skip runs of steps in cells whose max density is 0 (empty-space skipping)"""


@wp.struct
class OpaqueGPU:
    kind: int
    position: wp.vec3
    """sphere centre, or a point of the plane"""
    normal: wp.vec3
    """plane normal (unused for spheres)"""
    radius: float
    albedo: wp.vec3


@wp.struct
class ViewBuffers:
    """One view's render targets and its opaque-surface buffers (paper 001 §3.2's colour + z-buffer)."""

    image: wp.array2d(dtype=wp.vec4)
    """premultiplied linear RGBA, composited over the opaque surfaces"""
    depth: wp.array2d(dtype=float)
    """linear depth where the transmittance reached 1/2, else of the opaque surface, else INF"""
    occluder_color: wp.array2d(dtype=wp.vec4)
    """shaded opaque surface (rgb) and w = 1 where its colour is known (0 for a user depth image)"""
    occluder_depth: wp.array2d(dtype=float)
    """linear depth of the nearest opaque surface, INF where there is none"""


@wp.struct
class MarchState:
    """Front-to-back compositing state of one ray."""

    color: wp.vec3
    transmittance: float
    depth_t: float
    """ray distance where the transmittance first fell to 1/2 (the image's depth), INF if never"""
    samples: int
    """density fetches on this ray"""
    shaded: int
    """samples that were lit (non-zero density): each costs one light-map lookup or shadow ray per light"""
    skipped: int
    """steps not sampled because their max-density cell is empty (empty-space skipping)"""


@wp.func
def count(counters: wp.array(dtype=wp.int64), index: int, value: int):
    """Add ``value`` to a work counter, skipping the atomic when it is 0 (most pixels of a frame add nothing, and
    an atomic per pixel per counter was a measurable share of a cheap pass on the CPU)."""
    if value != 0:
        wp.atomic_add(counters, index, wp.int64(value))


@wp.func
def counter_row(counter_rows: wp.array2d(dtype=wp.int64), i: int, j: int):
    """The row of the frame's counters that thread (i, j) of a `launch_rows` kernel adds into: neighbouring threads
    add into different rows, because same-address atomics serialise on a GPU (measured on an H200: 12 M adds took
    9.2 ms into one address, 0.22 ms spread over 4096; docs/bench/cuda-atomics-h200.txt). A CPU band passes one row."""
    return counter_rows[(i + j) % counter_rows.shape[0]]


@wp.func
def camera_ray(cam: CameraGPU, row: int, col: int, jx: float, jy: float) -> wp.vec3:
    """Unit world direction through pixel (row, col) at sub-pixel offset (jx, jy) in [0, 1) (0.5 = centre)."""
    x = ((float(col) + jx) / float(cam.width) * 2.0 - 1.0) * cam.tan_half_fov * cam.aspect
    y = (1.0 - (float(row) + jy) / float(cam.height) * 2.0) * cam.tan_half_fov
    return wp.normalize(cam.forward + x * cam.right + y * cam.up)


@wp.func
def view_t_range(cam: CameraGPU, d: wp.vec3) -> wp.vec2:
    """Ray distances of the near and far planes along ``d`` (planes are at linear depths near/far)."""
    c = wp.dot(d, cam.forward)
    return wp.vec2(cam.near / c, cam.far / c)


@wp.func
def safe_inverse(x: float) -> float:
    """1 / x with x = 0 treated as +-1e-30: an axis-parallel ray then gets slab distances of +-1e30 * (1 -+ o),
    which leave the interval unconstrained when |o| < 1 and empty when |o| > 1, with no branch per axis."""
    if x >= 0.0:
        return 1.0 / wp.max(x, 1.0e-30)
    return 1.0 / wp.min(x, -1.0e-30)


@wp.func
def box_hit(o: wp.vec3, d: wp.vec3) -> wp.vec2:
    """Slab test of the ray ``o + t d`` against [-1, 1]^3; returns (t_enter, t_exit), empty when t_exit <= t_enter."""
    inv = wp.vec3(safe_inverse(d[0]), safe_inverse(d[1]), safe_inverse(d[2]))
    ta = wp.cw_mul(wp.vec3(-1.0) - o, inv)
    tb = wp.cw_mul(wp.vec3(1.0) - o, inv)
    t0 = wp.max(wp.max(wp.min(ta[0], tb[0]), wp.min(ta[1], tb[1])), wp.min(ta[2], tb[2]))
    t1 = wp.min(wp.min(wp.max(ta[0], tb[0]), wp.max(ta[1], tb[1])), wp.max(ta[2], tb[2]))
    return wp.vec2(t0, t1)


@wp.func
def inside_box(p: wp.vec3) -> bool:
    return wp.abs(p[0]) <= 1.0 and wp.abs(p[1]) <= 1.0 and wp.abs(p[2]) <= 1.0


vec8 = wp.types.vector(length=8, dtype=wp.float32)
"""The 8 voxels of a trilinear cell, x fastest: (x0,y0,z0), (x1,y0,z0), (x0,y1,z0), ..., (x1,y1,z1)."""


@wp.func
def grid_coords(res: wp.vec3i, p: wp.vec3) -> wp.vec3:
    """Continuous voxel coordinates of local ``p`` in [-1, 1]^3 (voxel centres at -1 + (i + 0.5) 2/n), clamped to the
    outermost centres (DESIGN.md)."""
    return wp.vec3(
        wp.clamp((p[0] + 1.0) * 0.5 * float(res[0]) - 0.5, 0.0, float(res[0] - 1)),
        wp.clamp((p[1] + 1.0) * 0.5 * float(res[1]) - 0.5, 0.0, float(res[1] - 1)),
        wp.clamp((p[2] + 1.0) * 0.5 * float(res[2]) - 0.5, 0.0, float(res[2] - 1)),
    )


@wp.func
def grid_cell(res: wp.vec3i, f: wp.vec3) -> wp.vec3i:
    """The trilinear cell (lowest corner voxel) holding continuous coordinates ``f``."""
    return wp.vec3i(wp.min(int(f[0]), res[0] - 2), wp.min(int(f[1]), res[1] - 2), wp.min(int(f[2]), res[2] - 2))


@wp.func
def cell_index(res: wp.vec3i, cell: wp.vec3i) -> int:
    """The index of ``cell`` (a voxel, or a trilinear cell's lowest corner) in a packed [z, y, x] grid of resolution
    res."""
    return (cell[2] * res[1] + cell[1]) * res[0] + cell[0]


@wp.func
def gather_cell(data: wp.array(dtype=float), offset: int, res: wp.vec3i, cell: wp.vec3i) -> vec8:
    """The 8 voxels of a packed [z, y, x] grid around ``cell``."""
    i = offset + cell_index(res, cell)
    sy = res[0]
    sz = res[0] * res[1]
    return vec8(data[i], data[i + 1], data[i + sy], data[i + sy + 1],
                data[i + sz], data[i + sz + 1], data[i + sz + sy], data[i + sz + sy + 1])


@wp.func
def brick_entry(table: wp.array(dtype=wp.int32), table_offset: int, bricks: wp.vec3i, shift: int,
                cell: wp.vec3i) -> int:
    """The page-table entry of the brick holding ``cell`` (`volren.kernels.bricks`): >= 0 a pool slot, < 0 a
    constant brick."""
    b = wp.vec3i(cell[0] >> shift, cell[1] >> shift, cell[2] >> shift)
    return table[table_offset + (b[2] * bricks[1] + b[1]) * bricks[0] + b[0]]


@wp.func
def brick_cell(pool: wp.array(dtype=float), first: int, edge: int, shift: int, cell: wp.vec3i) -> vec8:
    """The 8 voxels around ``cell`` in the resident apron brick whose first voxel is ``pool[first]`` (B = 1 << shift
    cells, ``edge`` = B + 1 voxels per edge): the cell's corners all lie in it, in `gather_cell`'s order."""
    mask = (1 << shift) - 1
    sy = edge
    sz = edge * edge
    i = first + (cell[2] & mask) * sz + (cell[1] & mask) * sy + (cell[0] & mask)
    return vec8(pool[i], pool[i + 1], pool[i + sy], pool[i + sy + 1],
                pool[i + sz], pool[i + sz + 1], pool[i + sz + sy], pool[i + sz + sy + 1])


@wp.func
def gather_grid(data: wp.array(dtype=float), offset: int, res: wp.vec3i, table: wp.array(dtype=wp.int32),
                table_offset: int, bricks: wp.vec3i, shift: int, constants_offset: int, cell: wp.vec3i) -> vec8:
    """The 8 voxels around ``cell`` of a packed grid: through its brick page table (`volren.sparse`; pool at
    ``offset``, constants at ``constants_offset``), or from its dense [z, y, x] voxels at ``offset`` where ``shift``
    is 0. Both give the same 8 values; a constant brick reads one value and no pool voxel."""
    if shift == 0:
        return gather_cell(data, offset, res, cell)
    entry = brick_entry(table, table_offset, bricks, shift, cell)
    if entry < 0:
        c = data[constants_offset - 1 - entry]
        return vec8(c, c, c, c, c, c, c, c)
    edge = (1 << shift) + 1
    return brick_cell(data, offset + entry * edge * edge * edge, edge, shift, cell)


@wp.func
def stream_level(vol: VolumeGPU, k: int):
    """Level ``k`` of a streamed volume as its header in the packed tables holds it (`STREAM_INTS` ints per level,
    `STREAM_FLOATS` map floats per level): (voxels x, y, z; bricks x, y, z; its page table's first entry; its map's
    first float in the density array)."""
    h = vol.stream_header + k * STREAM_INTS
    return (wp.vec3i(vol.table[h], vol.table[h + 1], vol.table[h + 2]),
            wp.vec3i(vol.table[h + 3], vol.table[h + 4], vol.table[h + 5]), vol.table[h + 6],
            vol.stream_map + k * STREAM_FLOATS)


@wp.func
def ancestor_voxel(density: wp.array(dtype=float), vol: VolumeGPU, v: wp.vec3i) -> float:
    """Level-0 voxel ``v`` of a streamed volume whose brick is not resident: a trilinear sample of the finest level
    k >= 1 whose cell there is resident (or known empty), at v's place on that level (index a v + b). The coarsest
    level is always resident, so a sample never falls into a hole (issue 41 item 3)."""
    for k in range(1, vol.stream_levels):
        res, bricks, table, m = stream_level(vol, k)
        f = level_index(density, m, res, v)
        cell = grid_cell(res, f)
        entry = brick_entry(vol.table, table, bricks, vol.brick_shift, cell)
        if entry != NOT_RESIDENT:
            corners = gather_grid(density, vol.offset, res, vol.table, table, bricks, vol.brick_shift,
                                  vol.constants_offset, cell)
            return interpolate_cell(corners, cell_fraction(f, cell))
    return 0.0


MISSING = wp.constant(-1.0)
"""`level0_voxel`'s answer where no level-0 brick on the device holds the voxel (densities are >= 0)"""


@wp.func
def level0_voxel(density: wp.array(dtype=float), vol: VolumeGPU, v: wp.vec3i) -> float:
    """Level-0 voxel ``v`` of a streamed volume from a level-0 brick on the device that holds it: its own brick, or,
    where v lies on a brick's first plane along some axes, the apron of a brick before it along some of those (tried
    in that order, the bits of ``sub`` naming the axes stepped back); `MISSING` where none does. Scalars per axis,
    and the steps back that cannot hold v (not on a first plane) skipped before any read: with a vector mutated per
    axis and step in loops Warp does not unroll, a streamed density read cost 20x a resident volume's on the CPU."""
    shift = vol.brick_shift
    size = 1 << shift
    edge = size + 1
    bx, by, bz = v[0] >> shift, v[1] >> shift, v[2] >> shift
    lx, ly, lz = v[0] & (size - 1), v[1] & (size - 1), v[2] & (size - 1)
    if bx >= vol.bricks[0]:  # the grid's last voxel: only in the last brick's apron
        bx, lx = vol.bricks[0] - 1, lx + size
    if by >= vol.bricks[1]:
        by, ly = vol.bricks[1] - 1, ly + size
    if bz >= vol.bricks[2]:
        bz, lz = vol.bricks[2] - 1, lz + size
    first = wp.where(lx == 0 and bx > 0, 1, 0) | wp.where(ly == 0 and by > 0, 2, 0) | wp.where(lz == 0 and bz > 0, 4, 0)
    subs = 8 + 0 * shift  # a loop bound Warp cannot unroll (`streamed_cell`)
    for sub in range(subs):
        if sub & first == sub:
            sx, sy, sz = sub & 1, (sub >> 1) & 1, sub >> 2
            entry = vol.table[vol.table_offset + ((bz - sz) * vol.bricks[1] + by - sy) * vol.bricks[0] + bx - sx]
            if entry >= 0:
                i = ((wp.where(sz == 1, size, lz) * edge + wp.where(sy == 1, size, ly)) * edge
                     + wp.where(sx == 1, size, lx))
                return density[vol.offset + entry * edge * edge * edge + i]
            if entry != NOT_RESIDENT:
                return density[vol.constants_offset - 1 - entry]
    return MISSING


@wp.func
def level_index(density: wp.array(dtype=float), m: int, res: wp.vec3i, v: wp.vec3i) -> wp.vec3:
    """Continuous index on a streamed level (its map at ``density[m]``, its voxels ``res``) of level-0 voxel ``v``:
    `ancestor_voxel`'s a v + b, clamped to the level."""
    return wp.vec3(
        wp.clamp(density[m] * float(v[0]) + density[m + 3], 0.0, float(res[0] - 1)),
        wp.clamp(density[m + 1] * float(v[1]) + density[m + 4], 0.0, float(res[1] - 1)),
        wp.clamp(density[m + 2] * float(v[2]) + density[m + 5], 0.0, float(res[2] - 1)),
    )


@wp.func(inline=False)  # CUDA __noinline__: one copy, not one at each of a marching kernel's density reads
def streamed_cell(density: wp.array(dtype=float), vol: VolumeGPU, cell: wp.vec3i) -> vec8:
    """The 8 voxels around ``cell`` of a streamed volume whose level-0 brick there is not resident: each from a
    level-0 brick on the device that holds it (`level0_voxel`), else from the finest resident ancestor
    (`ancestor_voxel`). Every copy of a level-0 voxel is the file's, so the cells either side of the face between a
    resident brick and one drawn from a coarser level share their face voxels: the density is continuous across it,
    no seam (issue 41 item 3).

    The values are those of a search per voxel (bit for bit), but the ancestor search is made once for the cell's
    voxels that no level-0 brick holds: a v + b is monotonic per axis, so where the cells of the lowest and highest
    corner lie in one brick of level k, every corner's does, and one page-table entry decides for all of them; one
    gather serves the corners that share a cell there, and where all 8 do (mostly, on a coarse level) their x lerps
    are shared too; a cell inside its brick skips the level-0 look-ups. Where the corners straddle a brick of some
    level, each is searched alone. (Searched per voxel, the first frame of a 256x144 close-up of a 512^3 pyramid,
    drawn from its coarsest level, took 3.9 s of CPU to march; 2 M such reads on one thread 1.88 s, now 0.30 s,
    and 0.06 s from a resident volume.)"""
    out = vec8()
    # loop bounds Warp cannot unroll: unrolled (8 corners x 8 bricks x 3 axes inlined at every density read), each
    # marching kernel's CUDA compile ran past 400 s and 11 GB
    corners = 8 + 0 * vol.stream_levels
    shift = vol.brick_shift
    inner = (1 << shift) - 2
    missing = int(255)  # a cell inside its brick: its voxels are on no first plane, and no brick but its own holds them
    if not (1 <= (cell[0] & (inner + 1)) <= inner and 1 <= (cell[1] & (inner + 1)) <= inner
            and 1 <= (cell[2] & (inner + 1)) <= inner):
        missing = int(0)
        for n in range(corners):
            x = level0_voxel(density, vol, cell + wp.vec3i(n % 2, (n / 2) % 2, n / 4))
            out[n] = x
            if x == MISSING:
                missing = missing | (1 << n)
        if missing == 0:
            return out
    high = cell + wp.vec3i(1, 1, 1)
    for k in range(1, vol.stream_levels):
        res, bricks, table, m = stream_level(vol, k)
        f_lo = level_index(density, m, res, cell)
        f_hi = level_index(density, m, res, high)
        lo = grid_cell(res, f_lo)
        hi = grid_cell(res, f_hi)
        if lo[0] >> shift != hi[0] >> shift or lo[1] >> shift != hi[1] >> shift or lo[2] >> shift != hi[2] >> shift:
            break
        if brick_entry(vol.table, table, bricks, shift, lo) != NOT_RESIDENT:
            base = gather_grid(density, vol.offset, res, vol.table, table, bricks, shift,
                               vol.constants_offset, lo)  # the corners whose cell there is the lowest's share it
            if lo[0] == hi[0] and lo[1] == hi[1] and lo[2] == hi[2]:
                # every corner in that one cell (a coarse level's): `interpolate_cell` of each, its x lerps shared
                a_lo = cell_fraction(f_lo, lo)
                a_hi = cell_fraction(f_hi, lo)
                x_lo = wp.vec4(wp.lerp(base[0], base[1], a_lo[0]), wp.lerp(base[2], base[3], a_lo[0]),
                               wp.lerp(base[4], base[5], a_lo[0]), wp.lerp(base[6], base[7], a_lo[0]))
                x_hi = wp.vec4(wp.lerp(base[0], base[1], a_hi[0]), wp.lerp(base[2], base[3], a_hi[0]),
                               wp.lerp(base[4], base[5], a_hi[0]), wp.lerp(base[6], base[7], a_hi[0]))
                for n in range(corners):
                    if (missing >> n) & 1 == 1:
                        xs = wp.where(n % 2 == 1, x_hi, x_lo)
                        ay = wp.where((n / 2) % 2 == 1, a_hi[1], a_lo[1])
                        az = wp.where(n / 4 == 1, a_hi[2], a_lo[2])
                        out[n] = wp.lerp(wp.lerp(xs[0], xs[1], ay), wp.lerp(xs[2], xs[3], ay), az)
                return out
            for n in range(corners):
                if (missing >> n) & 1 == 1:
                    f = level_index(density, m, res, cell + wp.vec3i(n % 2, (n / 2) % 2, n / 4))
                    c = grid_cell(res, f)
                    got = base
                    if c[0] != lo[0] or c[1] != lo[1] or c[2] != lo[2]:
                        got = gather_grid(density, vol.offset, res, vol.table, table, bricks, shift,
                                          vol.constants_offset, c)
                    out[n] = interpolate_cell(got, cell_fraction(f, c))
            return out
    for n in range(corners):
        if (missing >> n) & 1 == 1:
            out[n] = ancestor_voxel(density, vol, cell + wp.vec3i(n % 2, (n / 2) % 2, n / 4))
    return out


@wp.func
def gather_density(density: wp.array(dtype=float), vol: VolumeGPU, cell: wp.vec3i) -> vec8:
    """The 8 density voxels around ``cell`` of ``vol``: the one density read of every renderer (issue 41 item 1),
    through the volume's brick page table, or from its dense grid where ``brick_shift`` is 0 (grids under 2 voxels on
    an axis, and `volren.upload.upload_scene` with ``bricked=False`` for the equality tests). A streamed volume's
    brick that is not resident gives its 8 voxels from resident neighbours or the finest resident ancestor
    (`streamed_cell`): every caller interpolates them as it would the resident ones."""
    if vol.stream_levels > 1:  # noqa: SIM102 (Warp evaluates both sides of "and": a dense grid has no table)
        if brick_entry(vol.table, vol.table_offset, vol.bricks, vol.brick_shift, cell) == NOT_RESIDENT:
            return streamed_cell(density, vol, cell)
    return gather_grid(density, vol.offset, vol.res, vol.table, vol.table_offset, vol.bricks, vol.brick_shift,
                       vol.constants_offset, cell)


@wp.func
def cell_fraction(f: wp.vec3, cell: wp.vec3i) -> wp.vec3:
    return wp.vec3(f[0] - float(cell[0]), f[1] - float(cell[1]), f[2] - float(cell[2]))


@wp.func
def corner_weight(n: int, a: wp.vec3) -> float:
    """Trilinear weight of corner n of a cell (bit 0: +x, bit 1: +y, bit 2: +z) at fractional position a."""
    w = wp.where(n % 2 == 1, a[0], 1.0 - a[0]) * wp.where((n / 2) % 2 == 1, a[1], 1.0 - a[1])
    return w * wp.where(n / 4 == 1, a[2], 1.0 - a[2])


@wp.func
def interpolate_cell(v: vec8, a: wp.vec3) -> float:
    """Trilinear interpolation of a gathered cell at fractional position ``a`` in [0, 1]^3."""
    c00 = wp.lerp(v[0], v[1], a[0])
    c10 = wp.lerp(v[2], v[3], a[0])
    c01 = wp.lerp(v[4], v[5], a[0])
    c11 = wp.lerp(v[6], v[7], a[0])
    return wp.lerp(wp.lerp(c00, c10, a[1]), wp.lerp(c01, c11, a[1]), a[2])


@wp.func
def sample_grid(data: wp.array(dtype=float), offset: int, res: wp.vec3i, p: wp.vec3) -> float:
    """Trilinear sample of a packed [z, y, x] grid at local ``p`` in [-1, 1]^3, clamped at the border."""
    f = grid_coords(res, p)
    cell = grid_cell(res, f)
    return interpolate_cell(gather_cell(data, offset, res, cell), cell_fraction(f, cell))


@wp.func
def owns_sample(vol: VolumeGPU, p: wp.vec3) -> int:
    """1 where a sample at local ``p`` is ``vol``'s to take: always, unless ``vol`` is a data-parallel region, which
    takes the samples whose trilinear cell (the one `sample_density` reads) it owns. Deciding by the cell read, not
    by p against the region's planes, gives every sample to exactly one region and only reads voxels it holds."""
    if vol.region == 0:
        return 1
    cell = grid_cell(vol.res, grid_coords(vol.res, p))
    for a in range(3):
        if cell[a] < vol.owned_lo[a] or cell[a] >= vol.owned_hi[a]:
            return 0
    return 1


@wp.func
def region_steps(vol: VolumeGPU, o_l: wp.vec3, d_l: wp.vec3, t0: float, dt: float, offset: float, n: int) -> wp.vec2i:
    """The steps [i0, i1) of a march of ``n`` steps t = t0 + (i + offset) dt along the local ray ``o_l + t d_l`` that
    may fall in a data-parallel region's cells (all n for a whole volume): the others are never looked at, so N
    regions share one march's work rather than each doing it all."""
    if vol.region == 0:
        return wp.vec2i(0, n)
    c = 0.5 * (vol.region_lo + vol.region_hi)
    h = 0.5 * (vol.region_hi - vol.region_lo)
    hit = box_hit(wp.cw_div(o_l - c, h), wp.cw_div(d_l, h))
    if hit[1] < hit[0]:
        return wp.vec2i(0, 0)
    i0 = wp.clamp(int(wp.floor((hit[0] - t0) / dt - offset)), 0, n)
    i1 = wp.clamp(int(wp.ceil((hit[1] - t0) / dt - offset)), 0, n)
    return wp.vec2i(i0, i1)


@wp.func
def sample_density(density: wp.array(dtype=float), vol: VolumeGPU, p: wp.vec3) -> float:
    """Trilinear density of ``vol`` at local ``p`` in [-1, 1]^3, clamped at the border (`gather_density`)."""
    f = grid_coords(vol.res, p)
    cell = grid_cell(vol.res, f)
    return interpolate_cell(gather_density(density, vol, cell), cell_fraction(f, cell))


@wp.func
def sample_grid_rgb(data: wp.array(dtype=wp.vec3), offset: int, res: wp.vec3i, p: wp.vec3) -> wp.vec3:
    """Trilinear sample of a packed [z, y, x] vec3 grid at local ``p`` in [-1, 1]^3, clamped at the border."""
    f = grid_coords(res, p)
    cell = grid_cell(res, f)
    a = cell_fraction(f, cell)
    i = offset + cell_index(res, cell)
    out = wp.vec3(0.0)
    for n in range(8):
        out += corner_weight(n, a) * data[i + (n / 4) * res[0] * res[1] + ((n / 2) % 2) * res[0] + n % 2]
    return out


@wp.func
def blackbody_emission(vol: VolumeGPU, data: wp.array(dtype=float), p: wp.vec3, rho: float) -> wp.vec3:
    """Blackbody radiance per metre [W/(m^3 sr)] of the volume's emission grid at local ``p`` where the density rho
    is > 0 (`volren.scene`, "Fire"): u sampled trilinearly, then the table interpolated linearly at u (size - 1);
    u <= 0 emits nothing."""
    n = vol.emission_table_size
    if n == 0 or rho <= 0.0:
        return wp.vec3(0.0)
    g = grid_coords(vol.emission_grid_res, p)
    cell = grid_cell(vol.emission_grid_res, g)
    u = interpolate_cell(gather_grid(data, vol.emission_grid_offset, vol.emission_grid_res, vol.table,
                                     vol.emission_brick_table, vol.emission_bricks, vol.emission_brick_shift,
                                     vol.emission_constants_offset, cell), cell_fraction(g, cell))
    if u <= 0.0:
        return wp.vec3(0.0)
    f = wp.min(u, 1.0) * float(n - 1)
    i = wp.min(int(f), n - 2)
    a = f - float(i)
    k = vol.emission_table_offset + 3 * i
    return (1.0 - a) * wp.vec3(data[k], data[k + 1], data[k + 2]) + a * wp.vec3(data[k + 3], data[k + 4], data[k + 5])


@wp.func
def emitted_radiance(vol: VolumeGPU, data: wp.array(dtype=float), p: wp.vec3, rho: float) -> wp.vec3:
    """Radiance emitted per metre [W/(m^3 sr)] at local ``p`` of density rho: emission * rho plus the blackbody
    emission of the volume's emission grid (`blackbody_emission`)."""
    return vol.emission * rho + blackbody_emission(vol, data, p, rho)


@wp.func
def voxel_center(i: int, j: int, k: int, res: wp.vec3i) -> wp.vec3:
    """Local position of voxel (x=i, y=j, z=k)."""
    return wp.vec3(
        -1.0 + (float(i) + 0.5) * 2.0 / float(res[0]),
        -1.0 + (float(j) + 0.5) * 2.0 / float(res[1]),
        -1.0 + (float(k) + 0.5) * 2.0 / float(res[2]),
    )


@wp.func
def hg_phase(cos_theta: float, g: float) -> float:
    """Henyey-Greenstein phase function [1/sr]; cos_theta is between the light's and the scattered direction."""
    denom = 1.0 + g * g - 2.0 * g * cos_theta
    return (1.0 - g * g) / (4.0 * wp.pi * denom * wp.sqrt(denom))


@wp.func
def light_travel_dir(light: LightGPU, x: wp.vec3) -> wp.vec3:
    """Unit direction in which the light's radiance travels when it arrives at ``x``."""
    if light.kind == LIGHT_DIRECTIONAL:
        return light.vector
    return wp.normalize(x - light.vector)


@wp.func
def light_distance(light: LightGPU, x: wp.vec3) -> float:
    """[m] from ``x`` to the light (INF for a directional light): where a shadow ray stops."""
    if light.kind == LIGHT_DIRECTIONAL:
        return INF
    return wp.length(light.vector - x)


@wp.func
def spot_profile(light: LightGPU, c: float) -> float:
    """A spot's intensity at cos theta = c from its axis over the axial one (`volren.scene.SpotLight.falloff`):
    smoothstep(cos outer, cos inner, c) in the cosine, or (outer - theta) / (outer - inner) in the angle."""
    if light.falloff == SPOT_LINEAR:
        outer = wp.acos(light.cos_outer)
        return wp.clamp((outer - wp.acos(wp.clamp(c, -1.0, 1.0))) / (outer - wp.acos(light.cos_inner)), 0.0, 1.0)
    return wp.smoothstep(light.cos_outer, light.cos_inner, c)


@wp.func
def light_irradiance(light: LightGPU, x: wp.vec3) -> wp.vec3:
    """Unshadowed irradiance at ``x`` on a plane facing the light (inverse-square for a point or spot light, times
    the spot's cone profile `spot_profile`; a rect light as a point at its centre)."""
    if light.kind == LIGHT_DIRECTIONAL:
        return light.power
    r2 = wp.max(wp.length_sq(light.vector - x), 1.0e-8)
    if light.kind == LIGHT_SPOT:
        c = wp.dot(light.axis, (x - light.vector) / wp.sqrt(r2))
        return light.power * spot_profile(light, c) / r2
    if light.kind == LIGHT_RECT:
        # A point at the centre with intensity radiance * area * cos (the path tracer samples the area instead).
        n = wp.cross(light.edge_u, light.edge_v)
        c = wp.max(wp.dot(n, x - light.vector), 0.0) / wp.sqrt(r2)
        return light.power * (4.0 * c) / r2
    return light.power / r2


@wp.func
def march_step_count(length: float, diagonal: float, samples: int) -> int:
    """Uniform steps of at most diagonal / samples over ``length``: ceil(length / step), at least 1."""
    n = int(wp.ceil(length * float(samples) / diagonal - 1.0e-6))
    return wp.max(n, 1)


@wp.func
def next_box_boundary(
    o: wp.vec3, d: wp.vec3, t: float, volumes: wp.array(dtype=VolumeGPU), v_begin: int, v_end: int
) -> float:
    """The nearest box entry or exit of volumes [v_begin, v_end) on the ray ``o + t' d`` with t' > t (INF if none):
    marching between boundaries keeps every step inside one set of boxes, so piecewise media integrate exactly."""
    best = float(INF)
    eps = 1.0e-5 * (1.0 + wp.abs(t))
    for v in range(v_begin, v_end):
        vol = volumes[v]
        h = box_hit(wp.transform_point(vol.to_local, o), wp.transform_vector(vol.to_local, d))
        if h[1] > h[0]:
            if h[0] > t + eps:
                best = wp.min(best, h[0])
            if h[1] > t + eps:
                best = wp.min(best, h[1])
    return best


@wp.func
def density_inside(vol: VolumeGPU, x: wp.vec3, density: wp.array(dtype=float)) -> float:
    """The volume's density at world ``x``, or -1 where ``x`` lies outside its box."""
    p = wp.transform_point(vol.to_local, x)
    if inside_box(p):
        return sample_density(density, vol, p)
    return -1.0


@wp.func
def covering_diagonal(x: wp.vec3, volumes: wp.array(dtype=VolumeGPU), v_begin: int, v_end: int) -> float:
    """Smallest diagonal of the boxes containing ``x`` (INF if none): the step rule of a dense march there."""
    diag = float(INF)
    for v in range(v_begin, v_end):
        vol = volumes[v]
        if inside_box(wp.transform_point(vol.to_local, x)):
            diag = wp.min(diag, vol.diagonal)
    return diag


@wp.func
def skip_lookup(vol: VolumeGPU, max_density: wp.array(dtype=float), q: wp.vec3, o: wp.vec3, inv_d: wp.vec3) -> wp.vec2:
    """(value, exit) of the skip cell holding ``q`` (skip-cell coordinates, clamped to the grid) for the ray
    ``o + t d`` in those coordinates: its `skip_grid` value (> 0: not empty; -r <= 0: the cube of radius r around it
    is empty) and the ray distance where the ray leaves that cell (not empty) or that cube (empty)."""
    c = skip_cell_at(vol, q)
    value = max_density[vol.skip_offset + cell_index(vol.skip_res, c)]
    r = wp.max(-value, 0.0)
    t = float(1.0e30)
    for a in range(3):
        lo = float(c[a]) - r
        t = wp.min(t, wp.max((lo - o[a]) * inv_d[a], (lo + 1.0 + 2.0 * r - o[a]) * inv_d[a]))
    return wp.vec2(value, t)


@wp.func
def skip_cell_at(vol: VolumeGPU, q: wp.vec3) -> wp.vec3i:
    """The skip cell holding skip-cell coordinates q (`skip_cell_ray`), clamped to the grid."""
    cells = vol.skip_res
    return wp.vec3i(wp.clamp(int(wp.floor(q[0])), 0, cells[0] - 1), wp.clamp(int(wp.floor(q[1])), 0, cells[1] - 1),
                    wp.clamp(int(wp.floor(q[2])), 0, cells[2] - 1))


@wp.func
def skip_cell_scale(vol: VolumeGPU) -> wp.vec3:
    """Local units to skip-cell coordinates per axis: q = (p + 1) res / (2 skip_cell)."""
    return wp.vec3(float(vol.res[0]), float(vol.res[1]), float(vol.res[2])) * (0.5 / float(wp.max(vol.skip_cell, 1)))


@wp.func
def skip_value(vol: VolumeGPU, max_density: wp.array(dtype=float), p: wp.vec3) -> float:
    """The `skip_grid` value of the skip cell holding local point p: <= 0 where every voxel a trilinear sample at p
    reads is 0."""
    c = skip_cell_at(vol, wp.cw_mul(p + wp.vec3(1.0), skip_cell_scale(vol)))
    return max_density[vol.skip_offset + cell_index(vol.skip_res, c)]


@wp.func
def skip_cell_ray(vol: VolumeGPU, o_l: wp.vec3, d_l: wp.vec3):
    """The local ray ``o_l + t d_l`` in skip-cell coordinates (cell c spans [c, c + 1) on each axis:
    q = (p + 1) res / (2 skip_cell)): its origin, direction and the direction's inverse (for `skip_lookup`)."""
    to_cell = skip_cell_scale(vol)
    o_c = wp.cw_mul(o_l + wp.vec3(1.0), to_cell)
    d_c = wp.cw_mul(d_l, to_cell)
    return o_c, d_c, wp.vec3(safe_inverse(d_c[0]), safe_inverse(d_c[1]), safe_inverse(d_c[2]))


@wp.func
def first_skip_check(vol: VolumeGPU, skip: int) -> float:
    """The ray distance of a march's first skip-cell lookup: at once, or never when skipping is off (``skip`` 0) or
    the volume struct has no skip grid."""
    if skip == 0 or vol.skip_cell == 0:
        return 1.0e30
    return -1.0e30


@wp.func
def chord_depth(vol: VolumeGPU, rho_sum: float, dt: float, n: int) -> wp.vec2:
    """(tau, fetches) of a chord whose n fetched densities sum to rho_sum at step dt: sigma_t = density_scale *
    density (paper 000 Eq. 2)."""
    return wp.vec2(vol.density_scale * rho_sum * dt, float(n))


@wp.func
def optical_depth_skipping(
    vol: VolumeGPU,
    x: wp.vec3,
    toward: wp.vec3,
    t_limit: float,
    density: wp.array(dtype=float),
    max_density: wp.array(dtype=float),
    skip: int,
    samples: int,
) -> wp.vec3:
    """(tau, fetches, skipped): `optical_depth` with empty-space skipping when ``skip`` is 1 (and the volume has a
    skip grid): a step in an empty cell of ``max_density`` (`volren.upload.skip_grid`, zero density up to half a
    voxel beyond the cell) samples exactly 0 and adds nothing to the sum, so it is left unsampled and only the
    position advances (by the same float additions), and tau is bit-identical to skipping off. Cells are looked up
    as in the view march (`volren.render.marching.march.march_volume_light_map`): once per cell entered."""
    o_l = wp.transform_point(vol.to_local, x)
    d_l = wp.transform_vector(vol.to_local, toward)
    h = box_hit(o_l, d_l)
    t0 = wp.max(h[0], 0.0)
    t1 = wp.min(h[1], t_limit)
    if t1 <= t0:
        return wp.vec3(0.0, 0.0, 0.0)
    n = march_step_count(t1 - t0, vol.diagonal, samples)
    dt = (t1 - t0) / float(n)
    p = o_l + (t0 + 0.5 * dt) * d_l
    step = dt * d_l
    o_c, d_c, inv_d = skip_cell_ray(vol, o_l, d_l)
    check_t = first_skip_check(vol, skip)
    rho_sum = float(0.0)
    skipped = int(0)
    taken = int(0)
    steps = region_steps(vol, o_l, d_l, t0, dt, 0.5, n)
    i = steps[0]
    for _k in range(i):  # a region's first step, by the same float additions as the whole march's
        p = p + step
    while i < steps[1]:
        t = t0 + (float(i) + 0.5) * dt
        if t >= check_t:
            cell = skip_lookup(vol, max_density, o_c + t * d_c, o_c, inv_d)
            check_t = cell[1]
            if cell[0] <= 0.0:
                j = wp.min(wp.max(int(wp.ceil((check_t - t0) / dt - 0.5)), i + 1), steps[1])
                skipped += j - i
                for _k in range(j - i):
                    p = p + step
                i = j
                continue
        if owns_sample(vol, p) != 0:
            rho_sum += sample_density(density, vol, p)
            taken += 1
        p = p + step
        i += 1
    r = chord_depth(vol, rho_sum, dt, taken)
    return wp.vec3(r[0], r[1], float(skipped))


@wp.func
def optical_depth(
    vol: VolumeGPU, x: wp.vec3, toward: wp.vec3, t_limit: float, density: wp.array(dtype=float), samples: int
) -> wp.vec2:
    """(tau, fetches): the optical depth of one volume along ``x + t toward``, 0 <= t <= t_limit, by uniform midpoint
    steps of at most diagonal / samples over its chord, sampled in local space (no per-sample transform)."""
    r = optical_depth_skipping(vol, x, toward, t_limit, density, density, 0, samples)
    return wp.vec2(r[0], r[1])


@wp.func
def transmittance_toward_skipping(
    x: wp.vec3,
    toward: wp.vec3,
    t_limit: float,
    volumes: wp.array(dtype=VolumeGPU),
    v_begin: int,
    v_end: int,
    density: wp.array(dtype=float),
    samples: int,
    counters: wp.array(dtype=wp.int64),
    counter_index: int,
    max_density: wp.array(dtype=float),
    skip: int,
    skipped_index: int,
) -> float:
    """`transmittance_toward` (its arguments first) with empty-space skipping (`optical_depth_skipping`): the same
    T bit for bit; counts the fetches at ``counter_index`` and the steps left unsampled at ``skipped_index``."""
    tau = float(0.0)
    fetched = float(0.0)
    skipped = float(0.0)
    for v in range(v_begin, v_end):
        r = optical_depth_skipping(volumes[v], x, toward, t_limit, density, max_density, skip, samples)
        tau += r[0]
        fetched += r[1]
        skipped += r[2]
    count(counters, counter_index, int(fetched))
    count(counters, skipped_index, int(skipped))
    return wp.exp(-tau)


@wp.func
def transmittance_toward(
    x: wp.vec3,
    toward: wp.vec3,
    t_limit: float,
    volumes: wp.array(dtype=VolumeGPU),
    v_begin: int,
    v_end: int,
    density: wp.array(dtype=float),
    samples: int,
    counters: wp.array(dtype=wp.int64),
    counter_index: int,
) -> float:
    """Transmittance from world point ``x`` along unit ``toward`` up to ``t_limit`` through volumes
    [v_begin, v_end) (paper 000 Eq. 2). Optical depths add even where boxes overlap, so T is the product of each
    volume's own chord march (order-independent, as paper 000 §3.2 notes for its any-hit traversal)."""
    return transmittance_toward_skipping(x, toward, t_limit, volumes, v_begin, v_end, density, samples, counters,
                                         counter_index, density, 0, counter_index)


@wp.func
def optical_depth_bvh_skipping(
    x: wp.vec3,
    toward: wp.vec3,
    t_limit: float,
    bvh: wp.uint64,
    volumes: wp.array(dtype=VolumeGPU),
    density: wp.array(dtype=float),
    samples: int,
    max_density: wp.array(dtype=float),
    skip: int,
    exclude: int,
) -> wp.vec3:
    """(tau, fetches, skipped): `optical_depth_skipping` summed over every volume whose world box the ray hits but
    ``exclude`` (-1: none), found by a BVH over the boxes (paper 000 §3.2.3's any-hit traversal: the optical depths
    add in any order)."""
    total = wp.vec3(0.0)
    query = wp.bvh_query_ray(bvh, x, toward)
    v = int(0)
    while wp.bvh_query_next(query, v):
        if v != exclude:
            total += optical_depth_skipping(volumes[v], x, toward, t_limit, density, max_density, skip, samples)
    return total


@wp.func
def transmittance_bvh_skipping(
    x: wp.vec3,
    toward: wp.vec3,
    t_limit: float,
    bvh: wp.uint64,
    volumes: wp.array(dtype=VolumeGPU),
    density: wp.array(dtype=float),
    samples: int,
    counters: wp.array(dtype=wp.int64),
    counter_index: int,
    max_density: wp.array(dtype=float),
    skip: int,
    skipped_index: int,
) -> float:
    """`transmittance_bvh` (its arguments first) with empty-space skipping (`optical_depth_skipping`): the same T
    bit for bit."""
    r = optical_depth_bvh_skipping(x, toward, t_limit, bvh, volumes, density, samples, max_density, skip, -1)
    count(counters, counter_index, int(r[1]))
    count(counters, skipped_index, int(r[2]))
    return wp.exp(-r[0])


@wp.func
def transmittance_bvh(
    x: wp.vec3,
    toward: wp.vec3,
    t_limit: float,
    bvh: wp.uint64,
    volumes: wp.array(dtype=VolumeGPU),
    density: wp.array(dtype=float),
    samples: int,
    counters: wp.array(dtype=wp.int64),
    counter_index: int,
) -> float:
    """`transmittance_toward` through every volume whose world box the ray hits, found by a BVH over the boxes
    (paper 000 §3.2.3's any-hit traversal: the optical depths add in any order)."""
    return transmittance_bvh_skipping(x, toward, t_limit, bvh, volumes, density, samples, counters, counter_index,
                                      density, 0, counter_index)


@wp.func
def composite_step(acc: wp.vec4, source: wp.vec3, sigma_t: float, dt: float) -> wp.vec4:
    """Composite one step front to back into ``acc = (r, g, b, T)``, with sigma_t and the source term J (radiance
    added per metre) constant over the step: dL = T J (1 - exp(-sigma_t dt)) / sigma_t, T *= exp(-sigma_t dt) --
    exact for homogeneous media, so closed forms hold at any step count (paper 000 Eq. 1-2 discretised).

    Hot loops keep ``acc`` in a local vector: Warp copies a whole struct on every field write, which halved the
    march's speed when the state was a `MarchState` updated per sample."""
    tau = sigma_t * dt
    step_t = wp.exp(-tau)
    # (1 - e^-tau) / sigma_t = dt (1 - tau / 2 + tau^2 / 6 - ...): the series for thin steps, where float32's
    # 1 - e^-tau cancels (a thin cube came out 0.32% dark at tau = 7e-6); its relative error is < tau^3 / 24.
    weight = dt * (1.0 - tau * (0.5 - tau / 6.0))
    if tau > 1.0e-2:
        weight = (1.0 - step_t) / sigma_t
    w = acc[3] * weight
    return wp.vec4(acc[0] + w * source[0], acc[1] + w * source[1], acc[2] + w * source[2], acc[3] * step_t)


@wp.func
def half_depth(depth_t: float, before: float, after: float, t: float) -> float:
    """The ray distance where the transmittance first fell to 1/2: ``t`` if this step crossed it."""
    if before > 0.5 and after <= 0.5:
        return t
    return depth_t


@wp.func
def state_accumulator(s: MarchState) -> wp.vec4:
    return wp.vec4(s.color[0], s.color[1], s.color[2], s.transmittance)


@wp.func
def with_accumulator(state: MarchState, acc: wp.vec4) -> MarchState:
    s = state
    s.color = wp.vec3(acc[0], acc[1], acc[2])
    s.transmittance = acc[3]
    return s


@wp.func
def new_march_state() -> MarchState:
    s = MarchState()
    s.color = wp.vec3(0.0)
    s.transmittance = 1.0
    s.depth_t = INF
    s.samples = 0
    s.shaded = 0
    s.skipped = 0
    return s


@wp.func
def occluder_t(buffers: ViewBuffers, cam: CameraGPU, d: wp.vec3, row: int, col: int) -> float:
    """Ray distance to the opaque surface seen through pixel (row, col) along d (INF if none): rays stop there."""
    z = buffers.occluder_depth[row, col]
    if z >= INF:
        return INF
    return z / wp.dot(d, cam.forward)


@wp.func
def pixel_ray(cam: CameraGPU, buffers: ViewBuffers, row: int, col: int):
    """The unit direction through the centre of pixel (row, col) and its (near, far) ray distances, far cut at the
    opaque surface seen through the pixel."""
    d = camera_ray(cam, row, col, 0.5, 0.5)
    planes = view_t_range(cam, d)
    return d, wp.vec2(planes[0], wp.min(planes[1], occluder_t(buffers, cam, d, row, col)))


@wp.func
def project_pixel(cam: CameraGPU, x: wp.vec3) -> wp.vec3:
    """(column, row, linear depth) of world point x in the view; columns and rows are continuous pixel coordinates
    (pixel (r, c) spans [c, c + 1) x [r, r + 1))."""
    v = x - cam.origin
    z = wp.dot(v, cam.forward)
    col = (wp.dot(v, cam.right) / (z * cam.tan_half_fov * cam.aspect) + 1.0) * 0.5 * float(cam.width)
    row = (1.0 - wp.dot(v, cam.up) / (z * cam.tan_half_fov)) * 0.5 * float(cam.height)
    return wp.vec3(col, row, z)


@wp.func
def occluded_end(cam: CameraGPU, buffers: ViewBuffers, x: wp.vec3, t1: float, facing: float) -> float:
    """Ray distance t1 towards the world point x, cut at the opaque surface of the z-buffer pixel that x projects to
    (nearest pixel; x outside the viewport is not cut). ``facing`` is the ray direction's cosine with the view axis."""
    pix = project_pixel(cam, x)
    col = int(wp.floor(pix[0]))
    row = int(wp.floor(pix[1]))
    if col >= 0 and col < cam.width and row >= 0 and row < cam.height:
        return wp.min(t1, buffers.occluder_depth[row, col] / facing)
    return t1


@wp.func
def write_pixel(
    s: MarchState,
    cam: CameraGPU,
    d: wp.vec3,
    row: int,
    col: int,
    buffers: ViewBuffers,
    counters: wp.array(dtype=wp.int64),
    density_counter: int,
):
    """Store a finished ray: premultiplied RGBA (alpha = 1 - T) over the opaque surface behind it (alpha 1 there),
    linear view depth, and its density samples."""
    count(counters, density_counter, s.samples)
    color = s.color
    alpha = 1.0 - s.transmittance
    surface = buffers.occluder_color[row, col]
    if surface[3] > 0.0:
        color = color + s.transmittance * wp.vec3(surface[0], surface[1], surface[2])
        alpha = 1.0
    z = s.depth_t * wp.dot(d, cam.forward)
    if s.depth_t >= INF:
        z = buffers.occluder_depth[row, col]
    buffers.image[row, col] = wp.vec4(color[0], color[1], color[2], alpha)
    buffers.depth[row, col] = z


@wp.func
def ray_jitter(seed: int, view: int, row: int, col: int, width: int, height: int, index: int) -> float:
    """Seeded uniform number in [0, 1) for (view, pixel, index): the same inputs give the same image."""
    state = wp.rand_init(seed, ((view * height + row) * width + col) * 8 + index)
    return wp.randf(state)

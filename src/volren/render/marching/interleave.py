"""Interleaved spatial reuse (InS, paper 000 §3.1.3, Fig. 4 (a)) for CACRM's coupled march.

Texel rays converge towards the eye, so near it the four rays of a 2x2 texel quad run less than half a voxel apart.
There each ray samples its own step at an interleaved offset, (q + 1/2) / 4 of the step for lane q, and takes the
other three lanes' raw samples (their gathered 2x2x2 voxels) as supplementary samples: it re-interpolates each at
its own point at that lane's distance (trilinear weights clamped to the cell, exact when the point lies in it) and
composites the four quarter steps in order. One fetch per ray and step thus gives four samples per ray, which lets
VSA's long steps keep the sampling rate near the eye. Past the distance t_s = (voxel / 2) / (largest angle between
the quad's rays) a quad's rays are too far apart and every lane samples its own step midpoint, as without InS.

The paper shares the samples by wave shuffles between the quad's threads; here one work item marches the quad for
both eyes of a coupled pair (8 lanes whose state lives in small local matrices), the CPU-friendly equivalent. The
quad's lanes of one eye step on one shared lattice anchored at their farthest texel, so that the four lanes' samples
are at the same distances; each lane's steps are clipped to its own segment. The quad's next step is the smallest
of its lanes' Eq. 4 proposals (the quad must share one step; the smallest keeps every lane's sampling rate), and the
pair of eyes takes the larger of their two, as the texel kernel's coupling does (§3.1.3: "we take the max value").
Taking the largest of all eight lanes instead cost 1.0-1.7 dB at the close-up of ``bench binocular`` with the
fitted VSA, where each lane proposes its own real-valued step (N = 360, no quad interleaving: smoke 84.8, phantom
61.2 dB against 85.8 and 62.9 for the texel kernel; with the smallest: 86.3 and 63.4 dB at 1-3% more gathers).
A lane reuses the other eye's fetch when their samples fall in the same cell.

Interleaving needs steps of at least a voxel (m dt >= voxel): quarter steps of a shorter step sample finer than the
grid, and the re-interpolation (up to half a voxel of linear extension beyond the neighbour's cell) would only add its
error: measured at the close-up against 2048 uniform steps, InS at N = 360 without this floor fell from 75.2 to 60.2
dB (smoke) and 64.4 to 58.7 dB (cloud). An earlier floor of two base steps made InS wait for VSA to double the step;
the fitted VSA keeps steps near one base step close to the eye in thin media (f_A = 1 - T is about 0 there), so InS
never switched on at the close-up. With the voxel floor at N = 100 (1.1 voxels per base step, 64^3, 160x90 stereo,
against 2048 uniform steps): cloud 52.7 -> 58.0 dB, phantom 35.2 -> 35.2 dB, smoke 61.1 -> 59.9 dB (the smoke is
smooth at this step, and the re-interpolation error is all InS adds; clamping the weights to the cell instead: smoke
57.9, cloud 58.5 dB). Since the quad work item costs about twice a texel work item on the CPU, `interleave_tiles`
routes only the tiles where some quad can interleave to this kernel (a conservative test from the tile's corners)
and the rest to the texel kernel.

Empty space: a lane whose sample lies in an empty skip cell reads 8 zero voxels (`volren.upload.skip_grid`), so the
kernel takes its cell as zero without the fetch, and the lanes that re-interpolate it read 0 too: the same image bit
for bit with fewer gathers (smoke 64^3 at the close-up, N = 100: 1,244,432 -> 395,895; smoke 256^3 at N = 64 with
the adaptive LOD's coarse level, where every tile is routed here: 8.1 M -> 0.80 M). The steps are still walked one
by one (the texel kernel jumps idle runs), which is what the kernel costs in empty space: its march there is 1.4-5.5x
the texel kernel's (docs/BENCHMARKS-LOG.md, issue 24's fifth session).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from volren.kernels.common import (
    INF,
    cell_fraction,
    count,
    counter_row,
    gather_density,
    grid_cell,
    grid_coords,
    half_depth,
    interpolate_cell,
    skip_value,
    vec8,
)
from volren.render.compositing.mesh_layers import next_layer_t, segment_advance
from volren.render.frame import (
    DENSITY_SAMPLES,
    INTERLEAVED_SAMPLES,
    LIGHTMAP_LOOKUPS,
    RAYS,
    SHARED_SAMPLES,
    SKIPPED_STEPS,
)
from volren.render.marching.coupled import (
    CoupledJob,
    job_constants,
    pair_eye_ray,
    pair_finish,
    pair_mesh,
    pair_target,
    tile_views,
)
from volren.render.marching.cubemap import texel_index, texel_point, tile_texel
from volren.render.marching.march import lit_step
from volren.render.marching.vsa import END, ramp_slope, vsa_proposal

LANES = 8
"""2 eyes x 2 x 2 texels"""
mat84 = wp.types.matrix(shape=(LANES, 4), dtype=wp.float32)
mat83 = wp.types.matrix(shape=(LANES, 3), dtype=wp.float32)
mat88 = wp.types.matrix(shape=(LANES, 8), dtype=wp.float32)
mat84i = wp.types.matrix(shape=(LANES, 4), dtype=wp.int32)
vec8i = wp.types.vector(length=LANES, dtype=wp.int32)


@wp.func
def quad_lane_texel(tiles: wp.array(dtype=wp.vec3i), tile: int, apron: int, size: int, k: int, qr: int, qc: int,
                    lane: int) -> wp.vec3i:
    """The texel of lane (0..3, row-major in the quad) of quad (qr, qc) of tile k; face -1 when there is none."""
    tr = 2 * qr + lane / 2
    tc = 2 * qc + lane % 2
    if tr >= tile or tc >= tile:
        return wp.vec3i(-1, 0, 0)
    return tile_texel(tiles, tile, apron, size, k * tile + tr, tc)


@wp.func
def lane_fraction(cell_origin: wp.vec3, res: wp.vec3i, p: wp.vec3) -> wp.vec3:
    """Trilinear weights of local point p relative to the cell whose first voxel is cell_origin: inside the cell the
    exact interpolation, up to half a voxel outside it the cell's trilinear function extended linearly."""
    f = grid_coords(res, p) - cell_origin
    return wp.vec3(wp.clamp(f[0], -0.5, 1.5), wp.clamp(f[1], -0.5, 1.5), wp.clamp(f[2], -0.5, 1.5))


@wp.kernel
def quad_march_kernel(job: CoupledJob, counter_rows: wp.array2d(dtype=wp.int64), row0: int):
    """One 2x2 texel quad for both eyes of a pair (lanes 0-3: eye 0, 4-7: eye 1 when eyes == 2); with translucent
    meshes each lane also writes its cube k-buffer segments (`segment_advance`, as the texel kernel)."""
    r, c = wp.tid()
    counters = counter_row(counter_rows, r, c)
    vol, medium, params, vp, dt = job_constants(job)
    tile = job.tile
    row = r + row0
    quads = (tile + 1) / 2
    k = row / quads
    views = tile_views(job, k)
    qr = row - k * quads
    # Lane setup (`pair_eye_ray`): segment (t_min, t_max, facing, valid), world and local directions.
    seg = mat84()
    dw = mat83()
    dl = mat83()
    # Cube k-buffer cursor per lane: texel pixel (row, col, layers), segment base index; where the next segment
    # closes (INF: no layer ahead, or no texel).
    cursor = mat84i()
    next_t = vec8()
    # Per eye: the eye (world, local).
    eye_w = wp.matrix_from_rows(job.cam0.origin, job.cam1.origin)
    eye_l = wp.matrix_from_rows(wp.transform_point(vol.to_local, job.cam0.origin),
                                wp.transform_point(vol.to_local, job.cam1.origin))
    for lane in range(LANES):
        next_t[lane] = INF
        q = quad_lane_texel(job.tiles, tile, job.apron, job.size, k, qr, c, lane % 4)
        if q[0] >= 0:
            ray = pair_eye_ray(job, lane / 4, views, vol, wp.transform_point(vol.to_world, texel_point(q, job.size)),
                               texel_index(q[0], q[1], q[2], job.size), dt)
            seg[lane] = ray.seg
            dw[lane] = ray.d
            dl[lane] = ray.dl
            cursor[lane] = wp.vec4i(ray.pix[0], ray.pix[1], ray.pix[2], ray.base)
            next_t[lane] = ray.next_t
    # Per eye: the shared lattice anchor (farthest texel), the nearest segment start, and t_s, the distance up to
    # which the quad's rays stay within half a voxel of each other.
    anchor = wp.vec2(0.0)
    start = wp.vec2(INF)
    t_s = wp.vec2(0.0)
    voxel = vol.diagonal / wp.length(wp.vec3(float(vol.res[0]), float(vol.res[1]), float(vol.res[2])))
    step_floor = voxel
    for e in range(2):
        spread = float(0.0)
        valid = int(0)
        for ia in range(4):
            la = e * 4 + ia
            if seg[la, 3] > 0.0:
                valid += 1
                anchor[e] = wp.max(anchor[e], seg[la, 1])
                start[e] = wp.min(start[e], seg[la, 0])
                for ib in range(4):
                    lb = e * 4 + ib
                    if seg[lb, 3] > 0.0:
                        spread = wp.max(spread, wp.length(dw[la] - dw[lb]))
        # Interleaving needs all four lanes (a quad cut by a face edge, the viewport or a z-buffer edge marches plain).
        if valid == 4:
            t_s[e] = INF
            if spread > 0.0:
                t_s[e] = 0.5 * voxel / spread
    n0 = int(0)
    n1 = int(0)
    if anchor[0] > start[0]:
        n0 = int(wp.ceil((anchor[0] - start[0]) / dt - 1.0e-6))
    if anchor[1] > start[1]:
        n1 = int(wp.ceil((anchor[1] - start[1]) / dt - 1.0e-6))
    acc = mat84()
    snap = mat84()
    open_seg = vec8i()
    half = vec8()
    prev = vec8()
    prev_t = vec8()
    for lane in range(LANES):
        acc[lane] = wp.vec4(0.0, 0.0, 0.0, 1.0)
        snap[lane] = acc[lane]
        half[lane] = INF
        prev[lane] = -1.0
    cells = mat88()
    origins = mat83()
    own = vec8()
    own_t = vec8()
    samples = int(0)
    extra = int(0)
    shared = int(0)
    shaded = int(0)
    skipped = int(0)
    # Empty-space skipping (DVR: the quad kernel runs with VSA only): a lane whose sample lies in an empty skip cell
    # reads 8 zero voxels (`volren.upload.skip_grid`), so its cell is zero without a fetch, and so are the other
    # lanes' re-interpolations of it: the same samples, lattice and image.
    skipping = medium.skip != 0 and vol.skip_cell != 0
    blank = vec8i()
    absorb = vol.density_scale * dt
    pos = float(wp.max(n0, n1))
    m = float(1.0)
    while pos > END:
        m = wp.min(m, pos)
        lo = wp.vec2(anchor[0] - pos * dt, anchor[1] - pos * dt)
        hi = wp.vec2(anchor[0] - (pos - m) * dt, anchor[1] - (pos - m) * dt)
        inter = wp.vec2(0.0)
        for e in range(2):
            if hi[e] <= t_s[e] and m * dt >= step_floor:
                inter[e] = 1.0
        # A lane is live while its transmittance counts and the step overlaps its segment; an eye fetches while any
        # of its lanes is live (interleaved: all its lanes fetch, the others need their samples). The march ends
        # when no lane has anything left ahead.
        live = vec8()
        busy = wp.vec2(0.0)
        pending = int(0)
        for lane in range(LANES):
            e = lane / 4
            if seg[lane, 3] > 0.0 and acc[lane, 3] >= params.min_transmittance and lo[e] < seg[lane, 1]:
                pending = 1
                if hi[e] > seg[lane, 0]:
                    live[lane] = 1.0
                    busy[e] = 1.0
        if pending == 0:
            break
        # Fetch: each lane's own sample, at its interleaved offset or at its clipped step midpoint.
        fetched = vec8()
        for lane in range(LANES):
            e = lane / 4
            if busy[e] > 0.0 and seg[lane, 3] > 0.0 and (live[lane] > 0.0 or inter[e] > 0.0):
                t = lo[e] + (float(lane % 4) + 0.5) * 0.25 * (hi[e] - lo[e])
                if inter[e] == 0.0:
                    t = 0.5 * (wp.max(lo[e], seg[lane, 0]) + wp.min(hi[e], seg[lane, 1]))
                p = eye_l[e] + t * dl[lane]
                f = grid_coords(vol.res, p)
                cell = grid_cell(vol.res, f)
                origin = wp.vec3(float(cell[0]), float(cell[1]), float(cell[2]))
                mate = lane % 4
                blank[lane] = 0
                if e == 1 and job.share != 0 and fetched[mate] > 0.0 and origins[mate] == origin:
                    cells[lane] = cells[mate]
                    blank[lane] = blank[mate]
                    shared += int(blank[mate] == 0)
                elif skipping and skip_value(vol, medium.max_density, p) <= 0.0:
                    cells[lane] = vec8()
                    blank[lane] = 1
                else:
                    cells[lane] = gather_density(medium.density, vol, cell)
                origins[lane] = origin
                own[lane] = float(0.0)
                if blank[lane] == 0:
                    own[lane] = interpolate_cell(cells[lane], cell_fraction(f, cell))
                    samples += 1
                else:
                    skipped += 1
                own_t[lane] = t
                fetched[lane] = 1.0
        # Composite: four quarter steps from the quad's samples, or the lane's own step.
        quad_m = wp.vec2(INF)
        for lane in range(LANES):
            if live[lane] > 0.0:
                e = lane / 4
                a = acc[lane]
                h = half[lane]
                pieces = 1
                if inter[e] > 0.0:
                    pieces = 4
                for piece in range(pieces):
                    sub_lo = lo[e]
                    sub_hi = hi[e]
                    source = lane
                    if pieces == 4:
                        sub_lo = lo[e] + float(piece) * 0.25 * (hi[e] - lo[e])
                        sub_hi = sub_lo + 0.25 * (hi[e] - lo[e])
                        source = e * 4 + piece
                    sub_lo = wp.max(sub_lo, seg[lane, 0])
                    sub_hi = wp.min(sub_hi, seg[lane, 1])
                    if sub_hi > sub_lo and fetched[source] > 0.0:
                        t = 0.5 * (sub_lo + sub_hi)
                        p = eye_l[e] + t * dl[lane]
                        x = eye_w[e] + t * dw[lane]
                        rho = own[lane]
                        if source != lane:
                            rho = float(0.0)
                            if blank[source] == 0:
                                fraction = lane_fraction(origins[source], vol.res, p)
                                rho = wp.max(interpolate_cell(cells[source], fraction), 0.0)
                                extra += 1
                        if rho > 0.0:
                            shaded += 1
                            if t > next_t[lane]:
                                pix = wp.vec3i(cursor[lane, 0], cursor[lane, 1], cursor[lane, 2])
                                mesh = pair_mesh(job, e)
                                j, sn = segment_advance(mesh, pix, pair_target(job, e), cursor[lane, 3], seg[lane],
                                                        open_seg[lane], snap[lane], a, t)
                                next_t[lane] = next_layer_t(mesh, pix, j, seg[lane])
                                open_seg[lane] = j
                                snap[lane] = sn
                            b = a
                            a = lit_step(a, rho, vol, medium, p, x, dw[lane], sub_hi - sub_lo, params.ambient)
                            h = half_depth(h, b[3], a[3], t)
                acc[lane] = a
                half[lane] = h
                if vp.enabled != 0:
                    t = own_t[lane]
                    quad_m[e] = wp.min(quad_m[e], vsa_proposal(vp, t, ramp_slope(vp, seg[lane, 1]), own[lane],
                                                               prev[lane], prev_t[lane], a[3], dt, absorb))
                    prev[lane] = own[lane]
                    prev_t[lane] = t
        pos = pos - m
        m = float(1.0)
        for e in range(2):
            if quad_m[e] < INF:
                m = wp.max(m, quad_m[e])
    for lane in range(LANES):
        q = quad_lane_texel(job.tiles, tile, job.apron, job.size, k, qr, c, lane % 4)
        if q[0] >= 0:
            pair_finish(job, lane / 4, views, texel_index(q[0], q[1], q[2], job.size), seg[lane], acc[lane], half[lane],
                        wp.vec3i(cursor[lane, 0], cursor[lane, 1], cursor[lane, 2]), cursor[lane, 3], open_seg[lane],
                        snap[lane])
            count(counters, RAYS, int(seg[lane, 3]))
    count(counters, DENSITY_SAMPLES, samples)
    count(counters, SHARED_SAMPLES, shared)
    count(counters, INTERLEAVED_SAMPLES, extra)
    count(counters, SKIPPED_STEPS, skipped)
    count(counters, LIGHTMAP_LOOKUPS, shaded * medium.lights.shape[0])


def base_step_reaches_a_voxel(samples: int, res: tuple[int, int, int]) -> bool:
    """Whether InS runs at all: where the base step diagonal / N is at least a voxel (diagonal / |res|, the kernel's
    own floor for interleaving), i.e. N <= the grid's diagonal in voxels. Below it the quads interleave only on
    amplified steps and pay their kernel for nothing measurable: eyes inside the box (0.1, 0, 0.5), 128^3, 480x270
    stereo, N = 360 (0.62 voxels a base step), against the 1024-sample reference: InS -0.04 / +0.05 / -0.02 dB
    (smoke / cloud / phantom) for 3.0 / 3.4 / 1.4x the frame time of the texel kernel (before the quad kernel
    skipped empty cells; docs/bench/cacrm-inside-cpu-2026-12-04.jsonl)."""
    return samples <= float(np.linalg.norm(np.asarray(res, dtype=float)))


def interleave_tiles(to_world: np.ndarray, eyes: list[np.ndarray], near: float, origins: np.ndarray, rows: int,
                     size: int, voxel: float) -> np.ndarray:
    """Per tile (launch origins of ``rows`` texels at face size ``size``), whether some quad may interleave for some
    eye: whether a ray of the tile can start before t_s = (voxel / 2) / spread, the spread (largest angle between a
    quad's rays) taken at the tile's corners, where it is smallest or nearly. World units."""
    h = 2.0 / size
    f = origins[:, 0]
    axis, sign = f // 2, 1.0 - 2.0 * (f % 2)
    u = np.clip(np.stack([-1 + origins[:, 1] * h, -1 + (origins[:, 1] + rows) * h], 1), -1, 1)
    v = np.clip(np.stack([-1 + origins[:, 2] * h, -1 + (origins[:, 2] + rows) * h], 1), -1, 1)
    # Corners (u0, v0), (u0, v1), (u1, v0), (u1, v1): coordinate c is the face's sign, u or v by its axis.
    uu, vv = np.repeat(u, 2, axis=1), np.tile(v, 2)
    local = np.stack([np.where((axis == c)[:, None], sign[:, None], np.where(((axis + 1) % 3 == c)[:, None], uu, vv))
                      for c in range(3)], axis=2)
    world = local @ to_world[:3, :3].T + to_world[:3, 3]
    # The quad's diagonals (the kernel's spread is the largest lane distance), in world units.
    eu, ev = (world[:, 2] - world[:, 0]) / rows, (world[:, 1] - world[:, 0]) / rows
    diagonals = np.stack([eu + ev, eu - ev], 1)  # (n, 2, 3)
    to_local = np.linalg.inv(to_world)
    out = np.zeros(len(origins), dtype=bool)
    for eye in eyes:
        ray = world - eye
        dist = np.linalg.norm(ray, axis=2)
        unit = ray / dist[..., None]  # (n, 4, 3)
        # Angle between a corner's ray and its diagonal neighbours': the diagonal's part across the ray / distance.
        along = np.einsum("nkc,nmc->nkm", unit, diagonals)
        across = diagonals[:, None] - along[..., None] * unit[:, :, None]
        spread = np.linalg.norm(across, axis=3).max(axis=2) / dist
        t_s = 0.5 * voxel / np.maximum(spread.min(axis=1), 1e-12)
        # Box entry along the corner rays (the near plane when the eye is inside) bounds where the rays start.
        o = to_local[:3, :3] @ eye + to_local[:3, 3]
        d = unit @ to_local[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            entry = np.nan_to_num(np.minimum((-1 - o) / d, (1 - o) / d), nan=-np.inf).max(axis=2)
        out |= (np.maximum(entry, near) < t_s[:, None]).any(axis=1)
    return out

"""CACRM: coupled adaptive cube-map ray marching for binocular views (paper 000 §3.1), built on CMSRM.

Ray coupling (§3.1.2): the two eyes' rays that end on the same interior-face texel are marched by one work item.
Each eye's ray runs from its box entry (or near plane) to the texel (its t_min, t_max), cut at that eye's z-buffer,
in uniform steps of Delta t = diagonal / N anchored at the texel; the pair takes max(n_0, n_1) synchronised steps
front to back, and the eye whose segment is shorter skips the steps that lie outside it while keeping the step
(the paper's joint length t_d = max(t_max - t_min) with both rays starting at t_max - t_d). Where the two samples of
a step fall in the same trilinear cell (the paper's floor((x0 + t v) S + 0.5) test on voxel coordinates), its 8 voxels
are fetched once and interpolated for both rays (the explicit two-phase version); the counters record those as
``shared_samples``. The rays converge at the texel, so sharing grows towards the far faces. With empty-space
skipping a sample in the same cell as the other eye's sample in an empty skip cell reads 0 without a fetch (counted
as skipped): the cell is zero, though its own skip cell is not empty. Coupled against independent gathers, cloud 64^3,
stereo 160x90, defaults and --no-hybrid (issue 19 item 6): 0.711 with the fixed 2x VSA, 0.729 with the adaptive VSA
(Eq. 4's ramp lengthens the steps near the texels, where the eyes share most; uniform steps 0.712), 0.761 once
skipping left only the occupied cells to fetch (uniform 0.760), 0.763 with the face-rim pixels marched directly, 0.748
with the empty cells shared.

Both eyes get their own cube map (the visible faces of either eye, the finer LOD of the two) and are resampled to
their own views as in CMSRM. Views are coupled in pairs (0, 1), (2, 3), ...; an odd last view is marched alone.
``coupling=False`` marches each eye alone with the same anchored steps, so coupled marching without sharing gives the
same images; ``share_voxels=False`` keeps coupling but fetches per ray.

Variable step amplification (§3.1.3, Eq. 4-6): after each sample, each eye proposes the next step as
Delta t (N) max(k_a t / t_max, f_lambda^w_lambda f_T^w_T f_A^w_A, 1) with the base step Delta t = diagonal / N (the
paper's (t_max - t_min) / N; here the same base step as DSSRM and CMSRM, so that N means the same in all three), and
the pair takes the larger proposal (`marching.vsa`). Steps are real multiples of the base step counted back from
the texel, so uniform stepping (k_a = 0, w = 0) is exactly the texel-anchored lattice. An earlier version floored the
multiple to whole base steps: with f_lambda_max = 2 and f_T, f_A <= 1 every product below 2 became a uniform step, VSA
degenerated into a fixed 2x step and the density derivative never changed the image (issue 12). rho' is the
difference of the last two samples per base step (the paper uses Bergner et al.'s estimate). The constants come from
``scripts/fit_vsa.py`` (``vsa_fit.json``), fitted for quality at equal voxel gathers.

Empty-tile culling and tile LOD (32x32 tiles, the coarse phase) come from CMSRM; with a coupled pair a tile's level
bounds the footprint in both eyes. Interleaved spatial reuse (§3.1.3) routes the tiles where 2x2 quads can share
samples to `volren.render.marching.interleave`'s quad kernel.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.errors import VolrenError
from volren.kernels.common import (
    INF,
    ViewBuffers,
    VolumeGPU,
    cell_fraction,
    cell_index,
    count,
    counter_row,
    first_skip_check,
    gather_density,
    grid_cell,
    grid_coords,
    half_depth,
    interpolate_cell,
    skip_lookup,
)
from volren.render.compositing.mesh_layers import next_layer_t, segment_advance
from volren.render.frame import (
    DENSITY_SAMPLES,
    IDLE_RUNS,
    JUMPED_STEPS,
    LIGHTMAP_LOOKUPS,
    RAYS,
    SHARED_SAMPLES,
    SKIPPED_STEPS,
    PassClock,
)
from volren.render.marching.cmsrm import CMSRM, CMSRMConfig, TileGroup
from volren.render.marching.coupled import (
    CoupledJob,
    job_constants,
    pair_eye_ray,
    pair_finish,
    pair_mesh,
    pair_target,
    tile_views,
)
from volren.render.marching.cubemap import CubeLOD, CubeTarget, texel_index, texel_point, tile_texel
from volren.render.marching.interleave import base_step_reaches_a_voxel, interleave_tiles, quad_march_kernel
from volren.render.marching.march import lit_step, mode_step
from volren.render.marching.modes import MODE_DVR, MODE_MIP, skippable
from volren.render.marching.vsa import (
    END,
    VSA_FIT,
    VSAParams,
    lambda_cap,
    ramp_slope,
    vsa_proposal,
    vsa_ramp,
    zero_product,
)
from volren.upload import DeviceScene, camera_struct

mat22 = wp.types.matrix(shape=(2, 2), dtype=wp.float32)
mat23 = wp.types.matrix(shape=(2, 3), dtype=wp.float32)
mat24 = wp.types.matrix(shape=(2, 4), dtype=wp.float32)
mat23i = wp.types.matrix(shape=(2, 3), dtype=wp.int32)


@dataclass(frozen=True)
class CACRMConfig(CMSRMConfig):
    coupling: bool = True
    """march both eyes' rays to a texel in one work item (off: each eye alone, same steps)"""
    share_voxels: bool = True
    """fetch a trilinear cell once when both eyes' samples fall in it"""
    vsa: bool = True
    """variable step amplification (Eq. 4-6); off = uniform steps"""
    interleave: bool = True
    """interleaved spatial reuse (§3.1.3): 2x2 texel quads share their samples where their rays run < 1/2 voxel
    apart (`volren.render.marching.interleave`), where a base step is at least a voxel
    (`base_step_reaches_a_voxel`: N up to the grid's diagonal in voxels, 221 at 128^3)"""
    k_a: float = VSA_FIT["k_a"]
    """Eq. 4: ray-length amplification k_a t / t_max (paper: 3; fitted: 1.5, see vsa_fit.json)"""
    k_b: float = VSA_FIT["k_b"]
    """Eq. 5: wave-length factor f_lambda = min(k_b / |rho'|, f_lambda_max), rho' per base step"""
    f_lambda_max: float = VSA_FIT["f_lambda_max"]
    """Eq. 5's cap (paper: 2; fitted: 4)"""
    w_lambda: float = VSA_FIT["w_lambda"]
    w_t: float = VSA_FIT["w_t"]
    w_a: float = VSA_FIT["w_a"]

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("k_a", "k_b", "f_lambda_max", "w_lambda", "w_t", "w_a"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise VolrenError(f"{name} must be a finite number >= 0, got {value}")
        if self.cube_faces != "interior":
            raise VolrenError("cacrm couples rays on interior cube faces only (--cube-faces interior)")


@wp.func
def lattice_step(seg: wp.vec4, pos: float, m: float, dt: float) -> wp.vec2:
    """(midpoint, length) of the step covering [pos - m, pos) base steps counted back from the texel:
    [t_max - pos dt, t_max - (pos - m) dt], clipped at t_min (a step wholly before t_min has length <= 0)."""
    hi = seg[1] - (pos - m) * dt
    lo = wp.max(seg[1] - pos * dt, seg[0])
    return wp.vec2(0.5 * (lo + hi), hi - lo)


JUMP_MIN = wp.constant(4.0)
"""[steps] `ramp_jump` runs its closed form when at least this many steps remain to the nearest event (fewer: the
loop walks them; the closed form costs about as much as a few steps)"""
JUMP_SLACK = wp.constant(1.0e-2)
"""[base steps] `ramp_jump` counts a step as an event's when its float64 midpoint (or end) lies within this of the
event, so a step the jump takes is never one the float32 loop would call an event: the loop's midpoints and event
distances are rounded to about 1e-4 base steps (ray distances up to ~5 at float32's 6e-8, base steps ~0.01), and
the loop takes the event's step and decides it by its own test. The version before stopped two whole steps short
and walked 2.8 steps an idle run (now 1.5; smoke 128^3, 480x270 stereo)."""
JUMP_BITS = 7
"""`ramp_jump` finds the event step by bisection over powers lambda_1^(2^i), i < JUMP_BITS (runs of up to
2^JUMP_BITS - 1 steps; a longer run jumps again)"""
vec_bits = wp.types.vector(length=JUMP_BITS, dtype=wp.float64)
JUMP_SPAN = wp.constant(float(2 ** (JUMP_BITS - 1)))


@wp.func
def ramp_jump(pos: float, m: float, seg: mat24, slope: wp.vec2, live: wp.vec2i, n: wp.vec2i, trans: wp.vec2,
              check: wp.vec2, next_t: wp.vec2, product: wp.vec2, vp: VSAParams, dt: float, min_t: float):
    """`idle_run`'s steps from (pos, m) in closed form, up to the step of the first event (a live eye's skip-cell
    lookup or mesh layer, an eye entering its segment, the ray's end; within JUMP_SLACK counts as the event): (pos, m,
    steps k, each live eye's last step midpoint), k = 0 where the loop should walk.

    In an idle run every live eye proposes max(k_a t / t_max, P, 1) over a constant product P (`vsa_ramp`); the pair
    steps by the largest, C = max(1, P_e) while the ramp stays below C and then the ramp of the eye with the longest
    ray (k_a t / t_max = k_a (1 - s dt / t_max) at a step midpoint s base steps before the texel: largest for the
    largest t_max). Constant steps are pos - k C. Ramp steps are a linear recurrence: with X the step's start and M
    its length in base steps from that eye, X' = X + M and M' = kappa (X + M / 2), kappa = k_a dt / t_max, so (X, M)
    is a sum of two geometric sequences (the eigenvalues of [[1, 1], [kappa, kappa / 2]]: lambda_1 > 1 and
    -1 < lambda_2 < 0); the event's step is found by bisection over powers of lambda_1 (no logarithms: libm's
    float64 log and pow made a jump cost more than the steps it saved). In float64; the loop iterates in float32, so
    a jump moves the lattice by float rounding only (`tests/test_cacrm_speed.py`)."""
    c = float(1.0)
    far = float(0.0)
    stop = float(-INF)
    floor_ = float(0.0)
    clipped = int(0)
    ramp = float(0.0)
    last = wp.vec2(0.0)
    for e in range(2):
        if live[e] != 0:
            c = wp.max(c, product[e])
            far = wp.max(far, seg[e, 1])
            ramp = wp.max(ramp, slope[e] * (seg[e, 1] - (pos - 0.5 * m) * dt))
            # a live eye stops at the step whose midpoint t reaches its next lookup or mesh layer: s <= stop
            stop = wp.max(stop, (seg[e, 1] - wp.min(check[e], next_t[e])) / dt)
            clipped = clipped + int(pos * dt > seg[e, 1] - seg[e, 0])
        elif trans[e] >= min_t and n[e] > 0:
            floor_ = wp.max(floor_, float(n[e]))
    # unit steps with the ramp at most 1 are `idle_run`'s exact jump
    if clipped != 0 or (m == 1.0 and c <= 1.0 and ramp <= 1.0):
        return pos, m, 0.0, last
    if wp.min(pos - 0.5 * m - stop, pos - floor_) < JUMP_MIN * wp.max(wp.max(m, c), ramp):
        return pos, m, 0.0, last
    p = wp.float64(pos)
    mm = wp.float64(m)
    cc = wp.float64(c)
    ka = wp.float64(vp.k_a)
    eye = wp.float64(far) / wp.float64(dt)
    to_eye = wp.float64(dt) / wp.float64(far)
    slack = wp.float64(JUMP_SLACK)
    # events moved towards the run's start by the slack: a step within it of one is left to the loop
    s_stop = wp.float64(stop) + slack
    s_floor = wp.float64(floor_) + slack
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    k = wp.float64(0.0)
    mid = wp.float64(0.0)
    if ka * (one - (p - half * mm) * to_eye) <= cc:
        if mm != cc:
            return pos, m, 0.0, last
        # Constant steps of C: step j's midpoint is p - (j + 1/2) C. Events: the stop, the floor (p - (j + 1) C
        # below it), the ramp passing C after step j (the steps up to it are still C).
        j_evt = wp.min(wp.ceil((p - half * cc - s_stop) / cc), wp.floor((p - s_floor) / cc))
        if ka > wp.float64(0.0):
            j_evt = wp.min(j_evt, wp.floor((p - half * cc - eye * (one - cc / ka) - slack) / cc) + one)
        k = j_evt
        if k < one:
            return pos, m, 0.0, last
        mid = p - (k - half) * cc
        pos = float(p - k * cc)
    else:
        x0 = eye - p
        kappa = ka * to_eye
        b = one + half * kappa
        root = wp.sqrt(b * b + wp.float64(2.0) * kappa)
        l1 = half * (b + root)
        l2 = half * (b - root)
        c1 = (mm + (one - l2) * x0) / root
        c2 = x0 - c1
        # Step k's midpoint in X is c1 l1^k (1 + l1) / 2 + c2 l2^k (1 + l2) / 2 (|l2|^k: gone after a step); no
        # event at step k while it is below eye - s_stop and X_(k+1) = c1 l1^(k+1) + ... <= eye - s_floor. The
        # largest such k: bisection over l1^(2^i).
        mid_scale = half * c1 * (one + l1)
        end_scale = c1 * l1
        pw = vec_bits()
        pw[0] = l1
        for i in range(1, JUMP_BITS):
            pw[i] = pw[i - 1] * pw[i - 1]
        if mid_scale >= eye - s_stop or end_scale > eye - s_floor:
            return pos, m, 0.0, last
        cur = one
        span = wp.float64(JUMP_SPAN)
        for i in range(JUMP_BITS):
            # branch-free: the outcome is data, and a mispredicted branch per bit cost more than the bit's work
            trial = cur * pw[JUMP_BITS - 1 - i]
            ok = trial * mid_scale < eye - s_stop and trial * end_scale <= eye - s_floor
            cur = wp.where(ok, trial, cur)
            k = k + wp.where(ok, span, wp.float64(0.0))
            span = half * span
        # k: the last step without an event; jump k + 1 steps (0 .. k)
        k = k + one
        # the last jumped step, k - 1: l1^(k-1) is cur, l2^(k-1) by multiplication (|l2| < 0.01, below float64's
        # rounding of X after four)
        a1 = cur
        a2 = wp.float64(0.0)
        steps = int(float(k)) - 1
        if steps <= 3:
            a2 = one
            for _ in range(steps):
                a2 = a2 * l2
        x_last = c1 * a1 + c2 * a2
        m_last = c1 * (l1 - one) * a1 + c2 * (l2 - one) * a2
        mid = eye - x_last - half * m_last
        m = float(ka * (one - mid * to_eye))
        pos = float(eye - x_last - m_last)
    for e in range(2):
        if live[e] != 0:
            last[e] = float(wp.float64(seg[e, 1]) - mid * wp.float64(dt))
    return pos, m, float(k), last


@wp.func
def unit_run(pos: float, seg: mat24, slope: wp.vec2, live: wp.vec2i, n: wp.vec2i, trans: wp.vec2, check: wp.vec2,
             next_t: wp.vec2, product: wp.vec2, vp: VSAParams, dt: float, min_t: float) -> float:
    """`idle_run`'s unit steps from pos (m = 1) in closed form: each live eye's last step midpoint before its next
    skip-cell lookup, mesh layer and (VSA) the ramp's passing 1, an eye not yet in its segment still out. Float
    rounding can put it one step past the exact count, which `idle_run` then checks step by step."""
    k = wp.floor(pos)
    for e in range(2):
        if live[e] != 0:
            bound = wp.min(check[e], next_t[e])
            if vp.enabled != 0:
                # Eq. 4's ramp passes 1 beyond t = t_max / k_a, and a product above 1 leaves no unit step
                if product[e] > 1.0:
                    k = 0.0
                elif slope[e] > 0.0:
                    bound = wp.min(bound, 1.0 / slope[e])
            k = wp.min(k, wp.floor(pos + 0.5 - wp.max((seg[e, 1] - bound) / dt, -pos)))
        elif trans[e] >= min_t and n[e] > 0:
            k = wp.min(k, wp.floor(pos - float(n[e])))
    return k


@wp.func
def idle_run(pos: float, m: float, seg: mat24, slope: wp.vec2, live: wp.vec2i, n: wp.vec2i, trans: wp.vec2,
             check: wp.vec2, next_t: wp.vec2, product: wp.vec2, vp: VSAParams, dt: float, min_t: float):
    """The pair's steps from (pos, m) while they stay idle: each live eye's step midpoint before its next skip-cell
    lookup and mesh layer, an eye not yet in its segment still out. Returns (pos, m) of the first step that is not
    idle (or pos <= END), the eye steps taken, those of them `ramp_jump` took, and each eye's last step midpoint
    (VSA's previous distance).

    Every live eye's samples here are 0 after a 0 (rho' = 0, T unchanged), so its proposal is `vsa_ramp` over the
    constant ``product`` (`vsa_product`): the same lattice and counts as the kernel's loop, by the same arithmetic,
    at a fraction of its cost. Runs of unit steps (uniform stepping, or VSA's ramp and product at most 1 up to the
    run's end) are jumped in one go: pos - k is exact, and a step midpoint grows as pos falls, so the last step
    decides for all. Runs of longer steps are jumped by `ramp_jump` (to float rounding)."""
    steps = float(0.0)
    jumped = float(0.0)
    last = wp.vec2(0.0)
    if m == 1.0:
        k = unit_run(pos, seg, slope, live, n, trans, check, next_t, product, vp, dt, min_t)
        for e in range(2):
            if live[e] != 0:
                end = lattice_step(seg[e], pos - k + 1.0, 1.0, dt)[0]
                while k >= 1.0 and (end >= check[e] or end > next_t[e]
                                    or (vp.enabled != 0 and vsa_ramp(end, slope[e], product[e]) > 1.0)):
                    k = k - 1.0
                    end = lattice_step(seg[e], pos - k + 1.0, 1.0, dt)[0]
                last[e] = end
        if k >= 1.0:
            steps = k * float(live[0] + live[1])
            pos = pos - k
    tries = int(0)
    while pos > END:
        # Runs of VSA steps longer than a few: `ramp_jump` (tried again two steps after a jump, where constant steps
        # behind a medium turn into the ramp's).
        if vp.enabled != 0 and tries % 3 == 0 and tries < 9:
            pos, m, k, at = ramp_jump(pos, m, seg, slope, live, n, trans, check, next_t, product, vp, dt, min_t)
            if k > 0.0:
                steps += k * float(live[0] + live[1])
                jumped += k * float(live[0] + live[1])
                for e in range(2):
                    if live[e] != 0:
                        last[e] = at[e]
        tries += 1
        step = wp.min(m, pos)
        t = wp.vec2(0.0)
        for e in range(2):
            if live[e] != 0:
                t[e] = lattice_step(seg[e], pos, step, dt)[0]
                if t[e] >= check[e] or t[e] > next_t[e]:
                    return pos, m, steps, jumped, last
            elif trans[e] >= min_t and pos - step < float(n[e]):
                return pos, m, steps, jumped, last
        next_m = float(1.0)
        for e in range(2):
            if live[e] != 0:
                steps += 1.0
                last[e] = t[e]
                if vp.enabled != 0:
                    next_m = wp.max(next_m, vsa_ramp(t[e], slope[e], product[e]))
        pos = pos - step
        m = next_m
    return pos, m, steps, jumped, last


HORIZON_LOOKUPS = 32
"""`empty_horizon` follows at most this many empty cubes per call (a longer run is followed again at its end)"""
HORIZON_NUDGE = wp.constant(1.0e-2)
"""[skip cells] how far past an empty cube's exit `empty_horizon` looks up the next cell: far enough for float
rounding to land in the next cell, and well inside the half voxel beyond an empty cell that still reads zero
(`volren.upload.skip_grid`), so a step whose midpoint falls in that sliver is rightly taken as empty"""


@wp.func
def empty_horizon(vol: VolumeGPU, max_density: wp.array(dtype=float), o: wp.vec3, d: wp.vec3, inv: wp.vec3,
                  t: float, t_end: float, mode: int, acc: wp.vec4, inv_max: float, iso_value: float) -> float:
    """From the exit t of a skippable skip cell (or empty cube) of the ray ``o + t d`` (skip-cell coordinates),
    the ray distance up to which the cells that follow are skippable too: each next cell is looked up just past the
    last one's exit, until one that is not skippable, the segment's end t_end or HORIZON_LOOKUPS lookups.

    The coupled pair's idle run ends wherever either eye's next lookup falls due (`idle_run`); following an eye's
    empty cubes ahead of the lattice makes the run end only where an eye reaches a cell that is not empty, so the
    pair re-enters its loop and `ramp_jump` once per run of empty space instead of once per cube of either eye:
    idle runs per pair 8.2 -> 1.6 (smoke 128^3, 480x270 stereo). Which steps read 0 is unchanged (a step is
    skipped iff its midpoint lies in a skippable cube, as when each lookup waited for a step midpoint); in
    ``mode`` MIP the running max acc[0] cannot grow over the skipped steps, so the cells stay skippable."""
    nudge = HORIZON_NUDGE / wp.length(d)
    for _ in range(HORIZON_LOOKUPS):
        if t >= t_end:
            return t
        found = skip_lookup(vol, max_density, o + (t + nudge) * d, o, inv)
        if found[1] <= t + nudge or not skippable(mode, found[0], acc, inv_max, iso_value):
            return t
        t = found[1]
    return t


@wp.kernel
def coupled_march_kernel(job: CoupledJob, counter_rows: wp.array2d(dtype=wp.int64), row0: int):
    """One texel, both eyes (eye 1 only when job.eyes == 2): synchronised anchored steps, shared cell fetches; with
    translucent meshes each eye's ray is cut into its cube k-buffer's segments at the mesh layers of the pixel the
    texel projects to in that eye (`segment_advance`). Each eye's state is a row of small vectors and matrices, and
    one loop over the eyes serves both."""
    r, c = wp.tid()
    counters = counter_row(counter_rows, r, c)
    q = tile_texel(job.tiles, job.tile, job.apron, job.size, r + row0, c)
    if q[0] < 0:
        return
    vol, medium, params, vp, dt = job_constants(job)
    views = tile_views(job, (r + row0) / job.tile)
    texel = texel_index(q[0], q[1], q[2], job.size)
    x = wp.transform_point(vol.to_world, texel_point(q, job.size))
    # Per eye (row e): the ray (`pair_eye_ray`), and its state: accumulator, half-transmittance distance, MIDA's
    # running max, VSA's previous density and distance, the skip cell (next lookup distance, empty), the cube
    # k-buffer cursor (open segment, accumulator where it began, where it closes).
    seg = mat24()
    origin = mat23()
    d = mat23()
    o = mat23()
    dl = mat23()
    oc = mat23()
    dc = mat23()
    inv = mat23()
    n = wp.vec2i()
    pix = mat23i()
    base = wp.vec2i()
    next_t = wp.vec2()
    for e in range(2):
        ray = pair_eye_ray(job, e, views, vol, x, texel, dt)
        seg[e] = ray.seg
        origin[e] = ray.origin
        d[e] = ray.d
        o[e] = ray.o
        dl[e] = ray.dl
        oc[e] = ray.oc
        dc[e] = ray.dc
        inv[e] = ray.inv
        n[e] = ray.n
        pix[e] = ray.pix
        base[e] = ray.base
        next_t[e] = ray.next_t
    acc = mat24()
    snap = mat24()
    half = wp.vec2(INF)
    peak = wp.vec2(0.0)
    prev = wp.vec2(-1.0)
    prev_t = wp.vec2(0.0)
    # VSA: each eye's ramp per unit distance (`ramp_slope`) and the (T, product) of its last zero sample
    slope = wp.vec2(ramp_slope(vp, seg[0, 1]), ramp_slope(vp, seg[1, 1]))
    zero = mat22(-1.0, 0.0, -1.0, 0.0)
    check = wp.vec2(first_skip_check(vol, medium.skip))
    empty = wp.vec2i(0)
    j = wp.vec2i(0)
    for e in range(2):
        acc[e] = wp.vec4(0.0, 0.0, 0.0, 1.0)
        snap[e] = acc[e]
    samples = int(0)
    jumped = int(0)
    shared = int(0)
    skipped = int(0)
    idle_runs = int(0)
    shaded = int(0)
    share = job.share
    # VSA: the optical depth of a base step per unit density (Eq. 6's a).
    absorb = vol.density_scale * dt
    # The pair walks back from each eye's texel in units of the base step, front to back: pos base steps remain
    # before the texel, and each step covers m of them (m = 1: uniform steps on the texel-anchored lattice).
    pos = float(wp.max(n[0], n[1]))
    m = float(1.0)
    while pos > END:
        m = wp.min(m, pos)
        # Each eye's step while it is inside its segment (eye 1 is absent when marching one view alone), and its
        # trilinear cell (-1: none: not live, or in an empty skip cell). Empty-space skipping per eye (as
        # `march_volume_light_map`): the skip cell holding a step's midpoint is looked up when the step leaves the
        # last cell (or empty cube) looked up, and an empty one's successors are followed along the ray up to the
        # first that is not (`empty_horizon`); a step in an empty one reads density 0 without a fetch, exactly what
        # the fetch would read, so the lattice, VSA's proposals and the image are unchanged.
        live = wp.vec2i(0)
        s = mat22()
        p = mat23()
        f = mat23()
        cell = mat23i()
        # each eye's cell as one index (-1: none), compared for sharing: comparing the cells' rows read each back
        # from memory wider than it was written (a stalled store forward, 3% of the phantom's march)
        key = wp.vec2i(-1)
        idle = params.mode == MODE_DVR
        for e in range(2):
            if pos - m < float(n[e]) and acc[e, 3] >= params.min_transmittance:
                live[e] = 1
                s[e] = lattice_step(seg[e], pos, m, dt)
                if s[e, 0] >= check[e]:
                    found = skip_lookup(vol, medium.max_density, oc[e] + s[e, 0] * dc[e], oc[e], inv[e])
                    check[e] = found[1]
                    empty[e] = int(skippable(params.mode, found[0], acc[e], params.inv_max, params.iso_value))
                    if empty[e] != 0:
                        check[e] = empty_horizon(vol, medium.max_density, oc[e], dc[e], inv[e], check[e], seg[e, 1],
                                                 params.mode, acc[e], params.inv_max, params.iso_value)
                # the point and coordinates from registers, not read back from p's and f's rows (as for ``key``)
                pe = o[e] + s[e, 0] * dl[e]
                p[e] = pe
                if empty[e] == 0:
                    fe = grid_coords(vol.res, pe)
                    f[e] = fe
                    ce = grid_cell(vol.res, fe)
                    cell[e] = ce
                    key[e] = cell_index(vol.res, ce)
                # Idle: in an empty cell before the next mesh layer, DVR composites nothing for its density 0.
                idle = idle and empty[e] != 0 and s[e, 0] <= next_t[e]
        if live[0] + live[1] == 0:
            break
        rho = wp.vec2(0.0)
        if not idle:
            # Most steps are idle for both eyes (they cross empty space together): only the counters and VSA's
            # proposals then, without the sharing tests and compositing.
            both = live[0] + live[1] == 2
            if share != 0 and both and empty[0] + empty[1] == 1 and params.mode != MODE_MIP:
                # One eye in an empty skip cell: every trilinear cell read there is zero in all 8 voxels
                # (`volren.upload.skip_grid`), so where the other eye's sample falls in the same cell it reads 0
                # too, without a fetch (a coupled saving the eyes alone cannot make: the other eye's skip cell is
                # not empty). Iso skips cells below V, where reading 0 decides the same; MIP skips cells below the
                # eye's own max.
                blank = empty[1]
                key[blank] = cell_index(vol.res, grid_cell(vol.res, grid_coords(vol.res, p[blank])))
            same = both and share != 0 and key[0] == key[1]
            get = wp.vec2i(0)
            for e in range(2):
                get[e] = int(live[e] != 0 and empty[e] == 0 and not (same and empty[1 - e] != 0))
            if get[0] + get[1] == 2 and same:
                voxels = gather_density(medium.density, vol, cell[0])
                for e in range(2):
                    rho[e] = interpolate_cell(voxels, cell_fraction(f[e], cell[0]))
                shared += 1
            else:
                for e in range(2):
                    if get[e] != 0:
                        rho[e] = interpolate_cell(gather_density(medium.density, vol, cell[e]),
                                                  cell_fraction(f[e], cell[e]))
            for e in range(2):
                if live[e] != 0:
                    samples += get[e]
                    if s[e, 0] > next_t[e]:
                        mesh = pair_mesh(job, e)
                        open_seg, began = segment_advance(mesh, pix[e], pair_target(job, e), base[e], seg[e], j[e],
                                                          snap[e], acc[e], s[e, 0])
                        j[e] = open_seg
                        snap[e] = began
                        next_t[e] = next_layer_t(mesh, pix[e], open_seg, seg[e])
                    if params.mode == MODE_DVR:
                        # DVR's step of `mode_step` called directly (as `march_volume_light_map`): each call level
                        # copies the volume and medium structs it is passed.
                        if rho[e] > 0.0:
                            out = lit_step(acc[e], rho[e], vol, medium, p[e], origin[e] + s[e, 0] * d[e], d[e], s[e, 1],
                                           params.ambient)
                            half[e] = half_depth(half[e], acc[e, 3], out[3], s[e, 0])
                            acc[e] = out
                            shaded += 1
                    else:
                        out, top, lit, fetches, t_event = mode_step(acc[e], peak[e], rho[e], vol, medium, o[e], dl[e],
                                                                    origin[e], d[e], s[e, 0], s[e, 1],
                                                                    wp.max(s[e, 0] - dt, seg[e, 0]), params)
                        half[e] = half_depth(half[e], acc[e, 3], out[3], t_event)
                        acc[e] = out
                        peak[e] = top
                        shaded += lit
                        samples += fetches
                    skipped += 1 - get[e]
        else:
            skipped += live[0] + live[1]
        # VSA (Eq. 4-6): each live eye proposes the next step after its sample; the pair takes the larger.
        # A zero after a zero (rho' = 0) proposes the ramp over the product of a zero sample at the eye's T, kept
        # in ``zero`` until T changes (`zero_product`): the same proposal as `vsa_proposal`'s, bit for bit.
        next_m = float(1.0)
        for e in range(2):
            if vp.enabled != 0 and live[e] != 0:
                if rho[e] == 0.0 and prev[e] == 0.0:
                    zero[e] = zero_product(vp, zero[e], acc[e, 3], absorb)
                    next_m = wp.max(next_m, vsa_ramp(s[e, 0], slope[e], zero[e, 1]))
                else:
                    next_m = wp.max(next_m, vsa_proposal(vp, s[e, 0], slope[e], rho[e], prev[e], prev_t[e],
                                                         acc[e, 3], dt, absorb))
                prev[e] = rho[e]
                prev_t[e] = s[e, 0]
        pos = pos - m
        m = next_m
        if idle:
            # The steps after an idle one are mostly idle too: walk them without the rest of the loop
            # (`idle_run`); every live eye's last sample was 0, so its next proposals are Eq. 4's ramp over a
            # constant product.
            idle_runs += 1
            product = wp.vec2(1.0)
            for e in range(2):
                if vp.enabled != 0 and live[e] != 0:
                    zero[e] = zero_product(vp, zero[e], acc[e, 3], absorb)
                    product[e] = zero[e, 1]
            pos, m, ran, by_jumps, last = idle_run(pos, m, seg, slope, live, n, wp.vec2(acc[0, 3], acc[1, 3]), check,
                                                   next_t, product, vp, dt, params.min_transmittance)
            skipped += int(ran)
            jumped += int(by_jumps)
            for e in range(2):
                if live[e] != 0 and vp.enabled != 0 and ran > 0.0:
                    prev_t[e] = last[e]
    for e in range(2):
        pair_finish(job, e, views, texel, seg[e], acc[e], half[e], pix[e], base[e], j[e], snap[e])
    count(counters, DENSITY_SAMPLES, samples)
    count(counters, SHARED_SAMPLES, shared)
    count(counters, SKIPPED_STEPS, skipped)
    count(counters, JUMPED_STEPS, jumped)
    count(counters, IDLE_RUNS, idle_runs)
    count(counters, LIGHTMAP_LOOKUPS, shaded * medium.lights.shape[0])
    count(counters, RAYS, int(seg[0, 3] + seg[1, 3]))


def merge_lods(a: CubeLOD, b: CubeLOD) -> CubeLOD:
    """One LOD for a coupled pair: the finer level, and the larger face size and sample count of the two eyes."""
    finer = a if a.level <= b.level else b
    return replace(finer, size=max(a.size, b.size), samples=max(a.samples, b.samples),
                   edge_pixels=max(a.edge_pixels, b.edge_pixels))


class CACRM(CMSRM):
    """Coupled binocular cube-map ray marching; ``config`` is a `CACRMConfig`."""

    name = "cacrm"

    def __init__(self, config: CACRMConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or CACRMConfig(), device)

    def _vsa_on(self) -> bool:
        """VSA (and with it interleaving) in mode dvr only: Eq. 4-6's factors are fitted to DVR's transmittance and
        accumulated opacity; the other modes march the uniform texel-anchored lattice."""
        return self.config.vsa and self.config.mode == "dvr"

    def _vsa_params(self) -> VSAParams:
        c = self.config
        vp = VSAParams()
        vsa = self._vsa_on()
        vp.enabled = int(vsa)
        vp.k_a, vp.k_b, vp.f_lambda_max = (c.k_a, c.k_b, c.f_lambda_max) if vsa else (0.0, 1.0, 1.0)
        vp.w_lambda, vp.w_t, vp.w_a = (c.w_lambda, c.w_t, c.w_a) if vsa else (0.0, 0.0, 0.0)
        vp.lambda_cap = lambda_cap(vp.f_lambda_max, vp.w_lambda)
        return vp

    def _plan_views(self, ds: DeviceScene, views: list[Camera]) -> list[list[dict]]:
        """Per pair, one plan for both eyes: faces seen by either, the finer LOD, cube unless both would go direct."""
        plans = super()._plan_views(ds, views)
        for a, b in zip(plans[0::2], plans[1::2], strict=False):
            for pa, pb in zip(a, b, strict=True):
                merged = {
                    "faces": sorted(set(pa["faces"]) | set(pb["faces"])),
                    "lod": merge_lods(pa["lod"], pb["lod"]),
                    "scheme": max(pa["scheme"], pb["scheme"]),
                }
                merged["texels"] = len(merged["faces"]) * merged["lod"].size ** 2
                pa.update(merged)
                pb.update(merged)
        return plans

    def _view_groups(self, n: int) -> list[tuple[int, ...]]:
        """Coupled pairs (0, 1), (2, 3), ... and an odd last view alone; every view alone without coupling."""
        if not self.config.coupling:
            return super()._view_groups(n)
        return [tuple(range(v, min(v + 2, n))) for v in range(0, n, 2)]

    def _launch_march(self, ds: DeviceScene, views: list[Camera], group: tuple[int, ...], v: int, level: VolumeGPU,
                      tiles: TileGroup, samples: int, dest: list[CubeTarget], targets: list[ViewBuffers],
                      clock: PassClock) -> None:
        first, last = group[0], group[-1]
        # InS: one work item per 2x2 quad in the tiles where some quad can interleave; one per texel elsewhere.
        routes = [(coupled_march_kernel, tiles.origins, tiles.eyes, tiles.rows)]
        res = (level.res[0], level.res[1], level.res[2])
        if self.config.interleave and self._vsa_on() and base_step_reaches_a_voxel(samples, res):
            vol = ds.scene.volumes[v]
            origins = tiles.origins.numpy()
            quad = interleave_tiles(vol.to_world, [views[i].position for i in group], views[first].near, origins,
                                    tiles.rows, tiles.size, vol.diagonal / float(np.linalg.norm(res)))
            eyes = tiles.eyes.numpy()
            routes = [(kernel, wp.array(origins[mask], dtype=wp.vec3i, device=self.device),
                       wp.array(eyes[mask], dtype=int, device=self.device), cols)
                      for kernel, mask, cols in ((coupled_march_kernel, ~quad, tiles.rows),
                                                 (quad_march_kernel, quad, (tiles.rows + 1) // 2))
                      if mask.any()]
        job = CoupledJob()
        job.cam0, job.cam1 = camera_struct(views[first]), camera_struct(views[last])
        job.buffers0, job.buffers1 = targets[first], targets[last]
        job.mesh0, job.mesh1 = self._meshes[first], self._meshes[last]
        job.target0, job.target1 = dest[0], dest[-1]
        job.eyes, job.share = len(group), int(self.config.share_voxels)
        job.vol, job.tile, job.apron, job.size = level, tiles.rows, tiles.apron, tiles.size
        job.medium, job.params, job.vp = ds.medium(), self._params(ds, first, samples), self._vsa_params()
        for kernel, origins, eyes, cols in routes:
            job.tiles, job.tile_eyes = origins, eyes
            launch_rows(kernel, len(origins) * cols, cols, [job], self.device, clock.counters)

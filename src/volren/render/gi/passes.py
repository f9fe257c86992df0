"""Kernels of the per-voxel ambient GI (paper 000 §3.2): one thread per lighting-grid voxel of one volume.

The lighting grid of a volume has its light map's resolution. Per voxel it holds the SH coefficients
SH_j = integral of f_p(w) y_j(w) dw of the "phase function" f_p(w) = T(x, w), the transmittance from the voxel
towards the environment in direction w through every volume the ray crosses (found by the BVH over the volumes'
boxes, §3.2.3), isotropic in the outgoing direction as in the paper. Eq. 7 then gives the ambient in-scattering per
unit sigma_s, (1 / 4 pi) sum_j SH_j L_j, with L_j the environment's coefficients (1 / 4 pi: the isotropic phase, so
an unoccluded voxel gets the environment's mean radiance, the constant ambient of GI off).

Passes: `sample_kernel` (a uniform direction per voxel and its coarse or fine transmittance), `transform_kernel`
(3x3x3 reservoir resampling, Eq. 12, as resampled importance sampling: see `target`; fine march; SH projection
f y W; variance clamp and temporal accumulation, Eq. 8-11), `integrate_kernel` (Eq. 7); the baselines
`sphere_kernel` (brute force and PRT) and `major_kernel` (paper 001's major direction).
"""

from __future__ import annotations

import warp as wp

from volren.kernels.common import (
    INF,
    VolumeGPU,
    count,
    counter_row,
    sample_density,
    transmittance_bvh,
    voxel_center,
)
from volren.render.environment import EnvironmentLight, environment_radiance
from volren.render.frame import LIGHT_SAMPLES, RAYS
from volren.sh import sh_basis16, vec16

FOUR_PI = 4.0 * 3.14159265358979
NEGLIGIBLE = 1.0e-12
"""Eq. 12 as printed: transmittances below this are no candidates (keeps w_p = sum f / (M f*) finite)"""


@wp.struct
class GIScene:
    """What every GI pass reads: the volumes, their packed density and the BVH over their boxes."""

    volumes: wp.array(dtype=VolumeGPU)
    density: wp.array(dtype=float)
    bvh: wp.uint64
    v: int
    """the volume whose lighting grid is updated"""
    samples: int
    """L: at most this many samples across a box diagonal on each march"""


@wp.struct
class GIBuffers:
    """Per-voxel state of the lighting grids of all volumes, packed like the ambient grids (``ambient_offset``)."""

    dirs: wp.array(dtype=wp.vec3)
    """this frame's sample direction per voxel (sample pass)"""
    values: wp.array(dtype=float)
    """its transmittance (coarse for ours, fine for strict ReSTIR): the target function of the resampling"""
    sh: wp.array(dtype=float)
    """accumulated SH coefficients, ``order^2`` per voxel"""
    mu: wp.array(dtype=float)
    """last update's 3x3x3 coarse mean of f y / p per coefficient (Eq. 9 and 11's mu(n - 1))"""
    res_dir: wp.array(dtype=wp.vec3)
    """strict ReSTIR's temporal reservoir: chosen direction, its target value, weight sum and sample count"""
    res_value: wp.array(dtype=float)
    res_wsum: wp.array(dtype=float)
    res_m: wp.array(dtype=float)
    terms: wp.array(dtype=wp.vec3)
    """with ``record``: Eq. 10's inputs of the last update per coefficient, (SH_dst, SH_clamped, mu~)"""
    ambient: wp.array(dtype=wp.vec3)
    """output: ambient in-scattered radiance per unit sigma_s (Eq. 7)"""


@wp.struct
class Accumulation:
    """Eq. 8-11's parameters for one update of one volume."""

    order2: int
    n: int
    """updates of this volume before this one (0: no history)"""
    frames: int
    """N of lambda(n) = 1 / min(n + 1, N)"""
    k_gamma: float
    k_lambda: float
    w_dst: float
    w_clamped: float
    w_poly: float
    poly: wp.vec3
    """(a, b, c) of Eq. 10's cubic"""
    strict: int
    """1: strict ReSTIR (temporal reservoir reuse, fine targets)"""
    resampling: int
    """0: the voxel's own direction (no reuse); 1: Eq. 12 as printed (neighbours' coarse T, candidates with T below
    NEGLIGIBLE dropped); 2: RIS with the defensive target r = T~ l(w) + alpha"""
    record: int
    """1: write Eq. 10's inputs to ``terms`` (for fitting its weights)"""
    alpha: float
    """the defensive term of the RIS target (relative to the environment's mean luminance)"""
    cap: float
    """strict ReSTIR: the temporal reservoir's M is capped at cap times the spatial M"""
    seed: int


@wp.func
def voxel_index(sc: GIScene, row: int, i: int) -> int:
    """Packed index of voxel (i, row) of volume sc.v's lighting grid (row = k ny + j)."""
    vol = sc.volumes[sc.v]
    return vol.ambient_offset + row * vol.light_res[0] + i


@wp.func
def voxel_position(sc: GIScene, row: int, i: int) -> wp.vec3:
    """World position of voxel (i, row) of volume sc.v's lighting grid."""
    vol = sc.volumes[sc.v]
    res = vol.light_res
    k = row / res[1]
    return wp.transform_point(vol.to_world, voxel_center(i, row - k * res[1], k, res))


@wp.func
def uniform_sphere(u1: float, u2: float) -> wp.vec3:
    z = 1.0 - 2.0 * u1
    r = wp.sqrt(wp.max(1.0 - z * z, 0.0))
    phi = 2.0 * wp.pi * u2
    return wp.vec3(r * wp.cos(phi), z, r * wp.sin(phi))


@wp.func
def visibility(sc: GIScene, x: wp.vec3, d: wp.vec3, samples: int, counters: wp.array(dtype=wp.int64)) -> float:
    """f_p: transmittance from x towards the environment along d through every volume (counted as light samples)."""
    return transmittance_bvh(x, d, INF, sc.bvh, sc.volumes, sc.density, samples, counters, LIGHT_SAMPLES)


@wp.kernel
def sample_kernel(sc: GIScene, buf: GIBuffers, seed: int, counter_rows: wp.array2d(dtype=wp.int64), row0: int):
    """Sample-generation pass: a uniform random direction per voxel and its transmittance with ``sc.samples``."""
    r, i = wp.tid()
    counters = counter_row(counter_rows, r, i)
    idx = voxel_index(sc, r + row0, i)
    x = voxel_position(sc, r + row0, i)
    state = wp.rand_init(seed, idx)
    d = uniform_sphere(wp.randf(state), wp.randf(state))
    buf.dirs[idx] = d
    buf.values[idx] = visibility(sc, x, d, sc.samples, counters)
    count(counters, RAYS, 1)


@wp.func
def clamp_history(prev: float, mu: float, mu_prev: float, var: float, acc: Accumulation) -> float:
    """Eq. 9: SH_clamped, the history prev clamped to mu -+ gamma sigma with gamma = k_gamma / |mu(n) - mu(n - 1)|."""
    delta = wp.abs(mu - mu_prev)
    gamma = acc.k_gamma / wp.max(delta, 1.0e-6)
    spread = gamma * wp.sqrt(wp.max(var, 0.0))
    clamped = wp.clamp(prev, mu - spread, mu + spread)
    return clamped


@wp.func
def accumulate(prev: float, x: float, mu: float, mu_prev: float, var: float, acc: Accumulation) -> float:
    """Eq. 8-11 for one coefficient: the history prev calibrated by the variance clamp (Eq. 9) and the combination
    of Eq. 10, blended with this frame's estimate x by lambda(n) of Eq. 11. Eq. 8's w_SH stays 1 / p (x carries
    its own weight W, Eq. 12), so SH_dst(n - 1) = SH(n - 1)."""
    if acc.n == 0:
        return x
    delta = wp.abs(mu - mu_prev)
    clamped = clamp_history(prev, mu, mu_prev, var, acc)
    poly = ((mu + acc.poly[0]) * mu + acc.poly[1]) * mu + acc.poly[2]
    star = acc.w_dst * prev + acc.w_clamped * clamped + acc.w_poly * poly
    lam = wp.min((1.0 + acc.k_lambda * delta) / float(wp.min(acc.n + 1, acc.frames)), 1.0)
    return (1.0 - lam) * star + lam * x


@wp.func
def target(f: float, basis: vec16, luminance: vec16, acc: Accumulation) -> float:
    """The resampling weight r of a candidate direction w with transmittance f = T~(w). ``ris``: the target
    T~(w) l(w) / l_mean (l: the environment's luminance from its SH, so bright sky directions are preferred) plus
    the defensive alpha, positive for every candidate: whatever a neighbour's coarse T~ says, the RIS estimate stays
    unbiased (each candidate is a uniform direction and the selection probability r_i / sum r cancels in W) and
    bounded, f W <= 4 pi (1 + alpha) / alpha in a constant environment. ``eq12`` (as printed): r = T~, candidates
    below NEGLIGIBLE dropped, so W = sum T~ / (M T~*) grows without bound as T~* -> 0."""
    if acc.resampling == 1:
        if f > NEGLIGIBLE:
            return f
        return 0.0
    return f * wp.max(wp.dot(basis, luminance), 0.0) + acc.alpha


@wp.kernel
def transform_kernel(
    sc: GIScene, buf: GIBuffers, acc: Accumulation, luminance: vec16, counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """SH-transform pass: simplified reservoir resampling over the 3x3x3 neighbours' samples (Eq. 12 with the weights
    of `target`; strict ReSTIR also merges the voxel's temporal reservoir; ``resampling`` 0 keeps the voxel's own
    direction), a fine march along the chosen direction, its SH projection f y W (Eq. 8's w_p / p = W), and the
    temporal accumulation with the neighbours' coarse mean and variance (Eq. 8-11). ``luminance``: the
    environment's luminance over its mean, as SH coefficients."""
    r, i = wp.tid()
    counters = counter_row(counter_rows, r, i)
    row = r + row0
    idx = voxel_index(sc, row, i)
    x = voxel_position(sc, row, i)
    res = sc.volumes[sc.v].light_res
    k = row / res[1]
    j = row - k * res[1]
    state = wp.rand_init(acc.seed, idx)
    mean = vec16()
    square = vec16()
    neighbours = float(0.0)
    wsum = float(0.0)
    chosen = wp.vec3(0.0, 1.0, 0.0)
    chosen_f = float(0.0)
    for n in range(27):
        ii = i + n % 3 - 1
        jj = j + (n / 3) % 3 - 1
        kk = k + n / 9 - 1
        if ii >= 0 and ii < res[0] and jj >= 0 and jj < res[1] and kk >= 0 and kk < res[2]:
            other = idx + ((kk - k) * res[1] + (jj - j)) * res[0] + (ii - i)
            d = buf.dirs[other]
            f = buf.values[other]
            basis = sh_basis16(d)
            y = basis * (FOUR_PI * f)
            mean += y
            square += wp.cw_mul(y, y)
            neighbours += 1.0
            w = target(f, basis, luminance, acc)
            if w > 0.0:
                wsum += w
                if wp.randf(state) * wsum < w:
                    chosen = d
                    chosen_f = w
    mean = mean / neighbours
    var = square / neighbours - wp.cw_mul(mean, mean)
    m = neighbours
    if acc.resampling == 0:
        chosen = buf.dirs[idx]
        chosen_f = float(1.0)
        wsum = float(1.0)
        m = float(1.0)
    if acc.strict != 0:
        m_t = wp.min(buf.res_m[idx], acc.cap * neighbours)
        w_t = buf.res_wsum[idx] * m_t / wp.max(buf.res_m[idx], 1.0)
        if w_t > 0.0:
            wsum += w_t
            m += m_t
            if wp.randf(state) * wsum < w_t:
                chosen = buf.res_dir[idx]
                chosen_f = buf.res_value[idx]
    estimate = vec16()
    fine = float(0.0)
    basis = sh_basis16(chosen)
    if wsum > 0.0:
        # RIS: f(y) W with the unbiased contribution weight W = (1 / M) sum_i w_i / r(y), w_i = r_i / p and
        # p = 1 / 4 pi the uniform pdf every candidate was drawn with.
        fine = visibility(sc, x, chosen, sc.samples, counters)
        estimate = basis * (FOUR_PI * fine * (wsum / chosen_f) / m)
        count(counters, RAYS, 1)
    if acc.strict != 0:
        buf.res_dir[idx] = chosen
        buf.res_value[idx] = wp.max(target(fine, basis, luminance, acc), 1.0e-6)
        buf.res_wsum[idx] = wsum
        buf.res_m[idx] = m
    base = idx * acc.order2
    for c in range(16):
        if c < acc.order2:
            if acc.record != 0:
                buf.terms[base + c] = wp.vec3(
                    buf.sh[base + c], clamp_history(buf.sh[base + c], mean[c], buf.mu[base + c], var[c], acc), mean[c]
                )
            buf.sh[base + c] = accumulate(buf.sh[base + c], estimate[c], mean[c], buf.mu[base + c], var[c], acc)
            buf.mu[base + c] = mean[c]


@wp.kernel
def integrate_kernel(
    sc: GIScene, buf: GIBuffers, env_sh: wp.array(dtype=wp.vec3), order2: int, counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """Lighting-integration pass (Eq. 7): ambient = (1 / 4 pi) sum_j SH_j L_j, clamped at 0 (SH ringing)."""
    r, i = wp.tid()
    idx = voxel_index(sc, r + row0, i)
    out = wp.vec3(0.0)
    for c in range(16):
        if c < order2:
            out += buf.sh[idx * order2 + c] * env_sh[c]
    out = out / FOUR_PI
    buf.ambient[idx] = wp.vec3(wp.max(out[0], 0.0), wp.max(out[1], 0.0), wp.max(out[2], 0.0))


@wp.func
def basis_rule_size(i: int, n: int, projected: int) -> int:
    """Nodes of `basis_rule` for voxel i of n on an axis: 3 for the end functions, 2 otherwise; 1 (the centre)
    without ``projected``."""
    if projected == 0:
        return 1
    if n > 1 and (i == 0 or i == n - 1):
        return 3
    return 2


@wp.func
def basis_rule(i: int, n: int, j: int, projected: int) -> wp.vec2:
    """(local coordinate, weight) of node j of the Gauss rule whose weight function is the clamped linear basis
    function of voxel i of n on an axis (the weight trilinear lookups give that voxel): interior voxels a hat of
    half-width h = 2 / n about the centre (nodes +-h / sqrt(6)); the end voxels the constant 1 from the face to the
    centre, then the ramp to the next centre (3 nodes, for the field's steep fall from the face); one voxel the
    constant on [-1, 1]. Nodes and weights from the weight's moments; weights sum to 1. Without ``projected``: the
    voxel centre, weight 1."""
    h = 2.0 / float(n)
    if projected == 0:
        return wp.vec2(-1.0 + (float(i) + 0.5) * h, 1.0)
    if n == 1:
        return wp.vec2(wp.where(j == 0, -0.57735027, 0.57735027), 0.5)
    if i == 0 or i == n - 1:
        t = wp.where(j == 0, 0.14536447, wp.where(j == 1, 0.63032498, 1.18636298))
        w = wp.where(j == 0, 0.35738143, wp.where(j == 1, 0.49036715, 0.15225141))
        return wp.vec2(wp.where(i == 0, -1.0 + t * h, 1.0 - t * h), w)
    return wp.vec2(-1.0 + (float(i) + 0.5) * h + wp.where(j == 0, -0.40824829, 0.40824829) * h, 0.5)


@wp.kernel
def sphere_kernel(
    sc: GIScene, buf: GIBuffers, env: EnvironmentLight, rays: int, order2: int, seed: int, projected: int,
    counter_rows: wp.array2d(dtype=wp.int64), row0: int,
):
    """Brute force and PRT baselines: per voxel the basis-weighted means b = integral f phi / integral phi of the
    ambient field f (brute force: T L(w) averaged over directions, the ground truth, no SH; PRT: 4 pi T y_j), phi the
    voxel's trilinear basis function, by the product of `basis_rule` over the axes (8 to 27 points), ray n from
    point n mod P in direction n / P of the point's share of ``rays`` (z in equal bands, golden-angle azimuths,
    rotated randomly per point). `volren.render.gi.ambient.project_to_basis` turns b into the grid values whose
    trilinear interpolation is the field's L2 projection. Without ``projected`` (PRT, and brute force for comparing
    grids with the per-frame methods): the field at the voxel centre from all ``rays``."""
    r, i = wp.tid()
    counters = counter_row(counter_rows, r, i)
    row = r + row0
    idx = voxel_index(sc, row, i)
    vol = sc.volumes[sc.v]
    res = vol.light_res
    k = row / res[1]
    j = row - k * res[1]
    kx = basis_rule_size(i, res[0], projected)
    ky = basis_rule_size(j, res[1], projected)
    points = kx * ky * basis_rule_size(k, res[2], projected)
    coefficients = vec16()
    radiance = wp.vec3(0.0)
    for n in range(rays):
        p = n % points
        m = n / points
        share = (rays - p + points - 1) / points
        ax = basis_rule(i, res[0], p % kx, projected)
        ay = basis_rule(j, res[1], (p / kx) % ky, projected)
        az = basis_rule(k, res[2], p / (kx * ky), projected)
        x = wp.transform_point(vol.to_world, wp.vec3(ax[0], ay[0], az[0]))
        state = wp.rand_init(seed, idx * 27 + p)
        offset = wp.randf(state)
        turn = wp.randf(state)
        d = uniform_sphere((float(m) + offset) / float(share), float(m) * 0.38196601 + turn)
        weight = ax[1] * ay[1] * az[1] / float(share)
        t = visibility(sc, x, d, sc.samples, counters)
        coefficients += sh_basis16(d) * (t * weight)
        radiance += (t * weight) * environment_radiance(env, d)
    # points without a ray (rays < points): the others' weights renormalised
    covered = float(0.0)
    for p in range(wp.min(rays, points)):
        covered += (basis_rule(i, res[0], p % kx, projected)[1] * basis_rule(j, res[1], (p / kx) % ky, projected)[1]
                    * basis_rule(k, res[2], p / (kx * ky), projected)[1])
    count(counters, RAYS, rays)
    for c in range(16):
        if c < order2:
            buf.sh[idx * order2 + c] = coefficients[c] * FOUR_PI / covered
    buf.ambient[idx] = radiance / covered


@wp.kernel
def major_kernel(
    sc: GIScene, buf: GIBuffers, env_cosine: wp.array(dtype=wp.vec3), counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """Paper 001's simplified GI (the "M" of paper 000 Fig. 10): one march along the major direction n, the
    density's negative gradient (towards thinner medium), and the environment's cosine-weighted radiance about n
    (SH coefficients scaled by A_l / pi: an unoccluded voxel in a constant environment gets L) times T(x, n).
    Where the density is flat (no gradient) n is +y, the sky."""
    r, i = wp.tid()
    counters = counter_row(counter_rows, r, i)
    row = r + row0
    idx = voxel_index(sc, row, i)
    x = voxel_position(sc, row, i)
    vol = sc.volumes[sc.v]
    res = vol.light_res
    k = row / res[1]
    j = row - k * res[1]
    p = voxel_center(i, j, k, res)
    h = 1.0 / float(wp.max(wp.max(vol.res[0], vol.res[1]), vol.res[2]))
    g = wp.vec3(
        sample_density(sc.density, vol, p + wp.vec3(h, 0.0, 0.0))
        - sample_density(sc.density, vol, p - wp.vec3(h, 0.0, 0.0)),
        sample_density(sc.density, vol, p + wp.vec3(0.0, h, 0.0))
        - sample_density(sc.density, vol, p - wp.vec3(0.0, h, 0.0)),
        sample_density(sc.density, vol, p + wp.vec3(0.0, 0.0, h))
        - sample_density(sc.density, vol, p - wp.vec3(0.0, 0.0, h)),
    )
    # A world gradient is the local one times the inverse transform's transpose.
    m = vol.to_local
    gw = wp.vec3(
        m[0, 0] * g[0] + m[1, 0] * g[1] + m[2, 0] * g[2],
        m[0, 1] * g[0] + m[1, 1] * g[1] + m[2, 1] * g[2],
        m[0, 2] * g[0] + m[1, 2] * g[1] + m[2, 2] * g[2],
    )
    n = wp.vec3(0.0, 1.0, 0.0)
    if wp.length(gw) > 1.0e-6:
        n = -wp.normalize(gw)
    y = sh_basis16(n)
    lit = wp.vec3(0.0)
    for c in range(16):
        lit += y[c] * env_cosine[c]
    out = visibility(sc, x, n, sc.samples, counters) * lit
    count(counters, RAYS, 1)
    buf.ambient[idx] = wp.vec3(wp.max(out[0], 0.0), wp.max(out[1], 0.0), wp.max(out[2], 0.0))

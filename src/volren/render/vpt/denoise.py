"""The spatiotemporal DVR denoiser of paper 002 §5 (``--denoise ours``) and its baselines SVGF and WRLS.

Input per pixel: the path tracer's samples, each decoupled into two or three parts (Eq. 8, `tracer.SampleRecords`),
a high-detail-low-noise F_x times a low-detail-high-noise F_L each: part 0 the first collision's light samples
(F_x = A h, the albedo times the phase/BRDF value; F_L = T L / p), part 1 the rest (F_x = A, F_L = F_m: the uniform
ambient and every later scattering and emission, denoised like F_L as the paper says), and where some volume emits
part 2, the first collision's emission (F_x = its emitted radiance, material detail like A; F_L = 1: emission is not
modulated by the albedo, which may be 0), with the first collision's depth and scalar. The paper's second product,
the specular part, is here part 0 too: one SDF h holds both lobes (Eq. 5).
1. Clustering (§5.1): the hit samples of a pixel split in two at the largest gap of their sorted part-0 F_x
   luminances (one class when max - min < 0.1); each class k keeps n_k and per part the means F_x(C_k), F_L(C_k).
   Reprojection depth (§5.2): the nearest first-collision depth whose scalar exceeds 1/4 of the volume's maximum,
   else the median depth. Opacity alpha: the paths' mean ratio-tracked opacity of the camera ray (SampleRecords),
   not N_p / N: §5.3.3 itself recommends a lower-variance estimate at low spp. Along bench vpt's orbit (96x80,
   4 spp, against 256 spp) it raised ours from 27.25 to 27.28 dB with the depth-guided filter below unchanged.
   Holes (departure, not in the paper): a pixel none of whose samples hit has no classes and no depth, so neither
   the bilateral filters nor the reprojection reach it and it stays a black dot. When at least HOLE_NEIGHBOURS of
   its 8 neighbours have hits, it takes one class, their n-weighted mean, and their mean depth; alpha keeps its own
   ratio-tracked opacity (its paths missed the medium, the estimate did not). Fewer neighbours (outside a
   silhouette) leave it empty, so silhouettes do not grow a halo.
2. HDLN (§5.3.1), per part: a 3x3 joint bilateral over every class of the neighbours (Eq. 11, sigma_c = 0.2 on
   F_x, sigma_d on depth), then a temporal blend with the reprojected previous classes (Eq. 12, sigma_e = 0.2), the
   current class weighted 1. Two departures, because F_x = A h is not low-noise at a few spp: where the first
   collision lands in a semi-transparent layer sets P_brdf, n.l and A, so the per-path 4 pi h spreads by ~30% within
   a pixel (phantom, 64 spp: variance 0.28 about a mean of 1.71), and at 4 spp Eq. 11/12 at sigma 0.2 rejected
   almost every neighbour and history class (denoised F_x variance only 6% below the raw class means). (a) sigma_e
   grows by NOISE_Z standard errors of the pixel's mean F_x luminance (0 when its paths agree), so sampling noise
   does not reject the history while real changes (a turning light moves n.l) still do; (b) a history class weighs
   as many frames as it has accumulated (its Eq. 12 weight sum, capped at FRAMES_MAX), a running mean rather than
   an exponential one that keeps >= 1/3 on the current frame. Measured along bench vpt's orbit (96x80, 4 spp,
   against 256 spp) with the output variance of §6.4.3 (SVGF: 7.4): neither 27.93 dB, FLIP 0.0575, detail kept
   0.70, variance 14.0; z = 1 and 5 frames 28.23 dB, 0.0594, 0.67, 9.4; z = 1.75 and 4 frames (the constants)
   28.00 dB, 0.0643, 0.64, 6.5; z = 2 and 5 frames 27.87 dB, 0.0661, 0.63, 5.6. Rejected: the normal from a
   2-voxel gradient for the split only (13.5: the normal is not the noise), 8 extra unshadowed environment
   directions for h's weights (13.4).
3. LDHN (§5.3.2), per part: two edge-stopping a-trous passes (5x5, then 5x5 dilated by 2 = 9x9) guided by depth and
   the part's denoised F_x, then the sigmoid temporal weights of Eq. 13 (a = 3, b = 5), w_hat = 1 / S(a (change -
   1)) written as 1 + exp(-a (change - 1)). Departure: the change is |lu - lu_prev| relative to the two values'
   mean, in units of a 10% difference (CHANGE_UNIT). The paper's absolute difference assumes its own radiance
   scale: with display-range values it never leaves the sigmoid's flat end, the history keeps ~95% weight and the
   output lags (measured along bench vpt's orbit with a turning light, 96x80, 4 spp, against 256 spp: absolute
   19.6 dB, relative in units of 1 21.1 dB, of 0.2 25.6 dB, of 0.1 26.3 dB; SVGF 22.6 dB, raw 23.4 dB).
4. Opacity: Eq. 14 against the reprojected previous opacity. Departure: no 5x5 spatial bilateral. Guided by depth it
   averages a fringe pixel with hit neighbours only (pixels without hits have no depth), which at 4 spp biased the
   alpha of the 0.05-0.9 alpha band by +0.15 and blurred silhouettes; with the ratio-tracked alpha there is little
   noise left to filter. Measured along the orbit: depth-guided 27.28 dB, FLIP 0.0617, detail kept 0.57; none
   27.94 dB, FLIP 0.0575, detail 0.70; guided by alpha itself (sigma 0.05) the same as none.
5. Compositing (Eq. 15): alpha sum_k n_k sum_parts F_x(C_k) F_L(C_k) / sum_k n_k + (1 - alpha) B, B the surface
   behind.
Departures: depths are in metres, so sigma_d = 0.2 m stands for the paper's 2 decimetres; reprojection picks the
nearest previous pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from volren.kernels.common import INF, CameraGPU, ViewBuffers, camera_ray, project_pixel

SIGMA_C = 0.2
SIGMA_D = 0.2
"""[m] (the paper's 2 with decimetre units)"""
SIGMA_E = 0.2
NOISE_Z = 1.75
"""Eq. 12: sigma_e + NOISE_Z standard errors of the pixel's F_x (module docstring)"""
FRAMES_MAX = 4.0
"""Eq. 12: the most frames a denoised F_x class counts for"""
SIGMOID_A = 3.0
CHANGE_UNIT = 0.1
"""Eq. 13's luminance change is measured in units of this relative difference (see the module docstring)"""
WEIGHT_B = 5.0
SINGLE_CLASS = 0.1
"""one class when the F_x luminances of a pixel span less than this"""
DENSE = 0.25
"""reprojection depth: first collisions above this share of the volume's largest scalar"""
PARTS = 2
"""products F_x F_L per sample: the first collision's light samples, and the albedo times the rest (F_m); a third,
F_x = the first collision's emission, F_L = 1, where some volume emits (`EMISSION_PART`)"""
EMISSION_PART = 2
HOLE_NEIGHBOURS = 4
"""a pixel without hits is filled from its 8 neighbours when at least this many have hits"""


@wp.struct
class Classes:
    """Per pixel, two classes: per part F_x, F_L; n (float); and the pixel's alpha and reprojection depth."""

    f_x: wp.array4d(dtype=wp.vec3)
    """[row, col, class, part]"""
    f_l: wp.array4d(dtype=wp.vec3)
    n: wp.array3d(dtype=float)
    """[row, col, class]"""
    alpha: wp.array2d(dtype=float)
    depth: wp.array2d(dtype=float)
    fx_error: wp.array2d(dtype=float)
    """the standard error of the pixel's mean part-0 F_x luminance (0 with fewer than 2 hits)"""
    frames: wp.array4d(dtype=float)
    """[row, col, class, part] Eq. 12's accumulated weight of the denoised F_x (1 for a new class)"""


def new_classes(h: int, w: int, parts: int, device: str) -> Classes:
    c = Classes()
    c.f_x = wp.zeros((h, w, 2, parts), dtype=wp.vec3, device=device)
    c.f_l = wp.zeros((h, w, 2, parts), dtype=wp.vec3, device=device)
    c.n = wp.zeros((h, w, 2), dtype=float, device=device)
    c.alpha = wp.zeros((h, w), dtype=float, device=device)
    c.depth = wp.full((h, w), INF, dtype=float, device=device)
    c.fx_error = wp.zeros((h, w), dtype=float, device=device)
    c.frames = wp.ones((h, w, 2, parts), dtype=float, device=device)
    return c


def part_arrays(h: int, w: int, parts: int, device: str) -> wp.array4d:
    return wp.zeros((h, w, 2, parts), dtype=wp.vec3, device=device)


@wp.func
def luminance(c: wp.vec3) -> float:
    return 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]


@wp.kernel
def cluster_kernel(f_x: wp.array3d(dtype=wp.vec3), f_l: wp.array3d(dtype=wp.vec3), albedo: wp.array3d(dtype=wp.vec3),
                   f_m: wp.array3d(dtype=wp.vec3), emission: wp.array3d(dtype=wp.vec3), depth: wp.array3d(dtype=float),
                   density: wp.array3d(dtype=float), opacity: wp.array3d(dtype=float), out: Classes):
    """Step 1: two classes per pixel by the largest gap of the sorted F_x luminances; alpha; reprojection depth."""
    row, col = wp.tid()
    n = f_x.shape[2]
    hits = int(0)
    lo = float(INF)
    hi = float(-INF)
    dense_depth = float(INF)
    alpha = float(0.0)
    for i in range(n):
        alpha += opacity[row, col, i]
        if depth[row, col, i] >= 0.0:
            hits += 1
            lum = luminance(f_x[row, col, i])
            lo = wp.min(lo, lum)
            hi = wp.max(hi, lum)
            if density[row, col, i] > DENSE:
                dense_depth = wp.min(dense_depth, depth[row, col, i])
    out.alpha[row, col] = alpha / float(n)
    if hits == 0:
        out.depth[row, col] = INF
        return
    # The split: above the largest gap between consecutive sorted luminances (none when they span < 0.1).
    split = float(INF)
    if hi - lo >= SINGLE_CLASS:
        gap = float(-1.0)
        for i in range(n):
            if depth[row, col, i] >= 0.0:
                a = luminance(f_x[row, col, i])
                nxt = float(INF)
                for j in range(n):
                    if depth[row, col, j] >= 0.0:
                        b = luminance(f_x[row, col, j])
                        if b > a and b < nxt:
                            nxt = b
                if nxt < INF and nxt - a > gap:
                    gap = nxt - a
                    split = 0.5 * (a + nxt)
    for i in range(n):
        if depth[row, col, i] >= 0.0:
            k = int(0)
            if luminance(f_x[row, col, i]) > split:
                k = 1
            out.f_x[row, col, k, 0] = out.f_x[row, col, k, 0] + f_x[row, col, i]
            out.f_l[row, col, k, 0] = out.f_l[row, col, k, 0] + f_l[row, col, i]
            out.f_x[row, col, k, 1] = out.f_x[row, col, k, 1] + albedo[row, col, i]
            out.f_l[row, col, k, 1] = out.f_l[row, col, k, 1] + f_m[row, col, i]
            if out.f_x.shape[3] > EMISSION_PART:
                out.f_x[row, col, k, EMISSION_PART] = out.f_x[row, col, k, EMISSION_PART] + emission[row, col, i]
                out.f_l[row, col, k, EMISSION_PART] = out.f_l[row, col, k, EMISSION_PART] + wp.vec3(1.0)
            out.n[row, col, k] = out.n[row, col, k] + 1.0
    s1 = float(0.0)
    s2 = float(0.0)
    for i in range(n):
        if depth[row, col, i] >= 0.0:
            lum = luminance(f_x[row, col, i])
            s1 += lum
            s2 += lum * lum
    if hits > 1:
        mean = s1 / float(hits)
        out.fx_error[row, col] = wp.sqrt(wp.max(s2 / float(hits) - mean * mean, 0.0) / float(hits - 1))
    for k in range(2):
        m = out.n[row, col, k]
        if m > 0.0:
            for p in range(out.f_x.shape[3]):
                out.f_x[row, col, k, p] = out.f_x[row, col, k, p] / m
                out.f_l[row, col, k, p] = out.f_l[row, col, k, p] / m
    # Reprojection depth: the nearest dense first collision, else the median first-collision depth (by rank).
    if dense_depth < INF:
        out.depth[row, col] = dense_depth
        return
    target = (hits - 1) / 2
    for i in range(n):
        di = depth[row, col, i]
        if di >= 0.0:
            below = int(0)
            for j in range(n):
                dj = depth[row, col, j]
                if dj >= 0.0 and (dj < di or (dj == di and j < i)):
                    below += 1
            if below == target:
                out.depth[row, col] = di


@wp.kernel
def fill_holes_kernel(cur: Classes, out: Classes):
    """Step 1, holes: a pixel without hits but with >= HOLE_NEIGHBOURS hit neighbours of 8 gets one class, their
    n-weighted mean, and their mean depth (module docstring); every other pixel is copied."""
    row, col = wp.tid()
    h = cur.depth.shape[0]
    w = cur.depth.shape[1]
    out.alpha[row, col] = cur.alpha[row, col]
    out.depth[row, col] = cur.depth[row, col]
    out.fx_error[row, col] = cur.fx_error[row, col]
    for k in range(2):
        out.n[row, col, k] = cur.n[row, col, k]
        for p in range(cur.f_x.shape[3]):
            out.f_x[row, col, k, p] = cur.f_x[row, col, k, p]
            out.f_l[row, col, k, p] = cur.f_l[row, col, k, p]
    if cur.n[row, col, 0] + cur.n[row, col, 1] > 0.0:
        return
    neighbours = int(0)
    total = float(0.0)
    depth = float(0.0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            r = row + dy
            c = col + dx
            if r >= 0 and r < h and c >= 0 and c < w and (dy != 0 or dx != 0):
                m = cur.n[r, c, 0] + cur.n[r, c, 1]
                if m > 0.0:
                    neighbours += 1
                    depth += cur.depth[r, c]
                    total += m
    if neighbours < HOLE_NEIGHBOURS:
        return
    for p in range(cur.f_x.shape[3]):
        fx = wp.vec3(0.0)
        fl = wp.vec3(0.0)
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                r = row + dy
                c = col + dx
                if r >= 0 and r < h and c >= 0 and c < w:
                    for k in range(2):
                        fx += cur.n[r, c, k] * cur.f_x[r, c, k, p]
                        fl += cur.n[r, c, k] * cur.f_l[r, c, k, p]
        out.f_x[row, col, 0, p] = fx / total
        out.f_l[row, col, 0, p] = fl / total
    out.n[row, col, 0] = 1.0
    out.depth[row, col] = depth / float(neighbours)


@wp.func
def reproject(cam: CameraGPU, prev: CameraGPU, row: int, col: int, depth: float) -> wp.vec2i:
    """The previous frame's pixel (row, col) holding this pixel's point at linear depth ``depth``; -1 if none."""
    if depth >= INF:
        return wp.vec2i(-1, -1)
    d = camera_ray(cam, row, col, 0.5, 0.5)
    x = cam.origin + d * (depth / wp.dot(d, cam.forward))
    p = project_pixel(prev, x)
    c = int(wp.floor(p[0]))
    r = int(wp.floor(p[1]))
    if p[2] <= 0.0 or c < 0 or r < 0 or c >= prev.width or r >= prev.height:
        return wp.vec2i(-1, -1)
    return wp.vec2i(r, c)


@wp.kernel
def hdln_kernel(cur: Classes, cam: CameraGPU, prev_cam: CameraGPU, history: Classes, has_history: int,
                out: wp.array4d(dtype=wp.vec3), frames: wp.array4d(dtype=float)):
    """Step 2, per part: Eq. 11 over the 3x3 neighbours' classes, then Eq. 12 with the reprojected previous
    classes, each weighted by its accumulated frames, sigma_e widened by the F_x noise (module docstring)."""
    row, col = wp.tid()
    h = cur.depth.shape[0]
    w = cur.depth.shape[1]
    dj = cur.depth[row, col]
    src = wp.vec2i(-1, -1)
    if has_history != 0:
        src = reproject(cam, prev_cam, row, col, dj)
    for k in range(2):
        for p in range(cur.f_x.shape[3]):
            frames[row, col, k, p] = 1.0
            if cur.n[row, col, k] == 0.0:
                out[row, col, k, p] = wp.vec3(0.0)
                continue
            fk = cur.f_x[row, col, k, p]
            acc = wp.vec3(0.0)
            wsum = float(0.0)
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    r = wp.clamp(row + dy, 0, h - 1)
                    c = wp.clamp(col + dx, 0, w - 1)
                    for m in range(2):
                        if cur.n[r, c, m] > 0.0:
                            f = cur.f_x[r, c, m, p]
                            wgt = wp.exp(-wp.length(f - fk) / SIGMA_C) * wp.exp(
                                -wp.abs(cur.depth[r, c] - dj) / SIGMA_D)
                            acc += wgt * f
                            wsum += wgt
            spatial = acc / wsum
            blended = spatial
            if src[0] >= 0:
                num = spatial
                den = float(1.0)
                for m in range(2):
                    nm = history.n[src[0], src[1], m]
                    if nm > 0.0:
                        f = history.f_x[src[0], src[1], m, p]
                        # |grey difference| reads sqrt(3) x as a vec3 length: the luminance error to that scale.
                        sigma = SIGMA_E + NOISE_Z * wp.sqrt(3.0) * cur.fx_error[row, col]
                        wgt = wp.sqrt(1.0 / (wp.abs(cur.n[row, col, k] - nm) + 1.0)) * wp.exp(
                            -wp.length(spatial - f) / sigma) * history.frames[src[0], src[1], m, p]
                        num += wgt * f
                        den += wgt
                blended = num / den
                frames[row, col, k, p] = wp.min(den, FRAMES_MAX)
            out[row, col, k, p] = blended


@wp.func
def b3(i: int) -> float:
    """B3-spline taps 1/16, 1/4, 3/8, 1/4, 1/16 at offsets -2..2."""
    a = wp.abs(i)
    if a == 0:
        return 0.375
    if a == 1:
        return 0.25
    return 0.0625


@wp.kernel
def atrous_kernel(cur: Classes, f_x: wp.array4d(dtype=wp.vec3), src: wp.array4d(dtype=wp.vec3), step: int,
                  out: wp.array4d(dtype=wp.vec3)):
    """Step 3, spatial, per part: one edge-stopping a-trous pass (B3-spline 5x5 taps ``step`` pixels apart) on F_L,
    guided by depth and the part's denoised F_x."""
    row, col = wp.tid()
    h = cur.depth.shape[0]
    w = cur.depth.shape[1]
    dj = cur.depth[row, col]
    for k in range(2):
        for p in range(f_x.shape[3]):
            if cur.n[row, col, k] == 0.0:
                out[row, col, k, p] = wp.vec3(0.0)
                continue
            fk = f_x[row, col, k, p]
            acc = wp.vec3(0.0)
            wsum = float(0.0)
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    r = row + dy * step
                    c = col + dx * step
                    if r >= 0 and r < h and c >= 0 and c < w:
                        kernel = b3(dx) * b3(dy)
                        for m in range(2):
                            if cur.n[r, c, m] > 0.0:
                                wgt = kernel * wp.exp(-wp.length(f_x[r, c, m, p] - fk) / SIGMA_C) * wp.exp(
                                    -wp.abs(cur.depth[r, c] - dj) / SIGMA_D)
                                acc += wgt * src[r, c, m, p]
                                wsum += wgt
            out[row, col, k, p] = acc / wsum


@wp.kernel
def ldhn_temporal_kernel(cur: Classes, f_l: wp.array4d(dtype=wp.vec3), cam: CameraGPU, prev_cam: CameraGPU,
                         history: Classes, has_history: int, out: wp.array4d(dtype=wp.vec3)):
    """Step 3, temporal, per part: Eq. 13's sigmoid weights of the reprojected previous classes against
    w_k = 1 + b / sum."""
    row, col = wp.tid()
    src = wp.vec2i(-1, -1)
    if has_history != 0:
        src = reproject(cam, prev_cam, row, col, cur.depth[row, col])
    for k in range(2):
        for p in range(f_l.shape[3]):
            value = f_l[row, col, k, p]
            if src[0] >= 0 and cur.n[row, col, k] > 0.0:
                lu = luminance(value)
                num = wp.vec3(0.0)
                den = float(0.0)
                for m in range(2):
                    if history.n[src[0], src[1], m] > 0.0:
                        prev = history.f_l[src[0], src[1], m, p]
                        # |lu - lu_prev| relative to their mean, in units of CHANGE_UNIT (module docstring).
                        lp = luminance(prev)
                        change = wp.abs(lu - lp) / wp.max(CHANGE_UNIT * 0.5 * (lu + lp), 1.0e-4)
                        wgt = 1.0 + wp.exp(-SIGMOID_A * (change - 1.0))
                        num += wgt * prev
                        den += wgt
                wk = 1.0 + WEIGHT_B / (1.0e-6 + den)
                value = (wk * value + num) / (wk + den)
            out[row, col, k, p] = value


@wp.kernel
def alpha_kernel(cur: Classes, cam: CameraGPU, prev_cam: CameraGPU, history: Classes, has_history: int,
                 out: wp.array2d(dtype=float)):
    """Step 4: Eq. 14 against the reprojected previous alpha (no spatial filter: module docstring)."""
    row, col = wp.tid()
    a = cur.alpha[row, col]
    if has_history != 0:
        src = reproject(cam, prev_cam, row, col, cur.depth[row, col])
        if src[0] >= 0:
            prev = history.alpha[src[0], src[1]]
            e = wp.exp(-(1.0 + wp.abs(a - prev)))
            # Eq. 14 as printed subtracts the history; the blend it describes adds it: (a + e prev) / (1 + e).
            a = (a + e * prev) / (1.0 + e)
    out[row, col] = a


@wp.func
def write_over_surface(buffers: ViewBuffers, row: int, col: int, shade: wp.vec3, a: float):
    """The premultiplied pixel alpha * shade + (1 - alpha) * the opaque surface behind (Eq. 15's background)."""
    s = buffers.occluder_color[row, col]
    rgb = a * shade + (1.0 - a) * wp.vec3(s[0], s[1], s[2])
    buffers.image[row, col] = wp.vec4(rgb[0], rgb[1], rgb[2], a + (1.0 - a) * s[3])


@wp.func
def class_radiance(f_x: wp.array4d(dtype=wp.vec3), f_l: wp.array4d(dtype=wp.vec3), row: int, col: int,
                   k: int) -> wp.vec3:
    """sum over the parts of F_x F_L for class k (Eq. 8)."""
    r = wp.vec3(0.0)
    for p in range(f_x.shape[3]):
        r += wp.cw_mul(f_x[row, col, k, p], f_l[row, col, k, p])
    return r


@wp.func
def class_mean(values: wp.array4d(dtype=wp.vec3), n: wp.array3d(dtype=float), row: int, col: int,
               part: int) -> wp.vec3:
    """The pixel's two classes' values of one part averaged by their sample counts (0 without samples)."""
    total = n[row, col, 0] + n[row, col, 1]
    if total > 0.0:
        return (n[row, col, 0] * values[row, col, 0, part] + n[row, col, 1] * values[row, col, 1, part]) / total
    return wp.vec3(0.0)


@wp.func
def pixel_radiance(cur: Classes, row: int, col: int) -> wp.vec3:
    """The pixel's mean hit radiance, sum_k n_k sum_parts F_x F_L / sum_k n_k (0 without hits)."""
    shade = wp.vec3(0.0)
    total = float(0.0)
    for k in range(2):
        n = cur.n[row, col, k]
        shade += n * class_radiance(cur.f_x, cur.f_l, row, col, k)
        total += n
    if total > 0.0:
        shade = shade / total
    return shade


@wp.kernel
def composite_kernel(cur: Classes, f_x: wp.array4d(dtype=wp.vec3), f_l: wp.array4d(dtype=wp.vec3),
                     alpha: wp.array2d(dtype=float), buffers: ViewBuffers):
    """Step 5, Eq. 15: the classes' n-weighted sum of F_x F_L over the parts, over the surface colour by alpha
    (premultiplied)."""
    row, col = wp.tid()
    shade = wp.vec3(0.0)
    total = float(0.0)
    for k in range(2):
        n = cur.n[row, col, k]
        shade += n * class_radiance(f_x, f_l, row, col, k)
        total += n
    if total > 0.0:
        shade = shade / total
    write_over_surface(buffers, row, col, shade, alpha[row, col])


@dataclass
class History:
    classes: Classes
    camera: CameraGPU


class TemporalDenoiser:
    """What the denoisers share: per-view history, and step 1 (the samples clustered into classes, holes filled)."""

    def __init__(self, device: str) -> None:
        self.device = device
        self.history: dict[int, object] = {}

    def classes(self, records, h: int, w: int) -> Classes:
        """Step 1; a third part holds the first collision's emission where the records have it (`SampleRecords`)."""
        parts = PARTS + int(records.emission.shape == records.f_m.shape)
        cur = new_classes(h, w, parts, self.device)
        wp.launch(cluster_kernel, dim=(h, w), inputs=[records.f_x, records.f_l, records.albedo, records.f_m,
                                                       records.emission, records.depth, records.density,
                                                       records.opacity, cur], device=self.device)
        filled = new_classes(h, w, parts, self.device)
        wp.launch(fill_holes_kernel, dim=(h, w), inputs=[cur, filled], device=self.device)
        return filled


class Denoiser(TemporalDenoiser):
    """Runs steps 1-5 for one view and keeps that view's history (denoised classes, alpha, camera)."""

    def run(self, view: int, cam: CameraGPU, records, buffers: ViewBuffers) -> None:
        h, w = buffers.image.shape
        dev = self.device
        cur = self.classes(records, h, w)
        past = self.history.get(view)
        parts = cur.f_x.shape[3]
        valid = int(past is not None and past.classes.f_x.shape == cur.f_x.shape)
        prev_classes = past.classes if valid else cur
        prev_cam = past.camera if valid else cam
        f_x = part_arrays(h, w, parts, dev)
        frames = wp.empty((h, w, 2, parts), dtype=float, device=dev)
        wp.launch(hdln_kernel, dim=(h, w), inputs=[cur, cam, prev_cam, prev_classes, valid, f_x, frames], device=dev)
        first = part_arrays(h, w, parts, dev)
        second = part_arrays(h, w, parts, dev)
        wp.launch(atrous_kernel, dim=(h, w), inputs=[cur, f_x, cur.f_l, 1, first], device=dev)
        wp.launch(atrous_kernel, dim=(h, w), inputs=[cur, f_x, first, 2, second], device=dev)
        f_l = part_arrays(h, w, parts, dev)
        wp.launch(ldhn_temporal_kernel, dim=(h, w), inputs=[cur, second, cam, prev_cam, prev_classes, valid, f_l],
                  device=dev)
        alpha = wp.empty((h, w), dtype=float, device=dev)
        wp.launch(alpha_kernel, dim=(h, w), inputs=[cur, cam, prev_cam, prev_classes, valid, alpha], device=dev)
        wp.launch(composite_kernel, dim=(h, w), inputs=[cur, f_x, f_l, alpha, buffers], device=dev)
        denoised = Classes()
        denoised.f_x, denoised.f_l, denoised.n, denoised.alpha, denoised.depth = f_x, f_l, cur.n, alpha, cur.depth
        denoised.fx_error, denoised.frames = cur.fx_error, frames
        self.history[view] = History(denoised, cam)


# --- SVGF (Schied et al. 2017), a comparison baseline (``--denoise svgf``) -----------------------------------------
# On the albedo-demodulated illumination (per pixel: the hit samples' mean radiance over their mean first albedo A):
# temporal accumulation of the illumination and of its first two luminance moments (exponential weight 0.2,
# reprojected by the same depth as ours), variance from the moments (a 3x3 spatial estimate while the history is
# shorter than 4 frames), then 5 a-trous iterations (steps 1, 2, 4, 8, 16) with SVGF's edge-stopping on depth and on
# luminance relative to the filtered standard deviation (sigma_l = 4), the variance filtered along. Depth stands in
# for SVGF's normal and depth-gradient terms (volumes have no surface normal per pixel). Alpha is the unfiltered
# ratio-tracked opacity that ours gets.
SVGF_ALPHA = 0.2
SVGF_SIGMA_L = 4.0
SVGF_LEVELS = 5


@wp.func
def emitted(cur: Classes, row: int, col: int) -> wp.vec3:
    """The pixel's mean first-collision emission (0 without the emission part): not modulated by the albedo."""
    if cur.f_x.shape[3] > EMISSION_PART:
        return class_mean(cur.f_x, cur.n, row, col, EMISSION_PART)
    return wp.vec3(0.0)


@wp.func
def demodulated(cur: Classes, row: int, col: int) -> wp.vec3:
    """The pixel's mean hit radiance without the first collision's emission, divided by its mean first albedo, per
    channel (0 where the albedo is 0)."""
    a = class_mean(cur.f_x, cur.n, row, col, 1)
    r = pixel_radiance(cur, row, col) - emitted(cur, row, col)
    return wp.vec3(wp.where(a[0] > 0.0, r[0] / a[0], 0.0), wp.where(a[1] > 0.0, r[1] / a[1], 0.0),
                   wp.where(a[2] > 0.0, r[2] / a[2], 0.0))


@wp.kernel
def svgf_temporal_kernel(cur: Classes, cam: CameraGPU, prev_cam: CameraGPU, has_history: int,
                         prev_illum: wp.array2d(dtype=wp.vec3), prev_moments: wp.array2d(dtype=wp.vec3),
                         illum: wp.array2d(dtype=wp.vec3), moments: wp.array2d(dtype=wp.vec3)):
    """Accumulate illumination and (mean luminance, mean squared luminance, history length)."""
    row, col = wp.tid()
    light = demodulated(cur, row, col)
    lum = luminance(light)
    m = wp.vec3(lum, lum * lum, 1.0)
    if has_history != 0:
        src = reproject(cam, prev_cam, row, col, cur.depth[row, col])
        if src[0] >= 0:
            pm = prev_moments[src[0], src[1]]
            a = wp.max(SVGF_ALPHA, 1.0 / (pm[2] + 1.0))
            light = a * light + (1.0 - a) * prev_illum[src[0], src[1]]
            m = wp.vec3(a * lum + (1.0 - a) * pm[0], a * lum * lum + (1.0 - a) * pm[1], pm[2] + 1.0)
    illum[row, col] = light
    moments[row, col] = m


@wp.kernel
def svgf_variance_kernel(moments: wp.array2d(dtype=wp.vec3), variance: wp.array2d(dtype=float)):
    row, col = wp.tid()
    m = moments[row, col]
    v = wp.max(m[1] - m[0] * m[0], 0.0)
    if m[2] < 4.0:
        h = moments.shape[0]
        w = moments.shape[1]
        s1 = float(0.0)
        s2 = float(0.0)
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                q = moments[wp.clamp(row + dy, 0, h - 1), wp.clamp(col + dx, 0, w - 1)]
                s1 += q[0]
                s2 += q[1]
        v = wp.max(s2 / 9.0 - (s1 / 9.0) * (s1 / 9.0), 0.0)
    variance[row, col] = v


@wp.kernel
def svgf_atrous_kernel(depth: wp.array2d(dtype=float), illum: wp.array2d(dtype=wp.vec3),
                       variance: wp.array2d(dtype=float), step: int, out: wp.array2d(dtype=wp.vec3),
                       out_variance: wp.array2d(dtype=float)):
    row, col = wp.tid()
    h = illum.shape[0]
    w = illum.shape[1]
    lj = luminance(illum[row, col])
    dj = depth[row, col]
    sigma = SVGF_SIGMA_L * wp.sqrt(variance[row, col]) + 1.0e-6
    acc = wp.vec3(0.0)
    vacc = float(0.0)
    wsum = float(0.0)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            r = row + dy * step
            c = col + dx * step
            if r >= 0 and r < h and c >= 0 and c < w:
                dd = depth[r, c] - dj
                if dj >= INF and depth[r, c] >= INF:
                    dd = 0.0
                wgt = b3(dx) * b3(dy) * wp.exp(-wp.min(wp.abs(dd), 1.0e3) / SIGMA_D
                                               - wp.abs(luminance(illum[r, c]) - lj) / sigma)
                acc += wgt * illum[r, c]
                vacc += wgt * wgt * variance[r, c]
                wsum += wgt
    out[row, col] = acc / wsum
    out_variance[row, col] = vacc / (wsum * wsum)


@wp.kernel
def svgf_composite_kernel(cur: Classes, illum: wp.array2d(dtype=wp.vec3), buffers: ViewBuffers):
    row, col = wp.tid()
    shade = wp.cw_mul(class_mean(cur.f_x, cur.n, row, col, 1), illum[row, col]) + emitted(cur, row, col)
    write_over_surface(buffers, row, col, shade, cur.alpha[row, col])


class SVGF(TemporalDenoiser):
    """SVGF for one or more views, with their history (accumulated illumination, moments, camera)."""

    def run(self, view: int, cam: CameraGPU, records, buffers: ViewBuffers) -> None:
        h, w = buffers.image.shape
        dev = self.device
        cur = self.classes(records, h, w)
        past = self.history.get(view)
        valid = int(past is not None and past[0].shape == (h, w))
        prev_illum, prev_moments, prev_cam = past if valid else (
            wp.zeros((h, w), dtype=wp.vec3, device=dev), wp.zeros((h, w), dtype=wp.vec3, device=dev), cam)
        illum = wp.empty((h, w), dtype=wp.vec3, device=dev)
        moments = wp.empty((h, w), dtype=wp.vec3, device=dev)
        wp.launch(svgf_temporal_kernel, dim=(h, w), inputs=[cur, cam, prev_cam, valid, prev_illum, prev_moments, illum,
                                                             moments], device=dev)
        variance = wp.empty((h, w), dtype=float, device=dev)
        wp.launch(svgf_variance_kernel, dim=(h, w), inputs=[moments, variance], device=dev)
        src, var = illum, variance
        feedback = illum
        for level in range(SVGF_LEVELS):
            out = wp.empty((h, w), dtype=wp.vec3, device=dev)
            out_var = wp.empty((h, w), dtype=float, device=dev)
            wp.launch(svgf_atrous_kernel, dim=(h, w), inputs=[cur.depth, src, var, 1 << level, out, out_var],
                      device=dev)
            src, var = out, out_var
            if level == 0:
                feedback = out  # SVGF feeds the first a-trous level back as the colour history
        wp.launch(svgf_composite_kernel, dim=(h, w), inputs=[cur, src, buffers], device=dev)
        self.history[view] = (feedback, moments, cam)


# --- WRLS (Iglesias-Guitian, Mane, Moon 2020, paper 002's [8]), a comparison baseline (``--denoise wrls``) -------
# Per pixel a linear model of the mean hit radiance c over the noisy features x = (1, lum(A) - lum(A_j),
# (d - d_j) / sigma_d) (first albedo and reprojection depth, centred on the pixel's own), fitted by weighted
# recursive least squares: each frame the reprojected model (beta, P) is aged by the forgetting factor lambda
# (P <- P / lambda) and updated with the 3x3 neighbours' observations, each weighted by a Gaussian in pixel distance
# (k = w P x / (1 + w x^T P x), beta += (c - beta x) k^T, P -= k (P x)^T). The estimate is the model at the
# pixel's own features (beta's first column), and a final 3x3 depth/albedo bilateral smooths it (paper 002 §6.4.2:
# "WRLS incorporates bilateral filtering in the final stage"). A pixel whose model cannot be reprojected starts
# from beta = 0, P = WRLS_P0 I. When the centre moves, the model is re-expressed exactly (x_new = M x_old,
# beta_new = beta_old M^-1 (rows), P_new = M^-T P M^-1). Alpha is the unfiltered ratio-tracked opacity, as for
# SVGF. Departure: the original also fits the gradient normal; no per-pixel normal is recorded here.
WRLS_LAMBDA = 0.7
WRLS_P0 = 100.0
WRLS_SIGMA_X = 1.0
"""[px] the Gaussian weight of a neighbour's observation"""


@wp.struct
class WRLSModel:
    beta: wp.array2d(dtype=wp.mat33)
    """rows: the RGB channels' coefficients of (1, albedo luminance, depth)"""
    p: wp.array2d(dtype=wp.mat33)
    centre: wp.array2d(dtype=wp.vec2)
    """the features (albedo luminance, depth) the model is centred on; depth INF: no model"""


def new_wrls_model(h: int, w: int, device: str) -> WRLSModel:
    m = WRLSModel()
    m.beta = wp.zeros((h, w), dtype=wp.mat33, device=device)
    m.p = wp.zeros((h, w), dtype=wp.mat33, device=device)
    m.centre = wp.full((h, w), wp.vec2(0.0, INF), dtype=wp.vec2, device=device)
    return m


@wp.func
def wrls_features(cur: Classes, row: int, col: int) -> wp.vec2:
    return wp.vec2(luminance(class_mean(cur.f_x, cur.n, row, col, 1)), cur.depth[row, col])


@wp.kernel
def wrls_update_kernel(cur: Classes, cam: CameraGPU, prev_cam: CameraGPU, has_history: int, prev: WRLSModel,
                       out: WRLSModel, estimate: wp.array2d(dtype=wp.vec3)):
    """Reproject, age and update the pixel's model with its 3x3 neighbours' observations; estimate at its features."""
    row, col = wp.tid()
    h = cur.depth.shape[0]
    w = cur.depth.shape[1]
    centre = wrls_features(cur, row, col)
    out.centre[row, col] = centre
    if cur.n[row, col, 0] + cur.n[row, col, 1] == 0.0:
        out.beta[row, col] = wp.mat33(0.0)
        out.p[row, col] = wp.mat33(0.0)
        out.centre[row, col] = wp.vec2(0.0, INF)
        estimate[row, col] = wp.vec3(0.0)
        return
    beta = wp.mat33(0.0)
    p = WRLS_P0 * wp.identity(n=3, dtype=float)
    src = wp.vec2i(-1, -1)
    if has_history != 0:
        src = reproject(cam, prev_cam, row, col, centre[1])
    if src[0] >= 0:
        old = prev.centre[src[0], src[1]]
        if old[1] < INF:
            # x_new = M x_old with M = [[1, 0, 0], [-da, 1, 0], [-dd, 0, 1]] (the centre moved by da, dd).
            m = wp.mat33(1.0, 0.0, 0.0, -(centre[0] - old[0]), 1.0, 0.0, -(centre[1] - old[1]) / SIGMA_D, 0.0, 1.0)
            inv = wp.inverse(m)
            beta = prev.beta[src[0], src[1]] * inv
            p = wp.transpose(inv) * prev.p[src[0], src[1]] * inv / WRLS_LAMBDA
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            r = row + dy
            c = col + dx
            if r < 0 or r >= h or c < 0 or c >= w:
                continue  # no short-circuit evaluation in kernels: the bounds test comes first
            if cur.n[r, c, 0] + cur.n[r, c, 1] > 0.0:
                f = wrls_features(cur, r, c)
                x = wp.vec3(1.0, f[0] - centre[0], (f[1] - centre[1]) / SIGMA_D)
                wgt = wp.exp(-float(dx * dx + dy * dy) / (2.0 * WRLS_SIGMA_X * WRLS_SIGMA_X))
                px = p * x
                k = px * (wgt / (1.0 + wgt * wp.dot(x, px)))
                e = pixel_radiance(cur, r, c) - beta * x
                beta = beta + wp.outer(e, k)
                p = p - wp.outer(k, px)
    out.beta[row, col] = beta
    out.p[row, col] = p
    estimate[row, col] = wp.vec3(beta[0, 0], beta[1, 0], beta[2, 0])


@wp.kernel
def wrls_composite_kernel(cur: Classes, estimate: wp.array2d(dtype=wp.vec3), buffers: ViewBuffers):
    """The final 3x3 bilateral (depth and albedo luminance) of the estimates, over the surface by the raw alpha."""
    row, col = wp.tid()
    h = cur.depth.shape[0]
    w = cur.depth.shape[1]
    fj = wrls_features(cur, row, col)
    acc = wp.vec3(0.0)
    wsum = float(0.0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            r = row + dy
            c = col + dx
            if r < 0 or r >= h or c < 0 or c >= w:
                continue
            if cur.n[r, c, 0] + cur.n[r, c, 1] > 0.0:
                f = wrls_features(cur, r, c)
                wgt = wp.exp(-wp.abs(f[0] - fj[0]) / SIGMA_C - wp.abs(f[1] - fj[1]) / SIGMA_D)
                acc += wgt * estimate[r, c]
                wsum += wgt
    shade = wp.vec3(0.0)
    if wsum > 0.0:
        shade = acc / wsum
    write_over_surface(buffers, row, col, shade, cur.alpha[row, col])


class WRLS(TemporalDenoiser):
    """WRLS for one or more views, with their history (per-pixel models, camera)."""

    def run(self, view: int, cam: CameraGPU, records, buffers: ViewBuffers) -> None:
        h, w = buffers.image.shape
        dev = self.device
        cur = self.classes(records, h, w)
        past = self.history.get(view)
        valid = int(past is not None and past[0].beta.shape == (h, w))
        prev, prev_cam = past if valid else (new_wrls_model(h, w, dev), cam)
        model = new_wrls_model(h, w, dev)
        estimate = wp.empty((h, w), dtype=wp.vec3, device=dev)
        wp.launch(wrls_update_kernel, dim=(h, w), inputs=[cur, cam, prev_cam, valid, prev, model, estimate],
                  device=dev)
        wp.launch(wrls_composite_kernel, dim=(h, w), inputs=[cur, estimate, buffers], device=dev)
        self.history[view] = (model, cam)

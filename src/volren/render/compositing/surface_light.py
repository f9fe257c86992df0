"""Surfaces shaded by the volumes (issue 14 item 5): shadows from the light map and ambient occlusion, paper 000
Fig. 12's opacity-AO idea generalised from hair to any opaque surface.

Shadows. The light map (paper 001 §3, first pass; `volren.render.lightmap`) stores at each light-grid node the
optical depth from there to the light through the whole box (and, with GI on, through every other volume as well:
`cross_volume`). A surface point x outside a box reads it where its shadow ray enters the box, inside a box at x
itself; the outermost nodes lie on the faces, so the lookup at the entry covers the whole chord (issue 19 item 3:
no shell between the face and the nodes to march). Without GI each volume's map holds only its own
density, so the transmittances of every box the shadow ray meets (found by the BVH over the boxes) multiply; with
GI on the map of the first box along the ray already holds every volume behind it, so only that one is read (the
product would count the far volumes twice: two stacked slabs would give exp(-3 tau) instead of exp(-2 tau)).

Ambient occlusion. The surfaces' ambient stays albedo * L_ambient (the environment's mean radiance, as without
volumes) times AO(x, n) = (1 / pi) integral over the hemisphere about n of T(x, w) cos dw, the cosine-weighted
transmittance of the volumes towards the sky (opaque surfaces do not occlude the ambient, as before). With the GI
methods of `SH_AO_METHODS`, a point in or within `NEAR_VOXELS` light voxels of a box reads AO from the GI grid's SH
coefficients of T(x, w) (paper 000 Eq. 7's phase-function SH; `volren.render.gi.passes`), convolved with the clamped
cosine (factors A_l / pi = 1, 2/3, 1/4 per band, Ramamoorthi and Hanrahan 2001) and evaluated at n; elsewhere, and
with the other GI methods or none, AO comes from transmittance rays marched with 1/`AO_COARSE` of the light-map
samples (light-map-free), importance-sampled toward the volumes: AO = 1 - (1 / pi) integral of (1 - T(w)) max(n.w, 0)
dw, and 1 - T is zero outside each volume's occupied box (its non-empty skip cells, `occupied_boxes`), so the rays
are fixed uniform directions in the cone about those boxes seen from x (`box_cone`, several boxes' cones merged by
`cone_union`), weighted by omega cos / pi (omega: the cone's solid angle, 1 / pdf); directions below the horizon
weigh 0 and are not marched, and a point with no box above its horizon casts none. Each ray marches only its chord
through the occupied boxes (`ao_transmittance`). Narrow cones (cos theta >= `WIDEST_CONE`) take ``cone_rays``, wider
ones ``ao_rays``; a point inside an occupied box, or whose cone reaches 90 degrees, takes ``ao_rays`` fixed
cosine-distributed hemisphere directions (AO = their mean transmittance). The reference renderer samples the
hemisphere for every point with `REFERENCE_AO_RAYS` rays at full samples through the whole boxes and brute-force
shadow rays: the ground truth.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from volren.kernels.common import (
    INF,
    LightGPU,
    VolumeGPU,
    box_hit,
    cell_fraction,
    cell_index,
    corner_weight,
    count,
    grid_cell,
    grid_coords,
    optical_depth,
    transmittance_bvh,
)
from volren.render.frame import AO_BVH_QUERIES, LIGHT_SAMPLES, LIGHTMAP_LOOKUPS
from volren.render.lightmap import sample_light_map_across
from volren.sh import sh_basis16, vec16
from volren.upload import DeviceScene

SURFACE_UNLIT = wp.constant(0)
"""volumes neither shadow nor occlude surfaces (methods without a light map of their own: VPT, fog)"""
SURFACE_LIGHT_MAP = wp.constant(1)
SURFACE_BRUTE_FORCE = wp.constant(2)
AO_RAYS = 32
"""default cosine-distributed AO rays per surface point of the light-map methods where the hemisphere is sampled"""
AO_CONE_RAYS = 8
"""default AO rays per surface point that sees the volumes' occupied boxes in a cone narrower than `WIDEST_CONE`.
Measured on the smoke over a floor (96x54, default camera and from above, against 1024 hemisphere rays at full L):
max AO error 0.032 and 0.033, PSNR of the AO term 43.5 and 41.9 dB, against 0.040 and 0.037, 40.5 and 38.8 dB for
32 hemisphere rays everywhere (the estimator before); 4 cone rays: 40.6 and 38.3 dB. Surface pass at 320x180:
22-32 ms against 47-48 ms for the 32 hemisphere rays (CPU, 2 cores, shared with other jobs, min of 5, back to back;
0.69M AO samples against 1.34M): the points near the plume keep 32 rays and cost most"""
AO_COARSE = 8
"""the light-map methods' AO rays march with 1/AO_COARSE of the light samples: measured on the smoke over a floor
(32 rays), max AO error 0.0350 at L / 8 and 0.0353 at L / 4, mean 0.0099 and 0.0098, a third less time"""
REFERENCE_AO_RAYS = 256
SH_AO_METHODS = ("prt", "brute")
"""GI methods whose SH grid gives the surfaces' AO: those that project many rays per voxel. The per-frame methods'
coefficients are noisy in bands 1-2, which the cosine lobe weighs, and the clamp to [0, 1] near AO = 1 turns that
noise into darkening: measured on the smoke over a floor (16^3 grid), sresir darkened the floor under the plume
2.1 times as much as brute force after 16 frames (max error 0.57); PRT with 256 rays: 1.12 times, max 0.036."""
NEAR_VOXELS = wp.constant(1.0)
"""with GI on, points at most this many light voxels outside a box read AO from its SH grid"""
GOLDEN_ANGLE = wp.constant(2.39996323)
NO_CONE = wp.constant(2.0)
"""cone "cos theta" of no box above the horizon"""
WIDE_CONE = wp.constant(-2.0)
"""cone "cos theta" where the AO rays take the whole hemisphere (x inside an occupied box, or a cone of 90 degrees
or more: not convex)"""
WIDEST_CONE = wp.constant(0.7)
"""cones wider than this cos theta (45.6 degrees: points near a box) take ``ao_rays`` uniform rays, narrower ones
``cone_rays``. Measured on the smoke over a floor (96x54, 8 cone rays, against 1024 hemisphere rays): max AO error
0.045 with 0.5 and wide cones on the hemisphere rays, 0.032 with 0.7 and wide cones on 32 cone rays (16: 0.094)"""


@wp.struct
class SurfaceLight:
    """What the surface pass reads to let the volumes shade the surfaces."""

    mode: int
    """SURFACE_UNLIT, SURFACE_LIGHT_MAP or SURFACE_BRUTE_FORCE (shadow rays through the density)"""
    volumes: wp.array(dtype=VolumeGPU)
    density: wp.array(dtype=float)
    lightmap: wp.array(dtype=float)
    bvh: wp.uint64
    cross_volume: int
    """1: each light map already holds every volume between its voxels and the light (GI on)"""
    samples: int
    """L: at most this many samples across a box diagonal on shadow rays and the light-map shell"""
    ao_rays: int
    """AO rays per surface point that samples the hemisphere (brute force, or a point in or beside a volume)"""
    cone_rays: int
    """AO rays per surface point that sees the volumes in a cone (`box_cone`)"""
    ao_samples: int
    """L of the AO rays"""
    occupied: wp.array2d(dtype=float)
    """per volume the local box (x0, y0, z0, x1, y1, z1) outside which its density reads zero (`occupied_boxes`)"""
    sh: wp.array(dtype=float)
    """the GI grid's SH coefficients of T(x, w), ``order2`` per light voxel (packed like the ambient grids)"""
    order2: int
    """0: no SH grid (GI off, or a GI method without coefficients)"""


@wp.kernel
def occupied_kernel(volumes: wp.array(dtype=VolumeGPU), max_density: wp.array(dtype=float),
                    boxes: wp.array2d(dtype=float)):
    v, i = wp.tid()
    vol = volumes[v]
    r = vol.skip_res
    if i >= r[0] * r[1] * r[2] or max_density[vol.skip_offset + i] <= 0.0:
        return
    cell = wp.vec3i(i % r[0], (i / r[0]) % r[1], i / (r[0] * r[1]))
    for a in range(3):
        # the cell's voxels widened by one: a trilinear sample reads voxels within one of the one holding it
        lo = -1.0 + 2.0 * float(cell[a] * vol.skip_cell - 1) / float(vol.res[a])
        hi = -1.0 + 2.0 * float((cell[a] + 1) * vol.skip_cell + 1) / float(vol.res[a])
        wp.atomic_min(boxes, v, a, wp.max(lo, -1.0))
        wp.atomic_max(boxes, v, a + 3, wp.min(hi, 1.0))


def occupied_boxes(ds: DeviceScene) -> wp.array2d:
    """Per volume the local box of its non-empty skip cells (`volren.upload.skip_grid`, level 0), widened by a
    voxel: its density reads zero outside, so the AO rays aim there (an empty volume gets an empty box, lo > hi)."""
    n = len(ds.levels)
    init = np.tile(np.array([2.0, 2.0, 2.0, -2.0, -2.0, -2.0], np.float32), (max(n, 1), 1))
    boxes = wp.array(init, dtype=float, device=ds.device)
    cells = max((int(np.prod(lv[0].skip_res)) for lv in ds.levels), default=0)
    if n and cells:
        wp.launch(occupied_kernel, (n, cells), [ds.volumes, ds.max_density, boxes], device=ds.device)
    return boxes


def surface_light(ds: DeviceScene, mode: int, samples: int = 1, ao_rays: int = 0, ao_samples: int = 1,
                  cross_volume: bool = False, sh: wp.array | None = None, order2: int = 0,
                  cone_rays: int = 0) -> SurfaceLight:
    """``cone_rays`` 0: every point samples the hemisphere with ``ao_rays`` (the reference's brute force)."""
    s = SurfaceLight()
    s.mode, s.volumes, s.density, s.lightmap, s.bvh = mode, ds.volumes, ds.density, ds.lightmap, ds.volume_bvh.id
    s.cross_volume, s.samples, s.ao_rays, s.ao_samples = int(cross_volume), samples, ao_rays, ao_samples
    s.cone_rays = cone_rays
    s.occupied = occupied_boxes(ds) if cone_rays > 0 else wp.zeros((1, 6), dtype=float, device=ds.device)
    s.sh = sh if sh is not None else wp.zeros(1, dtype=float, device=ds.device)
    s.order2 = order2 if sh is not None else 0
    return s


def unlit(ds: DeviceScene) -> SurfaceLight:
    return surface_light(ds, SURFACE_UNLIT)


@wp.func
def light_map_transmittance(sl: SurfaceLight, vol: VolumeGPU, li: int, x: wp.vec3, to_light: wp.vec3, t0: float,
                            t1: float, counters: wp.array(dtype=wp.int64)) -> float:
    """T from x + t0 to_light (the box entry, or x inside the box) to light li, the chord running to t1: the light
    map of ``vol`` read there."""
    o_l = wp.transform_point(vol.to_local, x)
    d_l = wp.transform_vector(vol.to_local, to_light)
    res = vol.light_res
    count(counters, LIGHTMAP_LOOKUPS, 1)
    n = res[0] * res[1] * res[2]
    return sample_light_map_across(sl.lightmap, vol.light_offset + 2 * li * n, n, res, o_l + t0 * d_l, t1 - t0,
                                   sl.cross_volume)


@wp.func
def volume_shadow(sl: SurfaceLight, li: int, light: LightGPU, x: wp.vec3, to_light: wp.vec3, dist: float,
                  counters: wp.array(dtype=wp.int64)) -> float:
    """Transmittance of the volumes between surface point x and light li (``dist``: distance to the light)."""
    if sl.mode == SURFACE_UNLIT:
        return 1.0
    if sl.mode == SURFACE_BRUTE_FORCE:
        return transmittance_bvh(x, to_light, dist, sl.bvh, sl.volumes, sl.density, sl.samples, counters,
                                 LIGHT_SAMPLES)
    product = float(1.0)
    first_t = float(INF)
    first = float(1.0)
    query = wp.bvh_query_ray(sl.bvh, x, to_light)
    v = int(0)
    while wp.bvh_query_next(query, v):
        vol = sl.volumes[v]
        h = box_hit(wp.transform_point(vol.to_local, x), wp.transform_vector(vol.to_local, to_light))
        t0 = wp.max(h[0], 0.0)
        t1 = wp.min(h[1], dist)
        if t1 > t0:
            tv = light_map_transmittance(sl, vol, li, x, to_light, t0, t1, counters)
            product *= tv
            if t0 < first_t:
                first_t = t0
                first = tv
    if sl.cross_volume != 0:
        return first
    return product


@wp.func
def tangent_frame(n: wp.vec3) -> wp.mat33:
    """Columns (t, b, n): an orthonormal basis about unit n without branches on its direction (Duff et al. 2017)."""
    s = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    t = wp.vec3(1.0 + s * n[0] * n[0] * a, s * b, -s * n[0])
    u = wp.vec3(b, s + n[1] * n[1] * a, -n[1])
    return wp.mat33(t[0], u[0], n[0], t[1], u[1], n[1], t[2], u[2], n[2])


@wp.func
def cosine_direction(frame: wp.mat33, k: int, rays: int) -> wp.vec3:
    """Direction k of ``rays`` fixed cosine-distributed ones about the frame's normal (a Fibonacci spiral in the
    projected disk: equal areas of the disk carry equal cosine-weighted solid angle)."""
    r2 = (float(k) + 0.5) / float(rays)
    r = wp.sqrt(r2)
    phi = float(k) * GOLDEN_ANGLE
    return frame * wp.vec3(r * wp.cos(phi), r * wp.sin(phi), wp.sqrt(1.0 - r2))


@wp.func
def cone_direction(frame: wp.mat33, cos_max: float, k: int, rays: int) -> wp.vec3:
    """Direction k of ``rays`` fixed uniform ones in the cone cos theta >= cos_max about the frame's third axis (a
    Fibonacci spiral: uniform in cos theta, golden-angle steps in phi)."""
    ct = 1.0 - (float(k) + 0.5) / float(rays) * (1.0 - cos_max)
    st = wp.sqrt(wp.max(1.0 - ct * ct, 0.0))
    phi = float(k) * GOLDEN_ANGLE
    return frame * wp.vec3(st * wp.cos(phi), st * wp.sin(phi), ct)


@wp.func
def sh_cosine_visibility(sl: SurfaceLight, vol: VolumeGPU, p: wp.vec3, n: wp.vec3) -> float:
    """(1 / pi) integral of T(x, w) max(n.w, 0) dw from the GI grid's SH coefficients of T, trilinear at local p."""
    y = sh_basis16(n)
    lobe = vec16()
    for c in range(16):
        band = wp.where(c < 1, 1.0, wp.where(c < 4, 2.0 / 3.0, wp.where(c < 9, 0.25, 0.0)))
        lobe[c] = band * y[c]
    res = vol.light_res
    f = grid_coords(res, p)
    cell = grid_cell(res, f)
    a = cell_fraction(f, cell)
    base = vol.ambient_offset + cell_index(res, cell)
    total = float(0.0)
    for corner in range(8):
        idx = base + (corner / 4) * res[0] * res[1] + ((corner / 2) % 2) * res[0] + corner % 2
        s = float(0.0)
        for c in range(16):
            if c < sl.order2:
                s += sl.sh[idx * sl.order2 + c] * lobe[c]
        total += corner_weight(corner, a) * s
    return wp.clamp(total, 0.0, 1.0)


@wp.func
def box_cone(sl: SurfaceLight, v: int, x: wp.vec3, n: wp.vec3) -> wp.vec4:
    """(axis, cos theta) of the cone about the direction from x to the centre of volume v's occupied box that holds
    the box's 8 corners, so every direction into the box (their convex hull: with theta < 90 degrees the cone is
    convex). cos theta = NO_CONE: the box is empty or lies below x's tangent plane (no direction into it has
    n.w > 0); WIDE_CONE: x is inside it."""
    vol = sl.volumes[v]
    lo = wp.vec3(sl.occupied[v, 0], sl.occupied[v, 1], sl.occupied[v, 2])
    hi = wp.vec3(sl.occupied[v, 3], sl.occupied[v, 4], sl.occupied[v, 5])
    if lo[0] > hi[0]:
        return wp.vec4(n[0], n[1], n[2], NO_CONE)
    p = wp.transform_point(vol.to_local, x)
    if p[0] >= lo[0] and p[0] <= hi[0] and p[1] >= lo[1] and p[1] <= hi[1] and p[2] >= lo[2] and p[2] <= hi[2]:
        return wp.vec4(n[0], n[1], n[2], WIDE_CONE)
    axis = wp.normalize(wp.transform_point(vol.to_world, 0.5 * (lo + hi)) - x)
    cos_max = float(1.0)
    above = bool(False)
    for c in range(8):
        local = wp.vec3(wp.where(c % 2 == 0, lo[0], hi[0]), wp.where((c / 2) % 2 == 0, lo[1], hi[1]),
                        wp.where(c / 4 == 0, lo[2], hi[2]))
        d = wp.transform_point(vol.to_world, local) - x
        above = above or wp.dot(d, n) > 0.0
        cos_max = wp.min(cos_max, wp.dot(axis, d) / wp.length(d))
    if not above:
        return wp.vec4(axis[0], axis[1], axis[2], NO_CONE)
    return wp.vec4(axis[0], axis[1], axis[2], cos_max)


@wp.func
def ao_transmittance(sl: SurfaceLight, x: wp.vec3, w: wp.vec3, counters: wp.array(dtype=wp.int64)) -> float:
    """T along an AO ray through every volume the BVH reports, each marched only over its chord through the occupied
    box (the density is zero outside it, so T is that of `transmittance_bvh` with fewer samples: the step stays
    diagonal / L, the chord is shorter)."""
    tau = float(0.0)
    fetched = float(0.0)
    query = wp.bvh_query_ray(sl.bvh, x, w)
    v = int(0)
    while wp.bvh_query_next(query, v):
        vol = sl.volumes[v]
        lo = wp.vec3(sl.occupied[v, 0], sl.occupied[v, 1], sl.occupied[v, 2])
        hi = wp.vec3(sl.occupied[v, 3], sl.occupied[v, 4], sl.occupied[v, 5])
        if lo[0] <= hi[0]:
            # the occupied box's slab test in the local frame, scaled to [-1, 1]^3
            half = 0.5 * (hi - lo)
            o_b = wp.cw_div(wp.transform_point(vol.to_local, x) - 0.5 * (lo + hi), half)
            h = box_hit(o_b, wp.cw_div(wp.transform_vector(vol.to_local, w), half))
            t0 = wp.max(h[0], 0.0)
            if h[1] > t0:
                r = optical_depth(vol, x + t0 * w, w, h[1] - t0, sl.density, sl.ao_samples)
                tau += r[0]
                fetched += r[1]
    count(counters, LIGHT_SAMPLES, int(fetched))
    return wp.exp(-tau)


@wp.func
def cone_union(a: wp.vec4, b: wp.vec4) -> wp.vec4:
    """The narrowest cone holding cones a and b, each (axis, cos theta) with theta < 90 degrees (Conty Estevez and
    Kulla 2018, Alg. 1); cos theta = WIDE_CONE when it would reach 90 degrees."""
    if a[3] == NO_CONE:
        return b
    ua = wp.vec3(a[0], a[1], a[2])
    ub = wp.vec3(b[0], b[1], b[2])
    ta = wp.acos(a[3])
    tb = wp.acos(b[3])
    td = wp.acos(wp.clamp(wp.dot(ua, ub), -1.0, 1.0))
    if ta >= td + tb:
        return a
    if tb >= td + ta:
        return b
    to = 0.5 * (ta + td + tb)
    if to >= 0.5 * wp.pi:
        return wp.vec4(ua[0], ua[1], ua[2], WIDE_CONE)
    # rotate a's axis towards b's by to - ta (td > 0 here: equal axes keep the wider cone above)
    perp = wp.normalize(ub - wp.dot(ua, ub) * ua)
    axis = wp.cos(to - ta) * ua + wp.sin(to - ta) * perp
    return wp.vec4(axis[0], axis[1], axis[2], wp.cos(to))


@wp.func
def ambient_occlusion(sl: SurfaceLight, x: wp.vec3, n: wp.vec3, counters: wp.array(dtype=wp.int64)) -> float:
    """AO(x, n) of the volumes: the factor on the surfaces' ambient term (module docstring)."""
    if sl.mode == SURFACE_UNLIT:
        return 1.0
    if sl.order2 > 0:
        nearest = int(-1)
        best = float(INF)
        for v in range(sl.volumes.shape[0]):
            vol = sl.volumes[v]
            p = wp.transform_point(vol.to_local, x)
            res = vol.light_res
            # outside distance in light voxels (2 / res local units each)
            out = wp.max(wp.max(0.5 * float(res[0]) * (wp.abs(p[0]) - 1.0), 0.5 * float(res[1]) * (wp.abs(p[1]) - 1.0)),
                         0.5 * float(res[2]) * (wp.abs(p[2]) - 1.0))
            if out <= NEAR_VOXELS and out < best:
                best = out
                nearest = v
        if nearest >= 0:
            vol = sl.volumes[nearest]
            count(counters, LIGHTMAP_LOOKUPS, 1)
            return sh_cosine_visibility(sl, vol, wp.transform_point(vol.to_local, x), n)
    if sl.ao_rays == 0:
        return 1.0
    cone = wp.vec4(0.0, 0.0, 0.0, NO_CONE)
    if sl.cone_rays == 0:
        cone = wp.vec4(n[0], n[1], n[2], WIDE_CONE)
    else:
        for v in range(sl.volumes.shape[0]):
            c = box_cone(sl, v, x, n)
            if c[3] != NO_CONE and cone[3] != WIDE_CONE:
                cone = wp.where(c[3] <= 0.0, wp.vec4(c[0], c[1], c[2], WIDE_CONE), cone_union(cone, c))
    if cone[3] == NO_CONE:
        return 1.0  # no box above the horizon: nothing to march
    total = float(0.0)
    if cone[3] == WIDE_CONE:
        # cosine-distributed directions over the hemisphere: pdf cos / pi, so AO is the mean transmittance
        count(counters, AO_BVH_QUERIES, sl.ao_rays)
        frame = tangent_frame(n)
        for k in range(sl.ao_rays):
            w = cosine_direction(frame, k, sl.ao_rays)
            if sl.cone_rays == 0:
                total += transmittance_bvh(x, w, INF, sl.bvh, sl.volumes, sl.density, sl.ao_samples, counters,
                                           LIGHT_SAMPLES)
            else:
                total += ao_transmittance(sl, x, w, counters)
        return total / float(sl.ao_rays)
    rays = wp.where(cone[3] < WIDEST_CONE, sl.ao_rays, sl.cone_rays)
    count(counters, AO_BVH_QUERIES, rays)
    # Uniform directions in the cone (pdf 1 / omega): 1 - T vanishes outside it, so AO = 1 - (omega / pi) E[(1 - T)
    # max(n.w, 0)]; directions below the horizon weigh 0 and are not marched.
    frame = tangent_frame(wp.vec3(cone[0], cone[1], cone[2]))
    for k in range(rays):
        w = cone_direction(frame, cone[3], k, rays)
        cos_n = wp.dot(w, n)
        if cos_n > 0.0:
            total += (1.0 - ao_transmittance(sl, x, w, counters)) * cos_n
    omega = 2.0 * wp.pi * (1.0 - cone[3])
    return wp.max(1.0 - omega * total / (wp.pi * float(rays)), 0.0)

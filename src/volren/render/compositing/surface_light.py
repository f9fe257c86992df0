"""Surfaces shaded by the volumes (issue 14 item 5): shadows from the light map and ambient occlusion, paper 000
Fig. 12's opacity-AO idea generalised from hair to any opaque surface.

Shadows. The light map (paper 001 §3, first pass; `volren.render.lightmap`) stores at each light-grid voxel centre
the transmittance from there to the light through the whole box (and, with GI on, through every other volume as
well: `cross_volume`). A surface point x outside a box reads it where its shadow ray enters the box, inside a box at
x itself. Voxel centres stop half a light voxel short of the faces, and trilinear sampling clamps there, so a lookup
at the face would skip the optical depth of that outer shell (exp(sigma_t h / 2), 3% on a 32-voxel grid at
sigma_t = 2): the ray's short chord through the shell is marched with density samples (`optical_depth`) and the
map is read where the ray reaches the box of the outermost centres. Without GI each volume's map holds only its own
density, so the transmittances of every box the shadow ray meets (found by the BVH over the boxes) multiply; with
GI on the map of the first box along the ray already holds every volume behind it, so only that one is read (the
product would count the far volumes twice: two stacked slabs would give exp(-3 tau) instead of exp(-2 tau)).

Ambient occlusion. The surfaces' ambient stays albedo * L_ambient (the environment's mean radiance, as without
volumes) times AO(x, n) = (1 / pi) integral over the hemisphere about n of T(x, w) cos dw, the cosine-weighted
transmittance of the volumes towards the sky (opaque surfaces do not occlude the ambient, as before). With the GI
methods of `SH_AO_METHODS`, a point in or within `NEAR_VOXELS` light voxels of a box reads AO from the GI grid's SH
coefficients of T(x, w) (paper 000 Eq. 7's phase-function SH; `volren.render.gi.passes`), convolved with the clamped
cosine (factors A_l / pi = 1, 2/3, 1/4 per band, Ramamoorthi and Hanrahan 2001) and evaluated at n; elsewhere, and
with the other GI methods or none, AO is the mean transmittance of `AO_RAYS` fixed cosine-distributed directions
marched with 1/`AO_COARSE` of the light-map samples (light-map-free). The reference renderer uses the same estimator
with `REFERENCE_AO_RAYS` rays at full samples and brute-force shadow rays: the ground truth.
"""

from __future__ import annotations

import warp as wp

from volren.kernels.common import (
    INF,
    LightGPU,
    VolumeGPU,
    box_hit,
    cell_fraction,
    corner_weight,
    count,
    grid_cell,
    grid_coords,
    optical_depth,
    sample_grid,
    transmittance_bvh,
)
from volren.render.frame import LIGHT_SAMPLES, LIGHTMAP_LOOKUPS
from volren.sh import sh_basis16, vec16
from volren.upload import DeviceScene

SURFACE_UNLIT = wp.constant(0)
"""volumes neither shadow nor occlude surfaces (methods without a light map of their own: VPT, fog)"""
SURFACE_LIGHT_MAP = wp.constant(1)
SURFACE_BRUTE_FORCE = wp.constant(2)
AO_RAYS = 32
"""cosine-distributed AO directions per surface point of the light-map methods"""
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
    ao_samples: int
    """L of the AO rays"""
    sh: wp.array(dtype=float)
    """the GI grid's SH coefficients of T(x, w), ``order2`` per light voxel (packed like the ambient grids)"""
    order2: int
    """0: no SH grid (GI off, or a GI method without coefficients)"""


def surface_light(ds: DeviceScene, mode: int, samples: int = 1, ao_rays: int = 0, ao_samples: int = 1,
                  cross_volume: bool = False, sh: wp.array | None = None, order2: int = 0) -> SurfaceLight:
    s = SurfaceLight()
    s.mode, s.volumes, s.density, s.lightmap, s.bvh = mode, ds.volumes, ds.density, ds.lightmap, ds.volume_bvh.id
    s.cross_volume, s.samples, s.ao_rays, s.ao_samples = int(cross_volume), samples, ao_rays, ao_samples
    s.sh = sh if sh is not None else wp.zeros(1, dtype=float, device=ds.device)
    s.order2 = order2 if sh is not None else 0
    return s


def unlit(ds: DeviceScene) -> SurfaceLight:
    return surface_light(ds, SURFACE_UNLIT)


@wp.func
def light_map_transmittance(sl: SurfaceLight, vol: VolumeGPU, li: int, x: wp.vec3, to_light: wp.vec3, t0: float,
                            t1: float, counters: wp.array(dtype=wp.int64)) -> float:
    """T from x + t0 to_light (the box entry, or x inside the box) to light li: the light map of ``vol`` read where
    the ray reaches the box of the outermost voxel centres, times the transmittance of the shell before it."""
    o_l = wp.transform_point(vol.to_local, x)
    d_l = wp.transform_vector(vol.to_local, to_light)
    res = vol.light_res
    inner = wp.vec3(1.0 - 1.0 / float(res[0]), 1.0 - 1.0 / float(res[1]), 1.0 - 1.0 / float(res[2]))
    h = box_hit(wp.cw_div(o_l, inner), wp.cw_div(d_l, inner))
    ta = wp.max(h[0], t0)
    if h[1] <= ta or ta >= t1:
        # The ray only grazes the shell: its whole chord is this volume's optical depth.
        shell = optical_depth(vol, x, to_light, t1, sl.density, sl.samples)
        count(counters, LIGHT_SAMPLES, int(shell[1]))
        return wp.exp(-shell[0])
    tau = float(0.0)
    if ta > t0:
        shell = optical_depth(vol, x, to_light, ta, sl.density, sl.samples)
        count(counters, LIGHT_SAMPLES, int(shell[1]))
        tau = shell[0]
    count(counters, LIGHTMAP_LOOKUPS, 1)
    n = res[0] * res[1] * res[2]
    return wp.exp(-tau) * sample_grid(sl.lightmap, vol.light_offset + li * n, res, o_l + ta * d_l)


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
    base = vol.ambient_offset + (cell[2] * res[1] + cell[1]) * res[0] + cell[0]
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
    frame = tangent_frame(n)
    total = float(0.0)
    for k in range(sl.ao_rays):
        total += transmittance_bvh(x, cosine_direction(frame, k, sl.ao_rays), INF, sl.bvh, sl.volumes, sl.density,
                                   sl.ao_samples, counters, LIGHT_SAMPLES)
    return total / float(sl.ao_rays)

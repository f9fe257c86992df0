"""Volumetric path tracing for direct volume rendering (paper 002 §4), ``--method vpt``.

Per pixel ``spp`` paths. Free flights by delta (null-collision) tracking against the local majorants of each
volume's macrocell octree (`volren.render.vpt.majorants`); the first collision over all volumes is the nearest of the
volumes' own first collisions, which is exact for overlapping volumes too (independent null-collision processes).
At a real collision x: the emitted radiance, next-event estimation towards every light with ratio-tracked
transmittance (opaque surfaces block it) and towards the environment (importance-sampled,
`volren.render.environment`), optionally (``ambient``) the uniform ambient of the environment's mean radiance
(§6.1), then a new direction; at most ``max_bounces`` scattering events per path (1 = single scattering).

Emission. The medium adds E(x) [W/(m^3 sr)] of radiance per metre (a volume's emission * density, or a transfer
function's emission column), not modulated by the albedo, as in the reference renderer: L = integral T(t) E(x_t) dt
along each flight. Delta tracking collides with pdf T(t) mu_t(x_t) (summed over overlapping volumes, each volume's
collision picked with its own mu_t), so the collision estimator adds E / mu_t of the colliding volume at every real
collision, weighted by the path's throughput up to it (the albedos of the scatterings before, not its own). It needs
mu_t > 0 wherever E > 0 (`volren.transfer`; a volume with emission and density_scale 0 is refused). A volume's
emission grid (fire) emits only where its density is > 0 (`volren.scene`), so there mu_t = density_scale * density
> 0 too; a transfer function does not model it (refused with one).

The environment is a light only: with ``ambient`` off (the default) a constant environment of radiance 1 around an
albedo-1 medium returns radiance 1 (the furnace). ``ambient`` adds paper 002 §6.1's uniform, unshadowed ambient of
the environment's mean radiance at every collision on top (it keeps dark maps from darkening the volume; with an
environment light on it counts the environment twice: 3.4-3.7x in the furnace).

Opaque surfaces are shadowed by the volumes: the surface pass shades them without the volumes (`surfaces`), and the
path-tracing kernel re-shades each surface pixel with the mean of ``spp`` ratio-tracked transmittances towards each
light (unbiased; the ambient term stays albedo * the environment's mean, as in the surface pass), before its paths
composite over it.

Shading (§4.2): the transfer function gives albedo A and P_brdf; particles reflect by a Lambertian BRDF about the
(two-sided) gradient normal, f = max(n.w, 0) / pi, or scatter by Henyey-Greenstein p. Exposure Render (``er``, Eq. 4)
picks one particle type per collision with probability P_brdf and estimates with that lobe only; the surface-medium
coexistence model (``coexist``, Eq. 5-7) evaluates the single particle's SDF h = P_brdf f + (1 - P_brdf) p at every
light sample and picks the bounce lobe with P_b of Eq. 7 (= P_brdf here: one albedo serves both lobes). Both have
the mean of h; coexist has less variance. Reading of Eq. 4: its printed division by P_brdf (P_phase) would make
ER's mean f + p; the estimator here is f (p) alone for the picked event, whose mean is h, as the paper's proof of
equal expectation requires.

The pixel's alpha is the share of primary paths that collided (an unbiased 1 - T); colour is premultiplied, and the
opaque-surface colour shows through the paths that did not collide. Axis-aligned clipping (§6.1) cuts every volume
to ``clip`` in its local coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.errors import VolrenError
from volren.kernels.common import (
    INF,
    LIGHT_RECT,
    CameraGPU,
    LightGPU,
    OpaqueGPU,
    ViewBuffers,
    VolumeGPU,
    blackbody_emission,
    box_hit,
    camera_ray,
    count,
    counter_row,
    hg_phase,
    light_distance,
    light_irradiance,
    light_travel_dir,
    occluder_t,
    sample_density,
)
from volren.render.base import Renderer, frame_seed
from volren.render.compositing.surfaces import SURFACE_EPSILON, mesh_group, nearest_surface, occluded
from volren.render.environment import ENV_NONE, EnvironmentLight, environment_light, sample_environment
from volren.render.frame import DENSITY_SAMPLES, LIGHT_SAMPLES, RAYS, SHADOW_RAYS, PassClock
from volren.render.vpt.denoise import SVGF, WRLS, Denoiser, luminance
from volren.render.vpt.majorants import (
    MajorantGrid,
    Majorants,
    build_majorants,
    majorant_struct,
    range_max_table,
    table_scale,
    track,
)
from volren.transfer import linear, load_transfer_function
from volren.upload import DeviceScene, camera_struct

SHADING = ("coexist", "er")
DENOISERS = ("none", "ours", "svgf", "wrls")
MAX_BOUNCES = 64
MAX_SPP = 4096


@dataclass(frozen=True)
class VPTConfig:
    spp: int = 8
    """paths per pixel and frame"""
    max_bounces: int = 2
    """scattering events per path (the paper: 2; 1 = single scattering)"""
    shading: str = "coexist"
    """coexist (paper 002 Eq. 5-7) or er (Exposure Render's two particle types, Eq. 4)"""
    transfer: str | None = None
    """a preset name or JSON file; None = extinction proportional to density (the ray marchers' model)"""
    global_majorant: bool = False
    """one majorant per volume instead of the macrocell octree (slower; for comparison)"""
    environment_light: bool = True
    """sample the environment as a light at every collision (a map by luminance, a constant uniformly; ratio-tracked
    through the volumes, blocked by opaque surfaces)"""
    ambient: bool = False
    """also add the environment's mean radiance as a uniform, unshadowed ambient at every collision (§6.1: keeps
    dark maps from darkening the volume; not physical: with ``environment_light`` it counts the environment twice)"""
    clip: tuple[float, float, float, float, float, float] = (-1.0, 1.0, -1.0, 1.0, -1.0, 1.0)
    """x0, x1, y0, y1, z0, z1 in each volume's local coordinates [-1, 1]"""
    denoise: str = "none"
    """none, ours (the spatiotemporal denoiser of §5), or the baselines svgf and wrls, `volren.render.vpt.denoise`; all
    keep history across frames"""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.denoise not in DENOISERS:
            raise VolrenError(f"denoise must be one of {', '.join(DENOISERS)}, got '{self.denoise}'")
        if int(self.spp) != self.spp or not 1 <= self.spp <= MAX_SPP:
            raise VolrenError(f"spp must be an integer in [1, {MAX_SPP}], got {self.spp}")
        if int(self.max_bounces) != self.max_bounces or not 1 <= self.max_bounces <= MAX_BOUNCES:
            raise VolrenError(f"max bounces must be an integer in [1, {MAX_BOUNCES}], got {self.max_bounces}")
        if self.shading not in SHADING:
            raise VolrenError(f"shading must be one of {', '.join(SHADING)}, got '{self.shading}'")
        c = tuple(self.clip)
        if len(c) != 6 or not all(math.isfinite(v) for v in c) or any(c[2 * a] >= c[2 * a + 1] for a in range(3)):
            raise VolrenError(f"clip needs x0 < x1, y0 < y1, z0 < z1, got {c}")
        if self.transfer is not None:
            load_transfer_function(self.transfer)


@wp.struct
class VPTParams:
    spp: int
    max_bounces: int
    shading: int
    seed: int
    emits: int
    """1: some volume emits (``SampleRecords.emission`` is recorded)"""
    ambient: wp.vec3
    surface_ambient: wp.vec3
    """the opaque surfaces' ambient radiance (the environment's mean, as in the surface pass)"""
    clip_lo: wp.vec3
    clip_hi: wp.vec3


@wp.struct
class SampleRecords:
    """Per pixel and path (row, col, path): the decoupled radiance of §5.1, F_x F_L + A F_m (Eq. 8), the first
    collision's linear depth (-1: none) and normalised scalar (for the reprojection depth rule of §5.2).

    F_x, F_L: the first collision's light samples (lights and environment), split as the paper's F_L = T L / p and
    F_x = A h, the SDF h (phase and BRDF) being the detail the wide filter must not blur. With several light samples
    h is their mean weighted by the unshadowed luminance of L / p (weights without the noisy transmittance), and
    F_L = sum_i T_i (L_i / p_i) h_i / h, so that F_x F_L is exact. F_x is scaled by 4 pi (F_L by 1 / (4 pi)) so that
    an isotropic medium has F_x = A: the scale of the paper's sigma_c = 0.2 and clustering threshold 0.1. Without
    light samples F_x = A and F_L = 0.
    A, F_m: the first collision's albedo and the rest, demodulated by it: the uniform ambient there and every later
    scattering and emission (the paper's F_m, denoised like F_L; the bounce direction is drawn from h, so no h factor
    is left).
    Emission: the first collision's emitted radiance E / mu_t, not modulated by A (which may be 0): the radiance is
    F_x F_L + A F_m + emission. Shape (1, 1, 1) when no volume emits (the denoiser then keeps two parts).
    Opacity: 1 - the ratio-tracked transmittance of the path's camera ray (up to the opaque surface), from its own
    random stream so the paths are those of the raw frame. §5.3.3 recommends a lower-variance estimate than N_p / N
    at low spp (it names ray marching; ratio tracking is the unbiased one the tracker already has)."""

    f_x: wp.array3d(dtype=wp.vec3)
    f_l: wp.array3d(dtype=wp.vec3)
    albedo: wp.array3d(dtype=wp.vec3)
    f_m: wp.array3d(dtype=wp.vec3)
    emission: wp.array3d(dtype=wp.vec3)
    depth: wp.array3d(dtype=float)
    density: wp.array3d(dtype=float)
    opacity: wp.array3d(dtype=float)


@wp.struct
class VPTScene:
    volumes: wp.array(dtype=VolumeGPU)
    grids: wp.array(dtype=MajorantGrid)
    majorants: wp.array(dtype=float)
    inv_scale: wp.array(dtype=float)
    density: wp.array(dtype=float)
    table: wp.array(dtype=wp.vec4)
    """per volume (``table_size`` entries each) and transfer-function entry: extinction, albedo rgb"""
    p_brdf: wp.array(dtype=float)
    emission: wp.array(dtype=wp.vec3)
    """per entry like ``table``: the emission E [W/(m^3 sr)]"""
    table_size: int
    lights: wp.array(dtype=LightGPU)
    opaque: wp.array(dtype=OpaqueGPU)
    mesh_ids: wp.array(dtype=wp.uint64)
    mesh_albedo: wp.array(dtype=wp.vec3)
    environment: EnvironmentLight


@wp.func
def clipped_span(vol: VolumeGPU, params: VPTParams, o: wp.vec3, d: wp.vec3) -> wp.vec2:
    """Local ray parameters where o + t d (local) is inside the volume's box cut by the clip planes."""
    c = 0.5 * (params.clip_lo + params.clip_hi)
    h = 0.5 * (params.clip_hi - params.clip_lo)
    return box_hit(wp.cw_div(o - c, h), wp.cw_div(d, h))


@wp.func
def track_volumes(sc: VPTScene, params: VPTParams, x: wp.vec3, d: wp.vec3, t_max: float, ratio: int,
                  state: wp.uint32):
    """Null-collision tracking of the world ray x + t d, t in (0, t_max), through every volume (`track` per volume).
    ratio = 0: the nearest real collision, the nearest of the volumes' own (each volume's span is cut at the best so
    far): (t or INF, volume index, state, lookups). ratio = 1: the product of the volumes' ratio-tracked
    transmittances: (transmittance, -1, state, lookups)."""
    best = t_max
    value = float(1.0)
    hit = int(-1)
    lookups = int(0)
    for v in range(sc.volumes.shape[0]):
        vol = sc.volumes[v]
        o = wp.transform_point(vol.to_local, x)
        dl = wp.transform_vector(vol.to_local, d)
        span = clipped_span(vol, params, o, dl)
        t0 = wp.max(span[0], 0.0)
        t1 = wp.min(span[1], best)
        if t1 > t0 and value > 0.0:
            w, s2, n = track(sc.grids[v], sc.majorants, sc.density, vol, sc.inv_scale[v], sc.table,
                             v * sc.table_size, sc.table_size, o, dl, t0, t1, ratio, state)
            state = s2
            lookups += n
            if ratio != 0:
                value = value * w
            elif w < best:
                best = w
                hit = v
    if ratio != 0:
        return value, hit, state, lookups
    if hit < 0:
        best = INF
    return best, hit, state, lookups


@wp.func
def free_flight(sc: VPTScene, params: VPTParams, x: wp.vec3, d: wp.vec3, t_max: float, state: wp.uint32):
    """Nearest real collision along the world ray x + t d, t in (0, t_max): (t or INF, volume index, state, lookups)."""
    return track_volumes(sc, params, x, d, t_max, 0, state)


@wp.func
def transmittance(sc: VPTScene, params: VPTParams, x: wp.vec3, d: wp.vec3, dist: float, state: wp.uint32):
    """Ratio-tracked transmittance from x towards d over dist through every volume (0 behind an opaque surface)."""
    if occluded(x, d, dist, sc.opaque, sc.mesh_ids):
        return 0.0, state, 0
    tr, _hit, s2, lookups = track_volumes(sc, params, x, d, dist, 1, state)
    return tr, s2, lookups


@wp.func
def material(sc: VPTScene, v: int, x: wp.vec3):
    """(albedo, P_brdf, world gradient, normalised scalar u, emitted radiance E / mu_t) of volume v at world point x,
    E the table's emission plus the volume's blackbody emission; the gradient by central differences."""
    vol = sc.volumes[v]
    p = wp.transform_point(vol.to_local, x)
    rho = sample_density(sc.density, vol, p)
    u = rho * sc.inv_scale[v]
    n = sc.table_size
    f = wp.clamp(u, 0.0, 1.0) * float(n - 1)
    i = wp.min(int(f), n - 2) + v * n
    a = f - float(int(f))
    e = (1.0 - a) * sc.table[i] + a * sc.table[i + 1]
    p_brdf = (1.0 - a) * sc.p_brdf[i] + a * sc.p_brdf[i + 1]
    emitted = wp.vec3(0.0)
    if e[0] > 0.0:
        table_e = (1.0 - a) * sc.emission[i] + a * sc.emission[i + 1]
        emitted = (table_e + blackbody_emission(vol, sc.density, p, rho)) / e[0]
    grad = wp.vec3(0.0)
    for axis in range(3):
        h = wp.vec3(0.0)
        h[axis] = 1.0 / float(vol.res[axis])
        grad[axis] = (sample_density(sc.density, vol, p + h)
                      - sample_density(sc.density, vol, p - h)) * float(vol.res[axis]) * 0.5
    m = vol.to_local
    world = (grad[0] * wp.vec3(m[0, 0], m[0, 1], m[0, 2]) + grad[1] * wp.vec3(m[1, 0], m[1, 1], m[1, 2])
             + grad[2] * wp.vec3(m[2, 0], m[2, 1], m[2, 2]))
    return wp.vec3(e[1], e[2], e[3]), p_brdf, world, u, emitted


@wp.func
def frame_of(n: wp.vec3) -> wp.mat33:
    """Columns: two tangents and n (an orthonormal basis around unit n)."""
    a = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.9:
        a = wp.vec3(0.0, 1.0, 0.0)
    t = wp.normalize(wp.cross(a, n))
    b = wp.cross(n, t)
    return wp.mat33(t[0], b[0], n[0], t[1], b[1], n[1], t[2], b[2], n[2])


@wp.func
def sample_hg(d: wp.vec3, g: float, state: wp.uint32):
    """A direction scattered from travel direction d by Henyey-Greenstein g: (direction, state)."""
    xi = wp.randf(state)
    cos_t = 1.0 - 2.0 * xi
    if wp.abs(g) > 1.0e-3:
        s = (1.0 - g * g) / (1.0 - g + 2.0 * g * xi)
        cos_t = (1.0 + g * g - s * s) / (2.0 * g)
    sin_t = wp.sqrt(wp.max(1.0 - cos_t * cos_t, 0.0))
    phi = 2.0 * wp.pi * wp.randf(state)
    return frame_of(d) * wp.vec3(sin_t * wp.cos(phi), sin_t * wp.sin(phi), cos_t), state


@wp.func
def sample_cosine(n: wp.vec3, state: wp.uint32):
    """A cosine-distributed direction about unit n: (direction, state)."""
    r = wp.sqrt(wp.randf(state))
    phi = 2.0 * wp.pi * wp.randf(state)
    return frame_of(n) * wp.vec3(r * wp.cos(phi), r * wp.sin(phi), wp.sqrt(wp.max(1.0 - r * r, 0.0))), state


@wp.func
def scatter_direction(d: wp.vec3, normal: wp.vec3, g: float, p_b: float, state: wp.uint32):
    """The bounce after a real collision (§4.2): the BRDF lobe (cosine about the unit normal) with probability p_b
    (Eq. 7), else Henyey-Greenstein g about the travel direction d: (direction, state). Each lobe is sampled by its
    own pdf, so the throughput takes just the albedo when the light samples weigh the lobes by the same p_b."""
    if wp.randf(state) < p_b:
        return sample_cosine(normal, state)
    return sample_hg(d, g, state)


@wp.func
def shadowed_surface(sc: VPTScene, params: VPTParams, x: wp.vec3, normal: wp.vec3, d: wp.vec3, albedo: wp.vec3,
                     state: wp.uint32, estimates: int):
    """The surface pass's Lambertian radiance of surface point x seen along d (`surfaces.shade_lit_surface`) with each
    light's transmittance through the volumes: the mean of ``estimates`` ratio-tracked estimates (0 where an opaque
    object blocks the light). (radiance, state, density lookups, shadow rays)."""
    n = normal
    if wp.dot(n, d) > 0.0:
        n = -n
    lifted = x + SURFACE_EPSILON * n
    rgb = wp.cw_mul(albedo, params.surface_ambient)
    lookups = int(0)
    rays = int(0)
    for li in range(sc.lights.shape[0]):
        light = sc.lights[li]
        to_light = -light_travel_dir(light, x)
        cos = wp.dot(n, to_light)
        dist = light_distance(light, x)
        if cos > 0.0 and not occluded(lifted, to_light, dist, sc.opaque, sc.mesh_ids):
            tr = float(0.0)
            for _k in range(estimates):
                tk, _none, s2, nk = track_volumes(sc, params, lifted, to_light, dist, 1, state)
                state = s2
                tr += tk
                lookups += nk
            rays += estimates
            rgb += wp.cw_mul(albedo, light_irradiance(light, x)) * (tr / float(estimates) * cos / wp.pi)
    return rgb, state, lookups, rays


@wp.kernel
def vpt_kernel(
    cam: CameraGPU,
    sc: VPTScene,
    params: VPTParams,
    buffers: ViewBuffers,
    view: int,
    record: int,
    samples: SampleRecords,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    r, col = wp.tid()
    counters = counter_row(counter_rows, r, col)
    row = r + row0
    state = wp.rand_init(params.seed, ((view * cam.height + row) * cam.width + col) * 7919)
    opacity_state = wp.rand_init(params.seed + 1, ((view * cam.height + row) * cam.width + col) * 7919)
    radiance = wp.vec3(0.0)
    hits = int(0)
    depth_sum = float(0.0)
    density_lookups = int(0)
    light_lookups = int(0)
    shadow_rays = int(0)
    # Opaque objects are hit by each path's own jittered ray, so a silhouette pixel converges to its coverage (issue
    # 47 item 3; the surface pass shades pixel centres only); a user's depth image clips at its pixel's depth.
    geometry = sc.opaque.shape[0] + sc.mesh_ids.shape[0] > 0
    surface_sum = wp.vec3(0.0)
    covered = int(0)
    for path in range(params.spp):
        d = camera_ray(cam, row, col, wp.randf(state), wp.randf(state))
        x = cam.origin
        t_max = cam.far / wp.dot(d, cam.forward)
        ts = float(INF)
        sn = wp.vec3(0.0)
        s_albedo = wp.vec3(0.0)
        if geometry:
            ts, sn, s_albedo = nearest_surface(cam.origin, d, sc.opaque, sc.mesh_ids, sc.mesh_albedo)
            t_max = wp.min(t_max, ts)
        if not geometry or buffers.occluder_color[row, col][3] <= 0.0:
            t_max = wp.min(t_max, occluder_t(buffers, cam, d, row, col))
        if record != 0:
            tr0, _none, s0, n0 = track_volumes(sc, params, x, d, t_max, 1, opacity_state)
            opacity_state = s0
            light_lookups += n0
            samples.opacity[row, col, path] = 1.0 - tr0
        # The path's radiance is F_x F_L + A F_m (SampleRecords; each later vertex's contributions carry the
        # throughput after the first albedo A).
        throughput = wp.vec3(1.0)
        albedo0 = wp.vec3(0.0)
        f_l = wp.vec3(0.0)
        f_m = wp.vec3(0.0)
        emission0 = wp.vec3(0.0)
        sdf_weight = float(0.0)
        light_weight = float(0.0)
        first_depth = float(-1.0)
        first_u = float(0.0)
        for bounce in range(params.max_bounces):
            t, v, s2, n = free_flight(sc, params, x, d, t_max, state)
            state = s2
            density_lookups += n
            if v < 0:
                if bounce == 0 and ts < t_max + 1.0e-6 * ts:
                    # through the volumes to the surface: one shadow-ray estimate per light for this path
                    rgb_s, s5, n_s, rays_s = shadowed_surface(sc, params, cam.origin + ts * d, sn, d, s_albedo,
                                                              state, 1)
                    state = s5
                    light_lookups += n_s
                    shadow_rays += rays_s
                    surface_sum += rgb_s
                    covered += 1
                break
            x = x + t * d
            albedo, p_brdf, grad, u, emitted = material(sc, v, x)
            # Vertex weight: 1 at the first collision (its albedo is F_x), the albedo afterwards.
            weight = albedo
            if bounce == 0:
                hits += 1
                first_depth = t * wp.dot(d, cam.forward)
                depth_sum += first_depth
                first_u = u
                albedo0 = albedo
                emission0 = emitted
                weight = wp.vec3(1.0)
            else:
                # emission is not scattered here: the throughput of the scatterings before this vertex only
                f_m += wp.cw_mul(throughput, emitted)
            normal = wp.vec3(0.0)
            if wp.length(grad) > 1.0e-6:
                normal = -wp.normalize(grad)
                if wp.dot(normal, d) > 0.0:
                    normal = -normal
            else:
                p_brdf = 0.0
            g = sc.volumes[v].g
            # ER: one particle type for this collision (its light estimate and its bounce).
            surface = float(p_brdf)
            if params.shading == 1:
                surface = wp.where(wp.randf(state) < p_brdf, 1.0, 0.0)
            f_m += wp.cw_mul(wp.cw_mul(throughput, weight), params.ambient)
            direct = wp.vec3(0.0)
            vertex_sdf = float(0.0)
            vertex_light = float(0.0)
            if sc.environment.mode != ENV_NONE:
                # The environment as a light: an importance-sampled direction, ratio-tracked to infinity.
                w, weighted, state = sample_environment(sc.environment, state)
                sdf = (1.0 - surface) * hg_phase(wp.dot(-w, -d), g)
                if surface > 0.0:
                    sdf += surface * wp.max(wp.dot(normal, w), 0.0) / wp.pi
                vertex_sdf += sdf * luminance(weighted)
                vertex_light += luminance(weighted)
                if sdf > 0.0:
                    shadow_rays += 1
                    tr, s4, n3 = transmittance(sc, params, x, w, INF, state)
                    state = s4
                    light_lookups += n3
                    direct += weighted * (sdf * tr)
            for li in range(sc.lights.shape[0]):
                light = sc.lights[li]
                to_light = -light_travel_dir(light, x)
                dist = light_distance(light, x)
                arriving = light_irradiance(light, x)
                if light.kind == LIGHT_RECT:
                    # A uniform point of the rectangle: radiance cos / r^2 over the area pdf 1 / A.
                    y = light.vector + (2.0 * wp.randf(state) - 1.0) * light.edge_u + (
                        2.0 * wp.randf(state) - 1.0) * light.edge_v
                    dist = wp.length(y - x)
                    to_light = (y - x) / wp.max(dist, 1.0e-9)
                    facing = wp.cross(light.edge_u, light.edge_v)
                    arriving = light.power * (4.0 * wp.max(-wp.dot(facing, to_light), 0.0)
                                              / wp.max(dist * dist, 1.0e-12))
                sdf = (1.0 - surface) * hg_phase(wp.dot(-to_light, -d), g)
                if surface > 0.0:
                    sdf += surface * wp.max(wp.dot(normal, to_light), 0.0) / wp.pi
                vertex_sdf += sdf * luminance(arriving)
                vertex_light += luminance(arriving)
                if sdf > 0.0 and wp.length_sq(arriving) > 0.0:
                    shadow_rays += 1
                    tr, s3, n2 = transmittance(sc, params, x, to_light, dist, state)
                    state = s3
                    light_lookups += n2
                    direct += arriving * (sdf * tr)
            if bounce == 0:
                f_l = direct
                sdf_weight = vertex_sdf
                light_weight = vertex_light
            else:
                f_m += wp.cw_mul(wp.cw_mul(throughput, weight), direct)
            if bounce + 1 == params.max_bounces:
                break
            # New direction: P_b of Eq. 7 is P_brdf here (one albedo serves both lobes), or ER's event.
            d, state = scatter_direction(d, normal, g, surface, state)
            throughput = wp.cw_mul(throughput, weight)
            t_max = INF
        radiance += wp.cw_mul(albedo0, f_l + f_m) + emission0
        if record != 0:
            f_x = albedo0
            if sdf_weight > 0.0:
                scale = 4.0 * wp.pi * sdf_weight / light_weight
                f_x = albedo0 * scale
                f_l = f_l / scale
            samples.f_x[row, col, path] = f_x
            samples.f_l[row, col, path] = f_l
            samples.albedo[row, col, path] = albedo0
            samples.f_m[row, col, path] = f_m
            if params.emits != 0:
                samples.emission[row, col, path] = emission0
            samples.depth[row, col, path] = first_depth
            samples.density[row, col, path] = first_u
    inv = 1.0 / float(params.spp)
    alpha = float(hits) * inv
    surface_color = buffers.occluder_color[row, col]
    if geometry:
        # The surface behind the volumes, premultiplied by its coverage among the paths the volumes let through (the
        # denoiser composites its output over it: Eq. 15's background); with every path stopped in a volume, the
        # pixel centre's surface stands in, with as many shadow-ray estimates.
        misses = params.spp - hits
        if misses > 0:
            c = surface_sum / float(misses)
            surface_color = wp.vec4(c[0], c[1], c[2], float(covered) / float(misses))
        elif surface_color[3] > 0.0:
            dc = camera_ray(cam, row, col, 0.5, 0.5)
            tc, nc, ac = nearest_surface(cam.origin, dc, sc.opaque, sc.mesh_ids, sc.mesh_albedo)
            rgb_c, state, n_c, rays_c = shadowed_surface(sc, params, cam.origin + tc * dc, nc, dc, ac, state,
                                                         params.spp)
            light_lookups += n_c
            shadow_rays += rays_c
            surface_color = wp.vec4(rgb_c[0], rgb_c[1], rgb_c[2], 1.0)
        buffers.occluder_color[row, col] = surface_color
    rgb = radiance * inv + (1.0 - alpha) * wp.vec3(surface_color[0], surface_color[1], surface_color[2])
    buffers.image[row, col] = wp.vec4(rgb[0], rgb[1], rgb[2], alpha + (1.0 - alpha) * surface_color[3])
    depth = buffers.occluder_depth[row, col]
    if hits > 0:
        depth = depth_sum / float(hits)
    buffers.depth[row, col] = depth
    count(counters, RAYS, params.spp)
    count(counters, DENSITY_SAMPLES, density_lookups)
    count(counters, LIGHT_SAMPLES, light_lookups)
    count(counters, SHADOW_RAYS, shadow_rays)


def transfer_tables(volumes, transfer: str | None, scales: list[float] | None = None) -> list[np.ndarray]:
    """Each volume's lookup table (`TransferFunction.table`), indexed by u = density / the majorants' scale
    (``scales``, each volume's `table_scale` if None): the configured transfer function (in Hounsfield units where it
    has that form and the volume a ``value_range``: entry u holds HU lo + (hi - lo) * u * scale; it replaces the
    volumes' density_scale, albedo and emission), or each volume's density-scale model (extinction and emission
    proportional to density)."""
    scales = scales or [table_scale(v.density) for v in volumes]
    if transfer is not None and any(v.emission_grid is not None for v in volumes):
        raise VolrenError("vpt: a transfer function replaces the material, and its extinction need not be > 0 "
                          "where an emission grid emits: render fire without --tf")
    if transfer is None:
        for v in volumes:
            if (max(v.emission) > 0 or v.emission_grid is not None) and v.density_scale == 0:
                raise VolrenError(f"vpt: volume '{v.name}' emits but has density_scale 0: the path tracer finds "
                                  "emission only where its free flights collide (give it extinction)")
        return [linear(v.density_scale * peak, v.albedo, max_emission=tuple(e * peak for e in v.emission)).table()
                for v, peak in zip(volumes, scales, strict=True)]
    tf = load_transfer_function(transfer)
    tables = []
    for v, peak in zip(volumes, scales, strict=True):
        hu = None
        if v.value_range is not None:
            lo, hi = v.value_range
            hu = (lo, lo + (hi - lo) * peak)
        tables.append(tf.table(hu=hu))
    return tables


class VPT(Renderer):
    """Volumetric path tracing; ``config`` is a `VPTConfig`. Majorants are rebuilt when the transfer function or
    the scene changes (build time and memory in the frame info)."""

    name = "vpt"

    def __init__(self, config: VPTConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or VPTConfig(), device)
        self._majorants: tuple | None = None
        """(key, host majorants, VPTScene fields that depend only on densities and the transfer function)"""
        self._environment: tuple | None = None
        self._emits = False
        """whether the current transfer tables hold any emission"""
        self._scene: VPTScene | None = None
        self._denoiser = {"ours": Denoiser, "svgf": SVGF, "wrls": WRLS}.get(self.config.denoise, Denoiser)(self.device)

    def _prepare(self, scene, clock: PassClock, frame: int) -> DeviceScene:
        """Upload, then the majorant octrees (rebuilt only when the densities or the transfer function change: not
        for a new camera or light) and the environment's sampling tables (rebuilt when the environment changes)."""
        ds = self._upload(scene, clock)
        key = (tuple(id(v) for v in scene.volumes), self.config.transfer, self.config.global_majorant,
               ds.stream_generation)  # a streamed volume's new bricks: new bounds
        if self._majorants is None or self._majorants[0] != key:
            with clock.measure("majorants"):
                bounds = [None] * len(scene.volumes)
                for state in ds.streams:
                    bounds[state.volume] = (state.bounds[0], ds.levels[state.volume][0].skip_cell)
                # u = 1 at the largest density drawn: a streamed volume's fine bricks may exceed its coarse maximum
                scales = [table_scale(v.density) if b is None else max(table_scale(v.density), float(b[0].max()))
                          for v, b in zip(scene.volumes, bounds, strict=True)]
                tables = transfer_tables(scene.volumes, self.config.transfer, scales)
                majorants = [build_majorants(vol.density, table[:, 0], range_max_table(table[:, 0]),
                                             self.config.global_majorant, bounds=b, scale=peak)
                             for vol, table, b, peak in zip(scene.volumes, tables, bounds, scales, strict=True)]
                self._majorants = (key, majorants, self._majorant_arrays(tables, majorants))
                self._emits = any(float(table[:, 5:8].max()) > 0 or vol.emission_grid is not None
                                  for vol, table in zip(scene.volumes, tables, strict=True))
        env = scene.environment if self.config.environment_light else None
        if self._environment is None or self._environment[0] is not env:
            self._environment = (env, environment_light(env, self.device))
        sc = VPTScene()
        sc.volumes, sc.density, sc.lights = ds.volumes, ds.density, ds.lights
        sc.opaque, sc.environment = ds.opaque, self._environment[1]
        sc.mesh_ids, sc.mesh_albedo, _ = mesh_group(ds, translucent=False)  # VPT draws no translucent meshes
        sc.grids, sc.majorants, sc.inv_scale, sc.table, sc.p_brdf, sc.emission, sc.table_size = self._majorants[2]
        self._scene = sc
        majorants = self._majorants[1]
        self._frame_info["majorant_bytes"] = sum(m.nbytes for m in majorants)
        self._frame_info["majorant_build_ms"] = round(sum(m.build_ms for m in majorants), 3)
        return ds

    def release_views(self) -> None:
        super().release_views()
        self._denoiser.history.clear()

    def _render_views(self, ds: DeviceScene, views: list[Camera], frame: int, targets: list[ViewBuffers],
                      clock: PassClock) -> None:
        """The views, after dropping the denoiser's history of views past the last (before, it kept every view
        index ever rendered: 21 full-HD views' classes after the viewers had gone)."""
        for view in [v for v in self._denoiser.history if v >= len(views)]:
            del self._denoiser.history[view]
        super()._render_views(ds, views, frame, targets, clock)

    def _majorant_arrays(self, tables: list[np.ndarray], majorants: list[Majorants]) -> tuple:
        """Device arrays of the majorant octrees (packed) and of one lookup table per volume."""
        structs, values, offset = [], [], 0
        for m in majorants:
            structs.append(majorant_struct(m, offset))
            for level in m.levels:
                values.append(level.reshape(-1))
                offset += level.size
        packed = np.concatenate(tables)
        return (wp.array(structs, dtype=MajorantGrid, device=self.device),
                wp.array(np.concatenate(values), dtype=float, device=self.device),
                wp.array([1.0 / m.scale for m in majorants], dtype=float, device=self.device),
                wp.array(packed[:, :4], dtype=wp.vec4, device=self.device),
                wp.array(packed[:, 4], dtype=float, device=self.device),
                wp.array(packed[:, 5:8], dtype=wp.vec3, device=self.device), len(tables[0]))

    def _render_view(self, ds: DeviceScene, cam: Camera, view: int, frame: int, buffers: ViewBuffers,
                     clock: PassClock) -> None:
        c = self.config
        params = VPTParams()
        params.spp, params.max_bounces, params.shading = c.spp, c.max_bounces, SHADING.index(c.shading)
        params.seed = frame_seed(c.seed, frame)
        params.ambient = ds.ambient if c.ambient else wp.vec3(0.0)
        params.surface_ambient = ds.ambient
        params.emits = int(self._emits)
        params.clip_lo, params.clip_hi = wp.vec3(*c.clip[0::2]), wp.vec3(*c.clip[1::2])
        record = c.denoise != "none"
        shape = (cam.height, cam.width, c.spp) if record else (1, 1, 1)
        samples = SampleRecords()
        samples.f_x = wp.zeros(shape, dtype=wp.vec3, device=self.device)
        samples.f_l = wp.zeros(shape, dtype=wp.vec3, device=self.device)
        samples.albedo = wp.zeros(shape, dtype=wp.vec3, device=self.device)
        samples.f_m = wp.zeros(shape, dtype=wp.vec3, device=self.device)
        samples.emission = wp.zeros(shape if self._emits else (1, 1, 1), dtype=wp.vec3, device=self.device)
        samples.depth = wp.zeros(shape, dtype=float, device=self.device)
        samples.density = wp.zeros(shape, dtype=float, device=self.device)
        samples.opacity = wp.zeros(shape, dtype=float, device=self.device)
        cam_gpu = camera_struct(cam)
        with clock.measure("path_tracing"):
            launch_rows(vpt_kernel, cam.height, cam.width, [cam_gpu, self._scene, params, buffers, view, int(record),
                                                            samples], self.device, clock.counters, self.on_rows)
        if record:
            with clock.measure("denoise"):
                self._denoiser.run(view, cam_gpu, samples, buffers)

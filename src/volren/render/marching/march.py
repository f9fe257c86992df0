"""The light-map march shared by DSSRM, CMSRM's texel rays and CACRM: uniform steps through one volume's box, each
sample shaded with single scattering from the light map (sigma_s * phase * T_light * E) plus ambient and emission,
composited front to back with early ray termination (paper 000 §3.1, paper 001 §3.1).

Empty-space skipping (not in the papers, which march every step): a step whose point lies in an empty cell of the
volume's conservative max-density grid (`volren.upload.skip_grid`) samples zero density, so the march jumps to the
first step of its lattice past the cell's exit. The steps it lands on are the ones it would have taken, hence the
same image; ``MarchState.skipped`` counts the steps not sampled."""

from __future__ import annotations

import warp as wp

from volren.kernels.common import (
    MarchState,
    Medium,
    VolumeGPU,
    composite_step,
    emitted_radiance,
    first_skip_check,
    half_depth,
    hg_phase,
    light_distance,
    light_irradiance,
    light_travel_dir,
    march_step_count,
    owns_sample,
    region_steps,
    sample_density,
    sample_grid_rgb,
    skip_cell_ray,
    skip_lookup,
    state_accumulator,
    with_accumulator,
)
from volren.render.lightmap import light_path_length, sample_light_map
from volren.render.marching.modes import (
    ISO_FETCHES,
    MODE_DVR,
    MODE_ISO,
    MODE_MIDA,
    MODE_MIP,
    intensity,
    iso_crossing,
    iso_normal,
    iso_shade,
    mida_weight,
    mip_step,
    skippable,
)


@wp.struct
class MarchParams:
    samples: int
    jitter: int
    seed: int
    view: int
    min_transmittance: float
    ambient: wp.vec3
    mode: int
    """`volren.render.marching.modes`: MODE_DVR, MODE_MIP, MODE_MIDA or MODE_ISO"""
    iso_value: float
    """V of MODE_ISO [density]"""
    inv_max: float
    """1 / the scene's largest density: MIP's and MIDA's intensity P = rho inv_max"""


@wp.func
def shade_light_map(
    vol: VolumeGPU,
    medium: Medium,
    p: wp.vec3,
    x: wp.vec3,
    d: wp.vec3,
    ambient: wp.vec3,
) -> wp.vec3:
    """Radiance scattered towards -d per unit sigma_s at local p / world x: ambient + sum_l phase T_l E_l, the
    ambient from the GI grid when GI is on (paper 000 §3.2's lighting-integration output), else the constant."""
    res = vol.light_res
    radiance = ambient
    if medium.gi != 0:
        radiance = sample_grid_rgb(medium.ambient, vol.ambient_offset, res, p)
    count = res[0] * res[1] * res[2]
    for li in range(medium.lights.shape[0]):
        light = medium.lights[li]
        travel = light_travel_dir(light, x)
        s = light_path_length(vol, p, -travel, light_distance(light, x))
        t = sample_light_map(medium.lightmap, vol.light_offset + 2 * li * count, count, res, p, s, medium.gi)
        phase = hg_phase(wp.dot(travel, -d), vol.g)
        radiance += phase * t * light_irradiance(light, x)
    return radiance


@wp.func
def lit_step(
    acc: wp.vec4,
    rho: float,
    vol: VolumeGPU,
    medium: Medium,
    p: wp.vec3,
    x: wp.vec3,
    d: wp.vec3,
    dt: float,
    ambient: wp.vec3,
) -> wp.vec4:
    """Composite one step of density rho > 0 at local p / world x: single scattering from the light map, ambient
    and emission as the source, extinction density_scale * rho."""
    sigma_t = vol.density_scale * rho
    light = shade_light_map(vol, medium, p, x, d, ambient)
    source = wp.cw_mul(vol.albedo, light) * sigma_t + emitted_radiance(vol, medium.density, p, rho)
    return composite_step(acc, source, sigma_t, dt)


@wp.func
def mode_step(
    acc: wp.vec4,
    peak: float,
    rho: float,
    vol: VolumeGPU,
    medium: Medium,
    o_l: wp.vec3,
    d_l: wp.vec3,
    origin: wp.vec3,
    d: wp.vec3,
    t: float,
    dt: float,
    lo: float,
    params: MarchParams,
):
    """One step at ray distance t (length dt, density rho fetched) in ``params.mode`` (`volren.render.marching.modes`);
    ``peak`` is MIDA's running max P, ``lo`` the last distance known below the iso value. Returns (acc, peak, 1 if a
    light-map lookup per light was made, extra density fetches, ray distance of the event for the depth)."""
    out = acc
    lit = int(0)
    fetches = int(0)
    t_event = t
    if params.mode == MODE_MIP:
        out = mip_step(acc, rho, params.inv_max)
    elif params.mode == MODE_ISO:
        if rho >= params.iso_value:
            t_event = iso_crossing(medium.density, vol, o_l, d_l, lo, t, params.iso_value)
            p = o_l + t_event * d_l
            x = origin + t_event * d
            c = iso_shade(vol, medium, iso_normal(medium.density, vol, p), x, params.ambient)
            out = wp.vec4(acc[0] + acc[3] * c[0], acc[1] + acc[3] * c[1], acc[2] + acc[3] * c[2], 0.0)
            fetches = ISO_FETCHES
    else:
        p_i = float(0.0)
        if params.mode == MODE_MIDA:
            p_i = intensity(rho, params.inv_max)
            out = mida_weight(acc, peak, p_i)
        if rho > 0.0:
            lit = 1
            out = lit_step(out, rho, vol, medium, o_l + t * d_l, origin + t * d, d, dt, params.ambient)
        return out, wp.max(peak, p_i), lit, fetches, t_event
    return out, peak, lit, fetches, t_event


@wp.func
def march_volume_light_map(
    state: MarchState,
    vol: VolumeGPU,
    origin: wp.vec3,
    d: wp.vec3,
    t0: float,
    t1: float,
    offset: float,
    medium: Medium,
    params: MarchParams,
) -> MarchState:
    """March [t0, t1] of one volume with uniform steps (offset in [0, 1) within each step), shading from the light
    map; stops early below params.min_transmittance. ``state.samples`` counts density fetches, ``state.skipped``
    the steps empty-space skipping (``medium.skip``) left out.

    With skipping, each cell the ray enters is looked up once: a non-empty one is marched step by step up to its exit
    (``check_t``), an empty one's cube of empty cells is left at once for the first step at or after its exit. Float
    rounding of that exit cannot make a skipped step matter: an empty cell reads zero density up to half a voxel
    beyond its footprint (`volren.upload.skip_grid`)."""
    o_l = wp.transform_point(vol.to_local, origin)
    d_l = wp.transform_vector(vol.to_local, d)
    o_c, d_c, inv_d = skip_cell_ray(vol, o_l, d_l)
    n = march_step_count(t1 - t0, vol.diagonal, params.samples)
    dt = (t1 - t0) / float(n)
    acc = state_accumulator(state)
    depth_t = state.depth_t
    shaded = int(0)
    taken = int(0)
    skipped = int(0)
    check_t = first_skip_check(vol, medium.skip)
    peak = float(0.0)  # MIDA's running max P, from this box's entry (`volren.render.marching.modes`)
    steps = region_steps(vol, o_l, d_l, t0, dt, offset, n)
    i = steps[0]
    while i < steps[1]:
        t = t0 + (float(i) + offset) * dt
        if t >= check_t:
            cell = skip_lookup(vol, medium.max_density, o_c + t * d_c, o_c, inv_d)
            check_t = cell[1]
            if skippable(params.mode, cell[0], acc, params.inv_max, params.iso_value):
                j = wp.min(wp.max(int(wp.ceil((check_t - t0) / dt - offset)), i + 1), steps[1])
                skipped += j - i
                i = j
                continue
        p = o_l + t * d_l
        if owns_sample(vol, p) == 0:  # a data-parallel region's neighbour's step
            i += 1
            continue
        rho = sample_density(medium.density, vol, p)
        taken += 1
        if params.mode == MODE_DVR:
            if rho > 0.0:
                shaded += 1
                before = acc[3]
                acc = lit_step(acc, rho, vol, medium, p, origin + t * d, d, dt, params.ambient)
                depth_t = half_depth(depth_t, before, acc[3], t)
                if acc[3] < params.min_transmittance:
                    break
        else:
            before = acc[3]
            acc, peak, lit, fetches, t_event = mode_step(acc, peak, rho, vol, medium, o_l, d_l, origin, d, t, dt,
                                                         wp.max(t - dt, t0), params)
            shaded += lit
            taken += fetches
            depth_t = half_depth(depth_t, before, acc[3], t_event)
            if acc[3] < params.min_transmittance:
                break
        i += 1
    s = with_accumulator(state, acc)
    s.depth_t = depth_t
    s.samples = s.samples + taken
    s.shaded = s.shaded + shaded
    s.skipped = s.skipped + skipped
    return s

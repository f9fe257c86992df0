"""DSSRM: direct screen-space ray marching (paper 000 §4.1 baseline, paper 001 Table 1 "DSSRM").

Per pixel: intersect the view ray with each volume's box in local space [-1, 1]^3, march uniform steps (at most V
samples across the box diagonal, midpoint or seeded-jittered positions), shade each sample with single scattering
from the light map (sigma_s * phase * T_light * E) plus the unshadowed ambient sigma_s * L_ambient and emission,
composite front to back with early ray termination. Volumes are visited in painter's order per view; the segment
starts at the near plane when the eye is inside a box.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.kernels.common import (
    CameraGPU,
    MarchState,
    Medium,
    ViewBuffers,
    VolumeGPU,
    box_hit,
    composite_step,
    count,
    counter_row,
    half_depth,
    hg_phase,
    light_irradiance,
    light_travel_dir,
    march_step_count,
    new_march_state,
    pixel_ray,
    ray_jitter,
    sample_grid,
    sample_grid_rgb,
    state_accumulator,
    with_accumulator,
    write_pixel,
)
from volren.render.base import LightMapMarchConfig, LightMapRenderer, frame_seed
from volren.render.frame import DENSITY_SAMPLES, LIGHTMAP_LOOKUPS, RAYS, PassClock
from volren.upload import DeviceScene, camera_struct, depth_order


@dataclass(frozen=True)
class DSSRMConfig(LightMapMarchConfig):
    jitter: bool = False
    """seeded random start offset per ray instead of the step midpoint"""


@wp.struct
class MarchParams:
    samples: int
    jitter: int
    seed: int
    view: int
    min_transmittance: float
    ambient: wp.vec3


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
        t = sample_grid(medium.lightmap, vol.light_offset + li * count, res, p)
        phase = hg_phase(wp.dot(light_travel_dir(light, x), -d), vol.g)
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
    source = wp.cw_mul(vol.albedo, light) * sigma_t + vol.emission * rho
    return composite_step(acc, source, sigma_t, dt)


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
    map; stops early below params.min_transmittance. ``state.samples`` counts density fetches."""
    o_l = wp.transform_point(vol.to_local, origin)
    d_l = wp.transform_vector(vol.to_local, d)
    n = march_step_count(t1 - t0, vol.diagonal, params.samples)
    dt = (t1 - t0) / float(n)
    acc = state_accumulator(state)
    depth_t = state.depth_t
    shaded = int(0)
    taken = int(0)
    for i in range(n):
        t = t0 + (float(i) + offset) * dt
        p = o_l + t * d_l
        rho = sample_grid(medium.density, vol.offset, vol.res, p)
        taken += 1
        if rho > 0.0:
            shaded += 1
            before = acc[3]
            acc = lit_step(acc, rho, vol, medium, p, origin + t * d, d, dt, params.ambient)
            depth_t = half_depth(depth_t, before, acc[3], t)
            if acc[3] < params.min_transmittance:
                break
    s = with_accumulator(state, acc)
    s.depth_t = depth_t
    s.samples = s.samples + taken
    s.shaded = s.shaded + shaded
    return s


@wp.kernel
def dssrm_kernel(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    order: wp.array(dtype=int),
    medium: Medium,
    params: MarchParams,
    buffers: ViewBuffers,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    r, col = wp.tid()
    counters = counter_row(counter_rows, r, col)
    row = r + row0
    d, planes = pixel_ray(cam, buffers, row, col)
    s = new_march_state()
    hit = int(0)
    for k in range(order.shape[0]):
        vol = volumes[order[k]]
        h = box_hit(wp.transform_point(vol.to_local, cam.origin), wp.transform_vector(vol.to_local, d))
        t0 = wp.max(h[0], planes[0])
        t1 = wp.min(h[1], planes[1])
        if t1 > t0:
            hit = 1
            offset = float(0.5)
            if params.jitter != 0:
                offset = ray_jitter(params.seed, params.view, row, col, cam.width, cam.height, k)
            s = march_volume_light_map(s, vol, cam.origin, d, t0, t1, offset, medium, params)
            if s.transmittance < params.min_transmittance:
                break
    count(counters, LIGHTMAP_LOOKUPS, s.shaded * medium.lights.shape[0])
    count(counters, RAYS, hit)
    write_pixel(s, cam, d, row, col, buffers, counters, DENSITY_SAMPLES)


class DSSRM(LightMapRenderer):
    """Direct screen-space ray marching with a light map; ``config`` is a `DSSRMConfig`."""

    name = "dssrm"

    def __init__(self, config: DSSRMConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or DSSRMConfig(), device)

    def _prepare(self, scene, clock: PassClock, frame: int) -> DeviceScene:
        ds = self._upload(scene, clock, self.config.light_grid)
        self._lighting(ds, clock)
        return ds

    def _render_view(
        self, ds: DeviceScene, cam: Camera, view: int, frame: int, buffers: ViewBuffers, clock: PassClock
    ) -> None:
        c = self.config
        params = MarchParams()
        params.samples = c.samples
        params.jitter = int(c.jitter)
        params.seed = frame_seed(c.seed, frame)
        params.view = view
        params.min_transmittance = c.min_transmittance
        params.ambient = ds.ambient
        order = wp.array(depth_order(ds.scene, cam), dtype=int, device=self.device)
        with clock.measure("march"):
            launch_rows(
                dssrm_kernel,
                cam.height,
                cam.width,
                [camera_struct(cam), ds.volumes, order, ds.medium(), params, buffers],
                self.device,
                clock.counters,
                self.on_rows,
            )

"""Reference renderer: the ground truth of paper 000 §4.1 (Fig. 7 "GT").

Dense uniform view steps (default V = 1024 across the smallest diagonal of the boxes covering a stretch), restarted at
every box boundary the ray crosses so that no step straddles one, and, at every lit sample, a dense march towards each
light (default L = 1024, same rule) through every volume, instead of a light map. Where boxes overlap, extinction and
in-scattering of all volumes add at each sample, so overlapping volumes and shadows cast by one volume on another are
exact. The ambient term is the same unshadowed sigma_s * L_ambient as in DSSRM. Early termination below
``min_transmittance`` (default 1e-4) bounds the error by 1e-4 of the radiance behind that point. The shadow marches skip
steps in empty cells of each volume's skip grid (``skip_empty``; the same image bit for bit: a skipped step would have
read density 0). Slow, simple, obviously right. Opaque surfaces get brute-force shadow rays through the density and
ambient occlusion from REFERENCE_AO_RAYS transmittance rays, both at L samples
(`volren.render.compositing.surface_light`): the ground truth of the light-map methods' surface shading.

Translucent meshes (paper 000 §3.3) are exact too: the march also stops at every translucent layer the ray crosses
(found by repeated BVH queries from just past the previous one, any number of them, `next_layer`) and blends it there
(colour += T alpha c, T *= 1 - alpha), in front of, between and inside the volumes alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.kernels.common import (
    INF,
    CameraGPU,
    LightGPU,
    MarchState,
    ViewBuffers,
    VolumeGPU,
    box_hit,
    composite_step,
    count,
    counter_row,
    covering_diagonal,
    density_inside,
    emitted_radiance,
    half_depth,
    hg_phase,
    light_distance,
    light_irradiance,
    light_travel_dir,
    march_step_count,
    new_march_state,
    next_box_boundary,
    pixel_ray,
    state_accumulator,
    transmittance_toward_skipping,
    with_accumulator,
    write_pixel,
)
from volren.render.base import Renderer, check_sample_count, check_transmittance_threshold
from volren.render.compositing.mesh_layers import LayerScene, blend_layer, layer_scene, next_layer
from volren.render.compositing.surface_light import REFERENCE_AO_RAYS, SURFACE_BRUTE_FORCE, SurfaceLight, surface_light
from volren.render.frame import DENSITY_SAMPLES, LIGHT_SAMPLES, LIGHT_SKIPPED, RAYS, PassClock
from volren.upload import DeviceScene, camera_struct


@dataclass(frozen=True)
class ReferenceConfig:
    samples: int = 1024
    """V: view samples across the smallest box diagonal"""
    light_samples: int = 1024
    """L: samples across the smallest box diagonal on each shadow ray"""
    min_transmittance: float = 1e-4
    skip_empty: bool = True
    """shadow rays leave out steps in empty cells of each volume's skip grid (`optical_depth_skipping`: the same
    image bit for bit, ``light_skipped`` counts them)"""

    def __post_init__(self) -> None:
        check_sample_count("samples (V)", self.samples)
        check_sample_count("light samples (L)", self.light_samples)
        check_transmittance_threshold(self.min_transmittance)


@wp.struct
class ReferenceParams:
    samples: int
    light_samples: int
    min_transmittance: float
    ambient: wp.vec3
    skip: int
    """1: shadow rays skip empty space"""


@wp.func
def reference_sample(
    state: MarchState,
    x: wp.vec3,
    d: wp.vec3,
    t: float,
    dt: float,
    volumes: wp.array(dtype=VolumeGPU),
    density: wp.array(dtype=float),
    max_density: wp.array(dtype=float),
    lights: wp.array(dtype=LightGPU),
    params: ReferenceParams,
    counters: wp.array(dtype=wp.int64),
) -> MarchState:
    """One view sample at world x: extinction, emission and ambient of every volume containing x, plus each light
    attenuated by a dense shadow march through all volumes, phase-weighted per volume."""
    s = state
    n_vol = volumes.shape[0]
    sigma_t = float(0.0)
    source = wp.vec3(0.0)
    for v in range(n_vol):
        vol = volumes[v]
        rho = density_inside(vol, x, density)
        if rho >= 0.0:
            s.samples += 1
            sigma_t += vol.density_scale * rho
            source += wp.cw_mul(vol.albedo, params.ambient) * (vol.density_scale * rho) + emitted_radiance(
                vol, density, wp.transform_point(vol.to_local, x), rho)
    if sigma_t > 0.0:
        s.shaded += 1
        for li in range(lights.shape[0]):
            light = lights[li]
            to_light = -light_travel_dir(light, x)
            tl = transmittance_toward_skipping(
                x, to_light, light_distance(light, x), volumes, 0, n_vol, density, params.light_samples,
                counters, LIGHT_SAMPLES, max_density, params.skip, LIGHT_SKIPPED,
            )
            e = light_irradiance(light, x) * tl
            for v in range(n_vol):
                vol = volumes[v]
                rho = density_inside(vol, x, density)
                if rho >= 0.0:
                    sigma_s = vol.albedo * (vol.density_scale * rho)
                    source += wp.cw_mul(sigma_s, e) * hg_phase(wp.dot(-to_light, -d), vol.g)
    # Emission-only media (sigma_t = 0) still add radiance.
    acc = composite_step(state_accumulator(s), source, sigma_t, dt)
    s.depth_t = half_depth(s.depth_t, s.transmittance, acc[3], t)
    return with_accumulator(s, acc)


@wp.kernel
def reference_kernel(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    density: wp.array(dtype=float),
    max_density: wp.array(dtype=float),
    lights: wp.array(dtype=LightGPU),
    params: ReferenceParams,
    sc: LayerScene,
    buffers: ViewBuffers,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    r, col = wp.tid()
    counters = counter_row(counter_rows, r, col)
    row = r + row0
    d, planes = pixel_ray(cam, buffers, row, col)
    n_vol = volumes.shape[0]
    t0 = float(INF)
    t1 = float(-INF)
    for v in range(n_vol):
        vol = volumes[v]
        h = box_hit(wp.transform_point(vol.to_local, cam.origin), wp.transform_vector(vol.to_local, d))
        if h[1] > h[0]:
            t0 = wp.min(t0, h[0])
            t1 = wp.max(t1, h[1])
    t0 = wp.max(t0, planes[0])
    t1 = wp.min(t1, planes[1])
    s = new_march_state()
    if t1 > t0:
        count(counters, RAYS, 1)
    layer = next_layer(sc, cam.origin, d, 0.0, counters)
    while layer.t < wp.min(t0, planes[1]):
        s = blend_layer(s, layer.color, layer.t)
        layer = next_layer(sc, cam.origin, d, layer.t, counters)
    t = t0
    while t < t1 and s.transmittance >= params.min_transmittance:
        t_next = wp.min(wp.min(next_box_boundary(cam.origin, d, t, volumes, 0, n_vol), t1), layer.t)
        diag = covering_diagonal(cam.origin + (0.5 * (t + t_next)) * d, volumes, 0, n_vol)
        if diag < INF and t_next > t:
            n = march_step_count(t_next - t, diag, params.samples)
            dt = (t_next - t) / float(n)
            for i in range(n):
                ts = t + (float(i) + 0.5) * dt
                s = reference_sample(s, cam.origin + ts * d, d, ts, dt, volumes, density, max_density, lights,
                                     params, counters)
                if s.transmittance < params.min_transmittance:
                    break
        t = t_next
        if layer.t <= t:
            s = blend_layer(s, layer.color, layer.t)
            layer = next_layer(sc, cam.origin, d, layer.t, counters)
    while layer.t < planes[1]:
        s = blend_layer(s, layer.color, layer.t)
        layer = next_layer(sc, cam.origin, d, layer.t, counters)
    write_pixel(s, cam, d, row, col, buffers, counters, DENSITY_SAMPLES)


class Reference(Renderer):
    """The dense ground-truth renderer; ``config`` is a `ReferenceConfig`."""

    name = "reference"
    translucent_meshes = True

    def __init__(self, config: ReferenceConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or ReferenceConfig(), device)

    def _surface_light(self, ds: DeviceScene) -> SurfaceLight:
        samples = self.config.light_samples
        return surface_light(ds, SURFACE_BRUTE_FORCE, samples, REFERENCE_AO_RAYS, samples)

    def _render_view(
        self, ds: DeviceScene, cam: Camera, view: int, frame: int, buffers: ViewBuffers, clock: PassClock
    ) -> None:
        c = self.config
        params = ReferenceParams()
        params.samples = c.samples
        params.light_samples = c.light_samples
        params.min_transmittance = c.min_transmittance
        params.ambient = ds.ambient
        params.skip = int(c.skip_empty)
        with clock.measure("march"):
            launch_rows(
                reference_kernel,
                cam.height,
                cam.width,
                [camera_struct(cam), ds.volumes, ds.density, ds.max_density, ds.lights, params,
                 layer_scene(ds, self._surface_light(ds)), buffers],
                self.device,
                clock.counters,
                self.on_rows,
            )

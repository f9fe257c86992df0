"""DSSRM: direct screen-space ray marching (paper 000 §4.1 baseline, paper 001 Table 1 "DSSRM").

Per pixel: intersect the view ray with each volume's box in local space [-1, 1]^3, march uniform steps (at most V
samples across the box diagonal, midpoint or seeded-jittered positions), shade each sample with single scattering
from the light map (sigma_s * phase * T_light * E) plus the unshadowed ambient sigma_s * L_ambient and emission,
composite front to back with early ray termination. Each pixel composites the boxes its ray meets in the order it
meets them, overlapping ones marched jointly (`volren.render.compositing.oit`); a segment starts at the near plane
when the eye is inside a box. Translucent mesh layers (paper 000 §3.3, the mesh k-buffer of
`volren.render.compositing.mesh_layers`) split the march where they lie and are blended there; inside a joint run of
overlapping boxes they are blended after the run (the joint march is not split).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.kernels.common import (
    INF,
    CameraGPU,
    Medium,
    ViewBuffers,
    VolumeGPU,
    count,
    counter_row,
    new_march_state,
    pixel_ray,
    ray_jitter,
    write_pixel,
)
from volren.render.base import LightMapMarchConfig, LightMapRenderer, frame_seed
from volren.render.compositing.mesh_layers import (
    MeshLayers,
    blend_layers_before,
    layer_stats,
    march_between_layers,
    mesh_layers_pass,
)
from volren.render.compositing.oit import LayerFinder, OITParams, cluster_end, pixel_layers
from volren.render.frame import DENSITY_SAMPLES, JOINT_RAYS, LIGHTMAP_LOOKUPS, RAYS, SKIPPED_STEPS, PassClock
from volren.render.marching.march import MarchParams
from volren.upload import DeviceScene, camera_struct


@dataclass(frozen=True)
class DSSRMConfig(LightMapMarchConfig):
    jitter: bool = False
    """seeded random start offset per ray instead of the step midpoint"""


@wp.kernel
def dssrm_kernel(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    oit: OITParams,
    medium: Medium,
    params: MarchParams,
    mesh: MeshLayers,
    buffers: ViewBuffers,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    r, col = wp.tid()
    counters = counter_row(counter_rows, r, col)
    row = r + row0
    d, planes = pixel_ray(cam, buffers, row, col)
    layers = pixel_layers(oit, volumes, cam.origin, d, planes, row, col, counters)
    s = new_march_state()
    facing = wp.dot(d, cam.forward)
    next_mesh = int(0)
    joint = int(0)
    i = int(0)
    while i < layers.count:
        end = cluster_end(layers, i)
        offset = float(0.5)
        if params.jitter != 0:
            offset = ray_jitter(params.seed, params.view, row, col, cam.width, cam.height, i)
        if end - i > 1:
            joint = 1
        s, next_mesh = march_between_layers(s, next_mesh, mesh, row, col, facing, layers, i, end, volumes, cam.origin,
                                            d, offset, medium, params)
        if s.transmittance < params.min_transmittance:
            break
        i = end
    s, next_mesh = blend_layers_before(s, next_mesh, mesh, row, col, facing, INF)
    count(counters, LIGHTMAP_LOOKUPS, s.shaded * medium.lights.shape[0])
    count(counters, RAYS, wp.min(layers.count, 1))
    count(counters, JOINT_RAYS, joint)
    count(counters, SKIPPED_STEPS, s.skipped)
    write_pixel(s, cam, d, row, col, buffers, counters, DENSITY_SAMPLES)


class DSSRM(LightMapRenderer):
    """Direct screen-space ray marching with a light map; ``config`` is a `DSSRMConfig`."""

    name = "dssrm"
    translucent_meshes = True

    def __init__(self, config: DSSRMConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or DSSRMConfig(), device)

    def release_views(self) -> None:
        super().release_views()
        self._layers = LayerFinder(self.config.oit, self.config.oit_k, self.device)  # the views' OIT tiles gone

    def _prepare(self, scene, clock: PassClock, frame: int) -> DeviceScene:
        self._layers = LayerFinder(self.config.oit, self.config.oit_k, self.device)
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
        self._mode_params(params, ds)
        oit = self._layers.params(ds, cam, clock)
        mesh = mesh_layers_pass(ds, cam, buffers, c.mesh_layers, clock, self._surface_light(ds))
        self._frame_info["mesh_layers"] = layer_stats(mesh, c.mesh_layers, self._frame_info.get("mesh_layers"))
        with clock.measure("march"):
            launch_rows(
                dssrm_kernel,
                cam.height,
                cam.width,
                [camera_struct(cam), ds.volumes, oit, ds.medium(), params, mesh, buffers],
                self.device,
                clock.counters,
                self.on_rows,
            )

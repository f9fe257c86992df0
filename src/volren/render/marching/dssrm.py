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
    Medium,
    ViewBuffers,
    VolumeGPU,
    box_hit,
    count,
    counter_row,
    new_march_state,
    pixel_ray,
    ray_jitter,
    write_pixel,
)
from volren.render.base import LightMapMarchConfig, LightMapRenderer, frame_seed
from volren.render.frame import DENSITY_SAMPLES, LIGHTMAP_LOOKUPS, RAYS, PassClock
from volren.render.marching.march import MarchParams, march_volume_light_map
from volren.upload import DeviceScene, camera_struct, depth_order


@dataclass(frozen=True)
class DSSRMConfig(LightMapMarchConfig):
    jitter: bool = False
    """seeded random start offset per ray instead of the step midpoint"""


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

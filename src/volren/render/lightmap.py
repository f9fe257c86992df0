"""Light-map pass (paper 001 §3, first pass): per light-grid voxel, march towards each light for its transmittance.

The light grid has its own resolution (e.g. 128^3 for 256^3 density) and one channel per light (directional or
point). Marching uses L uniform samples at most across the box diagonal ("L" of the papers' METHOD:V:L). Only the
volume's own density attenuates: shadows cast between volumes come with the GI issue's BVH march (paper 000 §3.2).
"""

from __future__ import annotations

import warp as wp

from volren.device import launch_rows
from volren.kernels.common import (
    LightGPU,
    VolumeGPU,
    light_distance,
    light_travel_dir,
    transmittance_toward,
    voxel_center,
)
from volren.render.frame import LIGHT_SAMPLES, PassClock
from volren.upload import DeviceScene


@wp.kernel
def light_map_kernel(
    volumes: wp.array(dtype=VolumeGPU),
    v: int,
    density: wp.array(dtype=float),
    lights: wp.array(dtype=LightGPU),
    light_samples: int,
    lightmap: wp.array(dtype=float),
    counters: wp.array(dtype=wp.int64),
    row0: int,
):
    r, i = wp.tid()
    row = r + row0
    vol = volumes[v]
    res = vol.light_res
    k = row / res[1]
    j = row - k * res[1]
    x = wp.transform_point(vol.to_world, voxel_center(i, j, k, res))
    count = res[0] * res[1] * res[2]
    for li in range(lights.shape[0]):
        light = lights[li]
        t = transmittance_toward(
            x, -light_travel_dir(light, x), light_distance(light, x), volumes, v, v + 1, density, light_samples,
            counters, LIGHT_SAMPLES,
        )
        lightmap[vol.light_offset + li * count + (k * res[1] + j) * res[0] + i] = t


def compute_light_map(ds: DeviceScene, light_samples: int, clock: PassClock) -> None:
    """Fill ``ds.lightmap`` for every volume and light."""
    if ds.light_count == 0:
        return
    with clock.measure("light_map"):
        for v, (nx, ny, nz) in enumerate(ds.light_res):
            launch_rows(
                light_map_kernel,
                nz * ny,
                nx,
                [ds.volumes, v, ds.density, ds.lights, light_samples, ds.lightmap],
                ds.device,
                clock.counters,
            )

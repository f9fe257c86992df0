"""Light-map pass (paper 001 §3, first pass): per light-grid voxel, march towards each light for its transmittance.

The light grid has its own resolution (e.g. 128^3 for 256^3 density) and one channel per light (directional or
point). Marching uses L uniform samples at most across the box diagonal ("L" of the papers' METHOD:V:L). Without GI
only the volume's own density attenuates (paper 001); with GI on, the march crosses every volume its ray hits, found
through the BVH over the volumes' boxes (paper 000 §3.2.3's lighting update: shadows between volumes).
"""

from __future__ import annotations

import warp as wp

from volren.device import launch_rows
from volren.kernels.common import (
    LightGPU,
    VolumeGPU,
    counter_row,
    light_distance,
    light_travel_dir,
    transmittance_bvh,
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
    bvh: wp.uint64,
    cross_volume: int,
    lightmap: wp.array(dtype=float),
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    r, i = wp.tid()
    counters = counter_row(counter_rows, r, i)
    row = r + row0
    vol = volumes[v]
    res = vol.light_res
    k = row / res[1]
    j = row - k * res[1]
    x = wp.transform_point(vol.to_world, voxel_center(i, j, k, res))
    count = res[0] * res[1] * res[2]
    for li in range(lights.shape[0]):
        light = lights[li]
        toward = -light_travel_dir(light, x)
        reach = light_distance(light, x)
        t = float(0.0)
        if cross_volume != 0:
            t = transmittance_bvh(x, toward, reach, bvh, volumes, density, light_samples, counters, LIGHT_SAMPLES)
        else:
            t = transmittance_toward(x, toward, reach, volumes, v, v + 1, density, light_samples, counters,
                                     LIGHT_SAMPLES)
        lightmap[vol.light_offset + li * count + (k * res[1] + j) * res[0] + i] = t


def compute_light_map(ds: DeviceScene, light_samples: int, clock: PassClock, cross_volume: bool = False) -> None:
    """Fill ``ds.lightmap`` for every volume and light (``cross_volume``: through every volume, not just its own)."""
    if ds.light_count == 0:
        return
    with clock.measure("light_map"):
        for v, (nx, ny, nz) in enumerate(ds.light_res):
            launch_rows(
                light_map_kernel,
                nz * ny,
                nx,
                [ds.volumes, v, ds.density, ds.lights, light_samples, ds.volume_bvh.id, int(cross_volume),
                 ds.lightmap],
                ds.device,
                clock.counters,
            )

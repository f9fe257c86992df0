"""Light-map pass (paper 001 §3, first pass): per light-grid voxel, march towards each light for its transmittance.

The light grid has its own resolution (e.g. 128^3 for 256^3 density) and one channel per light (directional or
point). Marching uses L uniform samples at most across the box diagonal ("L" of the papers' METHOD:V:L). Without GI
only the volume's own density attenuates (paper 001); with GI on, the march crosses every volume its ray hits, found
through the BVH over the volumes' boxes (paper 000 §3.2.3's lighting update: shadows between volumes).

Empty-space skipping (not in the papers; on with the renderer's ``skip_empty``): the march towards the light leaves
out steps in empty cells of each volume's skip grid, as the view march does (`volren.kernels.common.
optical_depth_skipping`), with the same light map bit for bit; the ``light_skipped`` counter counts those steps.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from volren.device import launch_rows
from volren.kernels.common import (
    LightGPU,
    VolumeGPU,
    counter_row,
    light_distance,
    light_travel_dir,
    transmittance_bvh_skipping,
    transmittance_toward_skipping,
    voxel_center,
)
from volren.render.frame import LIGHT_SAMPLES, LIGHT_SKIPPED, PassClock
from volren.upload import DeviceScene


@wp.kernel
def light_map_kernel(
    volumes: wp.array(dtype=VolumeGPU),
    row_start: wp.array(dtype=int),
    density: wp.array(dtype=float),
    max_density: wp.array(dtype=float),
    skip: int,
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
    # the volume whose rows hold this one: row_start[v] <= row < row_start[v + 1]
    v = int(0)
    hi = row_start.shape[0] - 1
    while hi - v > 1:
        mid = (v + hi) / 2
        if row_start[mid] <= row:
            v = mid
        else:
            hi = mid
    vol = volumes[v]
    res = vol.light_res
    if i >= res[0]:
        return
    k = (row - row_start[v]) / res[1]
    j = (row - row_start[v]) - k * res[1]
    x = wp.transform_point(vol.to_world, voxel_center(i, j, k, res))
    count = res[0] * res[1] * res[2]
    for li in range(lights.shape[0]):
        light = lights[li]
        toward = -light_travel_dir(light, x)
        reach = light_distance(light, x)
        t = float(0.0)
        if cross_volume != 0:
            t = transmittance_bvh_skipping(x, toward, reach, bvh, volumes, density, light_samples, counters,
                                           LIGHT_SAMPLES, max_density, skip, LIGHT_SKIPPED)
        else:
            t = transmittance_toward_skipping(x, toward, reach, volumes, v, v + 1, density, light_samples, counters,
                                              LIGHT_SAMPLES, max_density, skip, LIGHT_SKIPPED)
        lightmap[vol.light_offset + li * count + (k * res[1] + j) * res[0] + i] = t


def compute_light_map(ds: DeviceScene, light_samples: int, clock: PassClock, cross_volume: bool = False) -> None:
    """Fill ``ds.lightmap`` for every volume and light (``cross_volume``: through every volume, not just its own),
    skipping empty space when ``ds.skip_empty``."""
    if ds.light_count == 0:
        return
    with clock.measure("light_map"):
        # one launch for every volume's (z, y) rows: per-volume launches cost ~0.2 ms each on the CPU (a band per
        # thread), as much as the march at 36 small instances
        rows = np.cumsum([0] + [ny * nz for (_, ny, nz) in ds.light_res])
        launch_rows(
            light_map_kernel,
            int(rows[-1]),
            max(nx for (nx, _, _) in ds.light_res),
            [ds.volumes, wp.array(rows, dtype=int, device=ds.device), ds.density, ds.max_density, int(ds.skip_empty),
             ds.lights, light_samples, ds.volume_bvh.id, int(cross_volume), ds.lightmap],
            ds.device,
            clock.counters,
        )

"""Light-map pass (paper 001 §3, first pass): per light-grid node, march towards each light for its transmittance.

The light grid has its own resolution (e.g. 128^3 for 256^3 density) and one channel per light (directional or
point). Marching uses L uniform samples at most across the box diagonal ("L" of the papers' METHOD:V:L). Without GI
only the volume's own density attenuates (paper 001); with GI on, the march crosses every volume its ray hits, found
through the BVH over the volumes' boxes (paper 000 §3.2.3's lighting update: shadows between volumes).

Layout (issue 19 item 3; not in the papers, which leave it open). The n nodes of an axis sit at -1 + 2 i / (n - 1),
the outermost on the box faces. Voxel centres (the density grid's layout) stop half a light voxel inside the faces,
and lookups clamped there gave a sample on a lit face the transmittance of a deeper point: on a uniform 8^3 box (4^3
light grid) lit from above, DSSRM's top image rows were 0.62-0.73 of the reference.

What a node holds (issue 47 item 1). Per light two planes: sigma_bar = tau_own / s, the mean extinction along the
node's path to the light inside its own box (s that path's length, `light_path_length`), and tau_in, the optical
depth of the other volumes on the way (GI on; 0 otherwise). A volume sample at p computes its own s(p) and takes
tau = interp(sigma_bar) s(p) + interp(tau_in), T = exp(-tau). Through a uniform medium sigma_bar is the same at every
node, so the lookup is exact whichever face the path leaves by. Interpolating tau itself (issues 19 to 46) is exact
only along the light: tau is the minimum of linear functions, one per exit face, and bends where the exit face
changes, so across a coarse axis its interpolation falls below it. A 16 x 2 x 1 m slab lit from above at a slant was
1.18x too bright (uniform; 1.14 with a varying density) where the path leaves by a side within a node spacing; the
mean extinction gives 0.998 (1.007). Interpolating T instead of the optical depth overshoots where T is convex in
depth (1.14x on the box above). The price is one path length per sample and light (a slab test): at most about 10%
of DSSRM's march on the CPU, below what the VM's timing resolves (docs/BENCHMARKS-LOG.md, issue 47). A surface's
shadow lookup, at the box entry (a face), interpolates only across the light's direction, over shadow edges, where
blending T is the closer to point-sampled shadows (smoke over a floor: 45.8 dB for T, 42.2 for tau, against shadow
rays), so it blends the corners' T along its chord (`sample_light_map_across`).

Empty-space skipping (not in the papers; on with the renderer's ``skip_empty``): the march towards the light leaves
out steps in empty cells of each volume's skip grid, as the view march does (`volren.kernels.common.
optical_depth_skipping`), with the same light map bit for bit; the ``light_skipped`` counter counts those steps.

Cache (`LightMapCache`, not in the papers, which recompute the map each frame): the map depends only on the lights,
the volumes (densities, skip grids, transforms, density scales, light-grid size: one upload holds one set of them,
and a scene or light grid that changes any of them is a new upload with new light-map storage), L and whether the
march crosses volumes (GI on).
While none of these changed since the storage was last filled, the pass is skipped: on an orbit or a camera drag
the light stands still, and the map is the same bit for bit. Densities edited in place after the upload are not
seen (nor by the march, which reads the uploaded copy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from volren.device import launch_rows
from volren.kernels.common import (
    LightGPU,
    VolumeGPU,
    box_hit,
    cell_fraction,
    count,
    counter_row,
    gather_cell,
    grid_cell,
    interpolate_cell,
    light_distance,
    light_travel_dir,
    optical_depth_bvh_skipping,
    optical_depth_skipping,
    vec8,
)
from volren.render.frame import LIGHT_SAMPLES, LIGHT_SKIPPED, PassClock
from volren.scene import Light
from volren.upload import DeviceScene

NODE_INSET = wp.constant(1.0 - 1.0e-5)
"""nodes on a face are marched from just inside it: a ray along the face would leave the box at once"""
MAX_OPTICAL_DEPTH = wp.constant(69.0)
"""-ln of 1e-30: what a node stores for T = 0 (a finite tau keeps the interpolation finite)"""


@wp.func
def light_node(i: int, j: int, k: int, res: wp.vec3i) -> wp.vec3:
    """Local position of light-map node (x=i, y=j, z=k): -1 + 2 i / (n - 1) (module docstring)."""
    return wp.vec3(
        -1.0 + float(i) * 2.0 / float(res[0] - 1),
        -1.0 + float(j) * 2.0 / float(res[1] - 1),
        -1.0 + float(k) * 2.0 / float(res[2] - 1),
    )


@wp.func
def light_map_cell(data: wp.array(dtype=float), offset: int, res: wp.vec3i, p: wp.vec3):
    """The 8 optical depths of the packed [z, y, x] light-map cell around local ``p`` in [-1, 1]^3 (clamped to the
    box) and p's fractional position in it."""
    f = wp.vec3(
        wp.clamp((p[0] + 1.0) * 0.5 * float(res[0] - 1), 0.0, float(res[0] - 1)),
        wp.clamp((p[1] + 1.0) * 0.5 * float(res[1] - 1), 0.0, float(res[1] - 1)),
        wp.clamp((p[2] + 1.0) * 0.5 * float(res[2] - 1), 0.0, float(res[2] - 1)),
    )
    cell = grid_cell(res, f)
    return gather_cell(data, offset, res, cell), cell_fraction(f, cell)


@wp.func
def light_path_length(vol: VolumeGPU, p: wp.vec3, toward: wp.vec3, reach: float) -> float:
    """[m] s: the length of the path from local ``p`` towards the light (world direction ``toward``, the light at
    distance ``reach``) inside the volume's box: the chord `optical_depth` marches from p."""
    h = box_hit(p, wp.transform_vector(vol.to_local, toward))
    return wp.max(wp.min(h[1], reach) - wp.max(h[0], 0.0), 0.0)


@wp.func
def optical_depth_at(data: wp.array(dtype=float), offset: int, nodes: int, res: wp.vec3i, p: wp.vec3, s: float,
                     gi: int) -> float:
    """tau = sigma_bar s + tau_in at local ``p`` whose path to the light runs ``s`` inside the box (module docstring:
    the mean extinction and, with ``gi``, the optical depth of the other volumes, each interpolated trilinearly)."""
    sigma_bar, a = light_map_cell(data, offset, res, p)
    tau = interpolate_cell(sigma_bar, a) * s
    if gi != 0:
        tau_in, a_in = light_map_cell(data, offset + nodes, res, p)
        tau += interpolate_cell(tau_in, a_in)
    return tau


@wp.func
def sample_light_map(data: wp.array(dtype=float), offset: int, nodes: int, res: wp.vec3i, p: wp.vec3, s: float,
                     gi: int) -> float:
    """Transmittance to the light of a volume sample at local ``p`` (``s``: `light_path_length`): exp(-tau), exact
    through a uniform medium whatever face the path leaves by."""
    return wp.exp(-optical_depth_at(data, offset, nodes, res, p, s, gi))


@wp.func
def sample_light_map_across(data: wp.array(dtype=float), offset: int, nodes: int, res: wp.vec3i, p: wp.vec3,
                            s: float, gi: int) -> float:
    """Transmittance to the light at a shadow ray's box entry ``p`` (a surface's lookup; ``s`` its chord through the
    box): the corners' transmittances along that chord interpolated (module docstring)."""
    sigma_bar, a = light_map_cell(data, offset, res, p)
    tau_in = vec8()
    if gi != 0:
        tau_in, a = light_map_cell(data, offset + nodes, res, p)
    t = vec8()
    for c in range(8):
        t[c] = wp.exp(-wp.min(sigma_bar[c] * s + tau_in[c], MAX_OPTICAL_DEPTH))
    return interpolate_cell(t, a)


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
    p = light_node(i, j, k, res) * NODE_INSET
    x = wp.transform_point(vol.to_world, p)
    nodes = res[0] * res[1] * res[2]
    node = (k * res[1] + j) * res[0] + i
    for li in range(lights.shape[0]):
        light = lights[li]
        toward = -light_travel_dir(light, x)
        reach = light_distance(light, x)
        # tau_own through this volume's box, tau_in through the others (GI on: paper 000 §3.2.3's shadows between
        # volumes)
        own = optical_depth_skipping(vol, x, toward, reach, density, max_density, skip, light_samples)
        others = wp.vec3(0.0)
        if cross_volume != 0:
            others = optical_depth_bvh_skipping(x, toward, reach, bvh, volumes, density, light_samples, max_density,
                                                skip, v)
        tau_own, tau_in = own[0], others[0]
        count(counters, LIGHT_SAMPLES, int(own[1] + others[1]))
        count(counters, LIGHT_SKIPPED, int(own[2] + others[2]))
        # the node's path length, from the local point the march started at (so tau_own / s is its mean extinction
        # to the last bit, however short the chord of a node on a lit face)
        s = wp.max(light_path_length(vol, wp.transform_point(vol.to_local, x), toward, reach), 1.0e-20)
        base = vol.light_offset + 2 * li * nodes
        lightmap[base + node] = wp.min(tau_own, MAX_OPTICAL_DEPTH) / s
        lightmap[base + nodes + node] = wp.min(tau_in, MAX_OPTICAL_DEPTH)


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


@dataclass(frozen=True, eq=False)
class LightMapInputs:
    """What a light map's contents depend on (module docstring, "Cache"), and the storage they were written into."""

    storage: wp.array
    """the upload's light-map array: one upload holds one set of volumes (a scene with other volumes is a new upload
    with new storage), so the storage stands for them"""
    lights: tuple[Light, ...]
    light_samples: int
    cross_volume: bool
    generation: int = 0
    """the upload's streamed bricks' changes so far (`DeviceScene.stream_generation`): new bricks, a new map"""

    def matches(self, other: LightMapInputs | None) -> bool:
        """Whether ``other``'s map is this one: the same storage (held here, so no later array can take its place),
        equal lights, L, cross-volume and streamed bricks."""
        return (other is not None and other.storage is self.storage and other.lights == self.lights
                and other.light_samples == self.light_samples and other.cross_volume == self.cross_volume
                and other.generation == self.generation)


class LightMapCache:
    """The light-map pass of one renderer, skipped while its inputs equal those the storage was last filled with."""

    def __init__(self) -> None:
        self._filled: LightMapInputs | None = None

    def update(self, ds: DeviceScene, light_samples: int, clock: PassClock, cross_volume: bool = False,
               reuse: bool = True) -> bool:
        """Fill ``ds.lightmap`` unless it already holds these inputs' map (always with ``reuse`` False); returns
        whether the pass ran."""
        inputs = LightMapInputs(ds.lightmap, tuple(ds.scene.lights), light_samples, bool(cross_volume),
                                ds.stream_generation)
        if reuse and inputs.matches(self._filled):
            return False
        compute_light_map(ds, light_samples, clock, cross_volume)
        self._filled = inputs
        return True

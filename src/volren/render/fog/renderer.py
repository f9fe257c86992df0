"""Froxel volumetric fog for many viewers (paper 003: Stojanovic et al. 2023, after Hillaire 2015), ``--method fog``.

Per frame and viewer: (1) lighting: every froxel's in-scattered radiance and extinction at its (jittered) centre,
S = sigma_s (sum_i phase_i V_i E_i + L_ambient) + emission, sigma_t; (2) accumulation: front to back along each
froxel column with Hillaire's energy-conserving step, S_int = (S - S exp(-sigma_t dl)) / sigma_t, storing the
integrated scattering and transmittance at every slice boundary; (3) application: each pixel reads the integrated
volume trilinearly at its surface depth and composites colour * T + S.

Light visibility V_i comes from one of two pipelines (``sharing``):
- ``none`` (the per-viewer reference): a ray-traced shadow ray per light and froxel, every viewer on its own;
- ``grid`` (paper 003 §3.1): (a) a world-space shadow grid over the scene with one uint8 light bitmask per voxel,
  re-traced each frame only for voxels inside some viewer's frustum and, after the first frame, only for the voxels
  of this frame's z parity (alternating, so each voxel refreshes every second frame); (b) a shadow frustum per viewer
  with 16x16-pixel froxels and a third of the depth slices over its own near range (``frustum_range``), all viewers
  in one launch; (c) lighting reads the shadow frustum within its range and the shadow grid (nearest voxel, or
  trilinear over the 8 nearest bitmasks) beyond.

Outside the shadow grid (a viewer outside the scene's bounds, or froxels beyond its walls; the paper keeps its
viewers inside and does not say) the grid pads the bounds of every occluder, so a shadow ray from outside that misses
the grid's box reaches its light; one that crosses it takes the nearest voxels inside (clamped to the border), like
the trilinear lookup at the border. Taking the whole outside as lit made fog in the hall's shadow 16x too bright.
Tracing those rays instead scored the same (courtyard, 4 wandering viewers at 192x108, 1 m voxels, no shadow frustum:
mean per-view PSNR 56.5 vs 55.5 dB, same minimum) for 7x the shadow rays (336,700 vs 49,511).

Temporal integration (Hillaire): froxel depths are jittered per frame (Halton base 2) and blended with the previous
frame's result reprojected into the previous camera (exponential weight ``temporal_weight``); a froxel whose history
falls outside the old grid starts afresh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.errors import VolrenError
from volren.kernels.common import (
    CameraGPU,
    LightGPU,
    OpaqueGPU,
    ViewBuffers,
    box_hit,
    corner_weight,
    count,
    counter_row,
    light_distance,
    light_irradiance,
    light_travel_dir,
)
from volren.render.base import Renderer
from volren.render.compositing.surfaces import occluded
from volren.render.fog.froxels import (
    FogGPU,
    FroxelGrid,
    depth_slice,
    fog_density,
    fog_struct,
    froxel_bytes,
    froxel_coords,
    froxel_grid,
    froxel_ray,
    halton,
    inscatter_source,
    light_phase,
    slice_depth,
)
from volren.render.frame import SHADOW_RAYS, SHADOW_VOXELS, PassClock
from volren.scene import Fog, Scene, Sphere, TriangleMesh
from volren.upload import DeviceScene, camera_struct

SHARING = ("none", "grid")
MAX_FOG_LIGHTS = 8
"""one uint8 bitmask per shadow-grid voxel"""
VIS_TRACE = wp.constant(0)
VIS_SHARED = wp.constant(1)


@dataclass(frozen=True)
class FogConfig:
    sharing: str = "grid"
    """none: per-viewer reference (a shadow ray per froxel and light); grid: shared shadow grid (paper 003)"""
    tile: int = 8
    """[px] froxel width"""
    slices: int = 128
    near: float = 0.1
    """[m] start of the fog range (linear depth)"""
    far: float = 64.0
    """[m] end of the fog range; surfaces beyond see the fog up to here"""
    voxel_size: float = 0.5
    """[m] shadow-grid voxel edge (grid sharing)"""
    frustum_tile: int = 16
    """[px] shadow-frustum froxel width (grid sharing)"""
    frustum_range: float = 1.0 / 3.0
    """grid sharing: the most of the fog range's distance that the shadow frustum covers (paper 003 §3.1.2: the local
    volume captures the near field). Its slices, a third of ``slices``, are exponentially spaced over its own depth
    range [near, z_f]; lighting reads it there and the shadow grid beyond. z_f = near + frustum_range (far - near),
    but no deeper than where a frustum froxel grows as wide as a grid voxel (`frustum_reach`): beyond that the grid
    resolves more (hall, 16-viewer arc at 96x54, 1 m voxels: minimum per-view PSNR 26.2 dB with a third of the range,
    30.7 dB when cut there, 26.9 dB without a frustum). Sharing the froxel grid's slices instead put the frustum at
    0.1-0.83 m of a 0.1-64 m range, where it changed nothing. 0 turns the frustum off (grid only)."""
    trilinear: bool = False
    """grid sharing: interpolate the 8 nearest voxels' visibility instead of taking the nearest"""
    temporal: bool = True
    """jitter froxel depths per frame and blend with the reprojected history"""
    temporal_weight: float = 0.1
    """weight of the new frame in the temporal blend"""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.sharing not in SHARING:
            raise VolrenError(f"fog sharing must be one of {', '.join(SHARING)}, got '{self.sharing}'")
        if not 1 <= self.tile <= 256 or not 1 <= self.frustum_tile <= 256:
            raise VolrenError(f"froxel sizes must lie in [1, 256] px, got {self.tile} and {self.frustum_tile}")
        if not 3 <= self.slices <= 1024:
            raise VolrenError(f"fog slices must lie in [3, 1024], got {self.slices}")
        if not (0 < self.near < self.far and math.isfinite(self.far)):
            raise VolrenError(f"fog range needs 0 < near < far, got {self.near} and {self.far}")
        if not (math.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise VolrenError(f"shadow-grid voxel size must be > 0, got {self.voxel_size}")
        if not 0 <= self.frustum_range <= 1:
            raise VolrenError(f"shadow-frustum range must lie in [0, 1] (a fraction of the fog range), got "
                              f"{self.frustum_range}")
        if not 0 < self.temporal_weight <= 1:
            raise VolrenError(f"temporal weight must lie in (0, 1], got {self.temporal_weight}")


@wp.struct
class ShadowGrid:
    """World-space light-visibility bitmasks: voxel (i, j, k) spans lo + [i, i + 1) voxel_size along x, etc."""

    lo: wp.vec3
    voxel_size: float
    res: wp.vec3i
    bits: wp.array3d(dtype=wp.uint8)
    """[k, j, i]"""
    bounded: int
    """1: every occluder lies inside the grid's box (a scene without an infinite plane)"""


@wp.struct
class Occluders:
    opaque: wp.array(dtype=OpaqueGPU)
    mesh_ids: wp.array(dtype=wp.uint64)
    lights: wp.array(dtype=LightGPU)


@wp.func
def visibility_bits(occ: Occluders, x: wp.vec3) -> int:
    """Bit i set when light i reaches x unoccluded (a shadow ray per light)."""
    bits = int(0)
    for li in range(occ.lights.shape[0]):
        light = occ.lights[li]
        to_light = -light_travel_dir(light, x)
        if not occluded(x, to_light, light_distance(light, x), occ.opaque, occ.mesh_ids):
            bits = bits | (1 << li)
    return bits


@wp.func
def in_frusta(cams: wp.array(dtype=CameraGPU), far: float, x: wp.vec3, margin: float) -> bool:
    """Whether x lies within ``margin`` of some viewer's frustum (up to the fog's far depth)."""
    for v in range(cams.shape[0]):
        cam = cams[v]
        q = x - cam.origin
        z = wp.dot(q, cam.forward)
        if z > -margin and z < far + margin:
            zc = wp.max(z, 0.0)
            slack = margin * wp.sqrt(1.0 + cam.tan_half_fov * cam.tan_half_fov * (1.0 + cam.aspect * cam.aspect))
            rx = zc * cam.tan_half_fov * cam.aspect + slack
            ry = zc * cam.tan_half_fov + slack
            if wp.abs(wp.dot(q, cam.right)) <= rx and wp.abs(wp.dot(q, cam.up)) <= ry:
                return True
    return False


@wp.kernel
def shadow_grid_kernel(
    grid: ShadowGrid,
    cams: wp.array(dtype=CameraGPU),
    far: float,
    parity: int,
    occ: Occluders,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """(a) Re-trace the voxels of this frame's z parity (-1: all) that lie in some viewer's frustum."""
    r, i = wp.tid()
    counters = counter_row(counter_rows, r, i)
    row = r + row0
    k = row / grid.res[1]
    j = row - k * grid.res[1]
    if parity >= 0 and k % 2 != parity:
        return
    x = grid.lo + (wp.vec3(float(i), float(j), float(k)) + wp.vec3(0.5)) * grid.voxel_size
    if not in_frusta(cams, far, x, 0.87 * grid.voxel_size):
        return
    grid.bits[k, j, i] = wp.uint8(visibility_bits(occ, x))
    count(counters, SHADOW_VOXELS, 1)
    count(counters, SHADOW_RAYS, occ.lights.shape[0])


@wp.func
def froxel_centre(cams: wp.array(dtype=CameraGPU), grids: wp.array(dtype=FroxelGrid), slices: int, ny: int, row: int,
                  ix: int, jitter: float):
    """Froxel (view, k, iy, ix) of a stacked launch's cell (row, ix), rows ordered (view, slice, iy): (view, k, iy,
    unit ray direction, world point at the jittered slice depth, 0 past the viewer's own grid else 1)."""
    view = row / (slices * ny)
    k = (row / ny) % slices
    iy = row % ny
    cam = cams[view]
    g = grids[view]
    inside = int(1)
    if ix >= g.nx or iy >= g.ny:
        inside = 0
    d = froxel_ray(cam, g, ix, iy)
    x = cam.origin + d * (slice_depth(g, float(k) + jitter) / wp.dot(d, cam.forward))
    return view, k, iy, d, x, inside


@wp.kernel
def shadow_frustum_kernel(
    cams: wp.array(dtype=CameraGPU),
    grids: wp.array(dtype=FroxelGrid),
    slices: int,
    ny: int,
    jitter: float,
    occ: Occluders,
    bits: wp.array4d(dtype=wp.uint8),
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """(b) Every viewer's shadow frustum in one launch: coarse froxels over the first ``slices`` slices."""
    r, ix = wp.tid()
    counters = counter_row(counter_rows, r, ix)
    view, k, iy, _d, x, inside = froxel_centre(cams, grids, slices, ny, r + row0, ix, jitter)
    if inside == 0:
        return
    bits[view, k, iy, ix] = wp.uint8(visibility_bits(occ, x))
    count(counters, SHADOW_RAYS, occ.lights.shape[0])


@wp.func
def misses_grid(grid: ShadowGrid, x: wp.vec3, light: LightGPU) -> bool:
    """Whether x lies outside the grid's box and its shadow ray towards ``light`` misses the box. The grid pads the
    bounds of every occluder of a bounded scene, so such a ray surely reaches its light."""
    half = 0.5 * grid.voxel_size * wp.vec3(float(grid.res[0]), float(grid.res[1]), float(grid.res[2]))
    q = x - (grid.lo + half)
    if grid.bounded == 0 or (wp.abs(q[0]) < half[0] and wp.abs(q[1]) < half[1] and wp.abs(q[2]) < half[2]):
        return False
    t = box_hit(wp.cw_div(q, half), wp.cw_div(-light_travel_dir(light, x), half))
    return t[1] <= wp.max(t[0], 0.0) or t[0] >= light_distance(light, x)


@wp.func
def grid_visibility(grid: ShadowGrid, x: wp.vec3, light: LightGPU, li: int, trilinear: int) -> float:
    """Light ``li``'s visibility at x from the shadow grid: the nearest voxel's bit, or the trilinear blend of the 8
    nearest voxels' bits. Outside the grid: 1 where the shadow ray misses the grid (`misses_grid`), else the nearest
    voxels inside (clamped to the border)."""
    if misses_grid(grid, x, light):
        return 1.0
    f = (x - grid.lo) / grid.voxel_size
    if trilinear == 0:
        i = wp.clamp(int(wp.floor(f[0])), 0, grid.res[0] - 1)
        j = wp.clamp(int(wp.floor(f[1])), 0, grid.res[1] - 1)
        k = wp.clamp(int(wp.floor(f[2])), 0, grid.res[2] - 1)
        return float((int(grid.bits[k, j, i]) >> li) & 1)
    c = f - wp.vec3(0.5)
    i0 = int(wp.floor(c[0]))
    j0 = int(wp.floor(c[1]))
    k0 = int(wp.floor(c[2]))
    a = c - wp.vec3(float(i0), float(j0), float(k0))
    vis = float(0.0)
    for n in range(8):
        i = wp.clamp(i0 + n % 2, 0, grid.res[0] - 1)
        j = wp.clamp(j0 + (n / 2) % 2, 0, grid.res[1] - 1)
        k = wp.clamp(k0 + n / 4, 0, grid.res[2] - 1)
        vis += corner_weight(n, a) * float((int(grid.bits[k, j, i]) >> li) & 1)
    return vis


@wp.func
def frustum_lookup(cam: CameraGPU, fg: FroxelGrid, bits: wp.array4d(dtype=wp.uint8), view: int, x: wp.vec3,
                   jitter: float) -> int:
    """The light bitmask of the shadow-frustum froxel nearest to x (its samples sit at slice coordinate k + jitter)."""
    c = froxel_coords(cam, fg, x)
    fx = wp.clamp(int(wp.floor(c[0])), 0, fg.nx - 1)
    fy = wp.clamp(int(wp.floor(c[1])), 0, fg.ny - 1)
    fk = wp.clamp(int(wp.floor(c[2] - jitter + 0.5)), 0, fg.slices - 1)
    return int(bits[view, fk, fy, fx])


@wp.func
def froxel_trilinear(volume: wp.array4d(dtype=wp.vec4), view: int, size: wp.vec3i, f: wp.vec3) -> wp.vec4:
    """Trilinear lookup of ``volume[view]`` at continuous index f = (ix, iy, k) (samples at integers), clamped to the
    ``size`` = (nx, ny, nk) samples the view uses."""
    x0 = int(wp.floor(f[0]))
    y0 = int(wp.floor(f[1]))
    k0 = int(wp.floor(f[2]))
    a = f - wp.vec3(float(x0), float(y0), float(k0))
    acc = wp.vec4(0.0)
    for n in range(8):
        i = wp.clamp(x0 + n % 2, 0, size[0] - 1)
        j = wp.clamp(y0 + (n / 2) % 2, 0, size[1] - 1)
        k = wp.clamp(k0 + n / 4, 0, size[2] - 1)
        acc += corner_weight(n, a) * volume[view, k, j, i]
    return acc


@wp.kernel
def froxel_lighting_kernel(
    cams: wp.array(dtype=CameraGPU),
    prev_cams: wp.array(dtype=CameraGPU),
    grids: wp.array(dtype=FroxelGrid),
    slices: int,
    ny: int,
    jitter: float,
    fog: FogGPU,
    ambient: wp.vec3,
    occ: Occluders,
    mode: int,
    grid: ShadowGrid,
    trilinear: int,
    frustum_grids: wp.array(dtype=FroxelGrid),
    frustum_bits: wp.array4d(dtype=wp.uint8),
    frustum: int,
    history: wp.array4d(dtype=wp.vec4),
    weight: float,
    out: wp.array4d(dtype=wp.vec4),
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """(1) Lighting of every froxel of every viewer: (S, sigma_t), blended with the reprojected history when
    weight < 1. Visibility by shadow rays (mode VIS_TRACE) or (VIS_SHARED) from the shadow frustum (when ``frustum``
    is 1) up to its far depth and from the shadow grid beyond (`grid_visibility`, also outside the grid)."""
    r, ix = wp.tid()
    counters = counter_row(counter_rows, r, ix)
    view, k, iy, d, x, inside = froxel_centre(cams, grids, slices, ny, r + row0, ix, jitter)
    if inside == 0:
        return
    g = grids[view]
    # Light bitmask from shadow rays or the shadow frustum; -1: read the shadow grid per light (maybe trilinear).
    bits = int(-1)
    rays = int(0)
    if mode == VIS_TRACE:
        bits = visibility_bits(occ, x)
        rays = occ.lights.shape[0]
    elif frustum == 1 and wp.dot(x - cams[view].origin, cams[view].forward) < frustum_grids[view].far:
        bits = frustum_lookup(cams[view], frustum_grids[view], frustum_bits, view, x, jitter)
    radiance = ambient
    for li in range(occ.lights.shape[0]):
        light = occ.lights[li]
        vis = float((bits >> li) & 1)
        if bits < 0:
            vis = grid_visibility(grid, x, light, li, trilinear)
        if vis > 0.0:
            radiance += vis * light_phase(fog, light_travel_dir(light, x), d) * light_irradiance(light, x)
    value = inscatter_source(fog, fog_density(fog, x), radiance)
    if weight < 1.0:
        # Reproject into the previous frame's grid, trilinear between its froxel centres (nearest would round a
        # motion of under half a froxel per frame away, so the history would never follow it); no history there:
        # start afresh.
        c = froxel_coords(prev_cams[view], g, x)
        if c[0] >= 0.0 and c[1] >= 0.0 and c[2] >= 0.0 and c[0] < float(g.nx) and c[1] < float(g.ny) and (
                c[2] < float(g.slices)):
            old = froxel_trilinear(history, view, wp.vec3i(g.nx, g.ny, g.slices), c - wp.vec3(0.5))
            value = weight * value + (1.0 - weight) * old
    out[view, k, iy, ix] = value
    count(counters, SHADOW_RAYS, rays)


@wp.kernel
def froxel_accumulate_kernel(
    cams: wp.array(dtype=CameraGPU),
    grids: wp.array(dtype=FroxelGrid),
    ny: int,
    lighting: wp.array4d(dtype=wp.vec4),
    integrated: wp.array4d(dtype=wp.vec4),
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """(2) Front-to-back integration of each froxel column; integrated[view, k] holds (S, T) at slice boundary k."""
    r, ix = wp.tid()
    row = r + row0
    view = row / ny
    iy = row % ny
    cam = cams[view]
    g = grids[view]
    if ix >= g.nx or iy >= g.ny:
        return
    d = froxel_ray(cam, g, ix, iy)
    facing = wp.dot(d, cam.forward)
    s_acc = wp.vec3(0.0)
    t_acc = float(1.0)
    integrated[view, 0, iy, ix] = wp.vec4(0.0, 0.0, 0.0, 1.0)
    for k in range(g.slices):
        dl = (slice_depth(g, float(k + 1)) - slice_depth(g, float(k))) / facing
        v = lighting[view, k, iy, ix]
        s = wp.vec3(v[0], v[1], v[2])
        sigma_t = v[3]
        t_step = wp.exp(-sigma_t * dl)
        s_int = s * dl
        if sigma_t > 1.0e-7:
            s_int = (s - s * t_step) / sigma_t
        s_acc += t_acc * s_int
        t_acc *= t_step
        integrated[view, k + 1, iy, ix] = wp.vec4(s_acc[0], s_acc[1], s_acc[2], t_acc)


@wp.kernel
def froxel_apply_kernel(
    cam: CameraGPU,
    g: FroxelGrid,
    view: int,
    integrated: wp.array4d(dtype=wp.vec4),
    buffers: ViewBuffers,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """(3) Per pixel: colour T + S at the surface's depth (the fog's far end where there is none)."""
    r, col = wp.tid()
    row = r + row0
    z = buffers.occluder_depth[row, col]
    w = depth_slice(g, wp.min(z, g.far))
    fx = (float(col) + 0.5) / float(g.tile) - 0.5
    fy = (float(row) + 0.5) / float(g.tile) - 0.5
    v = froxel_trilinear(integrated, view, wp.vec3i(g.nx, g.ny, g.slices + 1), wp.vec3(fx, fy, w))
    surface = buffers.occluder_color[row, col]
    rgb = wp.vec3(v[0], v[1], v[2]) + v[3] * wp.vec3(surface[0], surface[1], surface[2])
    alpha = 1.0 - v[3] * (1.0 - surface[3])
    buffers.image[row, col] = wp.vec4(rgb[0], rgb[1], rgb[2], alpha)
    buffers.depth[row, col] = z


def frustum_reach(cam: Camera, tile: int, voxel_size: float) -> float:
    """Linear depth [m] at which a ``tile``-pixel froxel of ``cam`` is ``voxel_size`` wide (vertically)."""
    return voxel_size * cam.height / (2 * cam.tan_half_fov * tile)


def occluders(ds: DeviceScene) -> Occluders:
    o = Occluders()
    o.opaque, o.mesh_ids, o.lights = ds.opaque, ds.mesh_ids, ds.lights
    return o


def frusta_corners(views: list[Camera], far: float) -> np.ndarray:
    """World corners of the viewers' frusta cut at linear depth ``far`` (8 per viewer)."""
    out = []
    for cam in views:
        inv = np.linalg.inv(cam.view_matrix())
        for z in (cam.near, far):
            for sx in (-1, 1):
                for sy in (-1, 1):
                    p = np.array([sx * z * cam.tan_half_fov * cam.width / cam.height, sy * z * cam.tan_half_fov, -z, 1])
                    out.append((inv @ p)[:3])
    return np.array(out)


def scene_bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray] | None:
    """World bounds of the meshes, spheres and fog boxes; None for a scene with an infinite plane (or nothing)."""
    points = []
    for o in scene.opaque:
        if isinstance(o, TriangleMesh):
            points.append(o.vertices)
        elif isinstance(o, Sphere):
            points.append(np.array([np.subtract(o.center, o.radius), np.add(o.center, o.radius)]))
        else:
            return None
    for b in scene.fog.boxes:
        points.append(np.array([np.subtract(b.center, b.half_size), np.add(b.center, b.half_size)]))
    if not points:
        return None
    p = np.concatenate(points)
    return p.min(0), p.max(0)


MAX_GRID_VOXELS = 2**28


class FogRenderer(Renderer):
    """Froxel fog; ``config`` is a `FogConfig`. Keeps the shadow grid and the temporal history between frames."""

    name = "fog"
    needs_volumes: ClassVar[bool] = False

    def __init__(self, config: FogConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or FogConfig(), device)
        self._grid: ShadowGrid | None = None
        self._grid_key: tuple | None = None
        self._history: wp.array | None = None
        self._history_key: tuple | None = None
        self._prev_cams: list[CameraGPU] | None = None
        self._fog: tuple[Fog, FogGPU] | None = None

    def _prepare(self, scene, clock: PassClock, frame: int) -> DeviceScene:
        if scene.fog is None:
            raise VolrenError(f"method 'fog' needs a scene with fog; scene '{scene.name}' has none")
        fire = [v.name for v in scene.volumes if v.emission_grid is not None]
        if fire:
            raise VolrenError(f"method 'fog' has no blackbody emission: the emission grid of volume '{fire[0]}' "
                              "would do nothing (use dssrm, cmsrm, cacrm, reference or vpt)")
        if len(scene.lights) > MAX_FOG_LIGHTS:
            raise VolrenError(f"fog supports at most {MAX_FOG_LIGHTS} lights, scene '{scene.name}' has "
                              f"{len(scene.lights)}")
        return self._upload(scene, clock)

    def release_views(self) -> None:
        super().release_views()
        self._history = self._history_key = self._prev_cams = None

    def _shadow_grid(self, ds: DeviceScene, views: list[Camera]) -> tuple[ShadowGrid, bool]:
        """The persistent shadow grid over the scene's bounds, padded by a voxel (new: every voxel must be traced
        once). It is kept while the bounds stay the same, also across re-built scenes (objects moving inside a fixed
        room), and re-traced by parity. An unbounded scene (an infinite plane) gets a grid over the frusta of the
        frame that first needs one, kept for as long as the voxel size."""
        voxel = self.config.voxel_size
        bounds = scene_bounds(ds.scene)
        key = (voxel, None if bounds is None else (tuple(bounds[0]), tuple(bounds[1])))
        if self._grid is not None and self._grid_key == key:
            return self._grid, False
        lo, hi = bounds if bounds is not None else (frusta_corners(views, self.config.far).min(0),
                                                    frusta_corners(views, self.config.far).max(0))
        lo, hi = lo - voxel, hi + voxel
        res = tuple(int(n) for n in np.maximum(np.ceil((hi - lo) / voxel), 1))
        if math.prod(res) > MAX_GRID_VOXELS:
            raise VolrenError(f"shadow grid of {res[0]}x{res[1]}x{res[2]} voxels is too large; use a larger "
                              f"--voxel-size than {self.config.voxel_size} m")
        g = ShadowGrid()
        g.lo, g.voxel_size, g.res = wp.vec3(*lo), voxel, wp.vec3i(*res)
        g.bits = wp.zeros(res[::-1], dtype=wp.uint8, device=self.device)
        g.bounded = int(bounds is not None)
        self._grid, self._grid_key = g, key
        return g, True

    def _render_views(self, ds: DeviceScene, views: list[Camera], frame: int, targets: list[ViewBuffers],
                      clock: PassClock) -> None:
        c = self.config
        grids = [froxel_grid(cam, c.tile, c.slices, c.near, c.far) for cam in views]
        ny, nx = max(g.ny for g in grids), max(g.nx for g in grids)
        cams = [camera_struct(cam) for cam in views]
        cams_gpu = wp.array(cams, dtype=CameraGPU, device=self.device)
        grids_gpu = wp.array(grids, dtype=FroxelGrid, device=self.device)
        occ = occluders(ds)
        if self._fog is None or self._fog[0] != ds.scene.fog:
            with clock.measure("fog_bake"):
                self._fog = (ds.scene.fog, fog_struct(ds.scene.fog, self.device))
        fog = self._fog[1]
        jitter = halton(frame + c.seed, 2) if c.temporal else 0.5
        shape = (len(views), c.slices, ny, nx)
        # Temporal history: valid for the same viewers' grids as the last frame.
        key = (shape, tuple((v.width, v.height) for v in views))
        weight = 1.0
        if c.temporal and self._history is not None and self._history_key == key and self._prev_cams is not None:
            weight = c.temporal_weight
        history = self._history if weight < 1.0 else wp.zeros((1, 1, 1, 1), dtype=wp.vec4, device=self.device)
        prev = wp.array(self._prev_cams if weight < 1.0 else cams, dtype=CameraGPU, device=self.device)
        mode = VIS_TRACE
        grid = ShadowGrid()
        grid.lo, grid.voxel_size, grid.res = wp.vec3(0.0), 1.0, wp.vec3i(1, 1, 1)
        grid.bits = wp.zeros((1, 1, 1), dtype=wp.uint8, device=self.device)
        grid.bounded = 1
        fgrids_gpu = grids_gpu
        frustum = wp.zeros((1, 1, 1, 1), dtype=wp.uint8, device=self.device)
        info = {"froxel_bytes_per_viewer": [froxel_bytes([g]) for g in grids]}
        if c.sharing == "grid":
            mode = VIS_SHARED
            grid, fresh = self._shadow_grid(ds, views)
            res = (grid.res[0], grid.res[1], grid.res[2])
            with clock.measure("shadow_grid"):
                launch_rows(shadow_grid_kernel, res[2] * res[1], res[0],
                            [grid, cams_gpu, c.far, -1 if fresh else frame % 2, occ], self.device, clock.counters)
            info |= {"shadow_grid_voxels": list(res), "shadow_grid_bytes": math.prod(res),
                     "shadow_frustum_bytes_per_viewer": 0}
            if c.frustum_range > 0:
                limit = c.near + c.frustum_range * (c.far - c.near)
                frustum_slices = max(c.slices // 3, 1)
                fgrids = [froxel_grid(cam, c.frustum_tile, frustum_slices, c.near,
                                      max(min(limit, frustum_reach(cam, c.frustum_tile, c.voxel_size)), 2 * c.near))
                          for cam in views]
                fgrids_gpu = wp.array(fgrids, dtype=FroxelGrid, device=self.device)
                fny, fnx = max(g.ny for g in fgrids), max(g.nx for g in fgrids)
                frustum = wp.zeros((len(views), frustum_slices, fny, fnx), dtype=wp.uint8, device=self.device)
                with clock.measure("shadow_frustum"):
                    launch_rows(shadow_frustum_kernel, len(views) * frustum_slices * fny, fnx,
                                [cams_gpu, fgrids_gpu, frustum_slices, fny, jitter, occ, frustum], self.device,
                                clock.counters)
                info["shadow_frustum_bytes_per_viewer"] = frustum_slices * fny * fnx
        lighting = wp.empty(shape, dtype=wp.vec4, device=self.device)
        with clock.measure("lighting"):
            launch_rows(froxel_lighting_kernel, len(views) * c.slices * ny, nx,
                        [cams_gpu, prev, grids_gpu, c.slices, ny, jitter, fog, ds.ambient, occ, mode, grid,
                         int(c.trilinear), fgrids_gpu, frustum, int(c.frustum_range > 0), history, weight,
                         lighting],
                        self.device, clock.counters)
        integrated = wp.empty((len(views), c.slices + 1, ny, nx), dtype=wp.vec4, device=self.device)
        with clock.measure("accumulation"):
            launch_rows(froxel_accumulate_kernel, len(views) * ny, nx, [cams_gpu, grids_gpu, ny, lighting,
                                                                         integrated], self.device, clock.counters)
        with clock.measure("application"):
            for v, (cam, g) in enumerate(zip(views, grids, strict=True)):
                launch_rows(froxel_apply_kernel, cam.height, cam.width,
                            [cams[v], g, v, integrated, targets[v]], self.device, clock.counters, self.on_rows)
        self._history, self._history_key, self._prev_cams = lighting, key, cams
        self._frame_info |= info | {"jitter": jitter, "temporal_weight": weight}


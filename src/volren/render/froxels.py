"""Froxel grids and the participating media of the fog method (paper 003 §2-3, after Hillaire 2015).

A viewer's froxel grid splits its frustum into ``tile`` x ``tile``-pixel columns and ``slices`` depth slices whose
boundaries are exponentially distributed over the fog range [near, far] (linear view depth):
z_k = near (far / near)^(k / slices). Froxel (ix, iy, k) is centred at pixel ((ix + 1/2) tile, (iy + 1/2) tile)
(clamped to the image) and at the slice's depth z(k + j) for the frame's jitter j in [0, 1) (1/2 without temporal
integration). Arrays are stacked over viewers with the largest viewer's dimensions: index [view, k, iy, ix].
"""

from __future__ import annotations

import math

import warp as wp

from volren.camera import Camera
from volren.kernels.common import CameraGPU, hg_phase
from volren.scene import Fog


@wp.struct
class FroxelGrid:
    """One viewer's froxel grid: columns of ``tile`` pixels, ``slices`` slices over linear depth [near, far]."""

    nx: int
    ny: int
    slices: int
    tile: int
    near: float
    far: float
    log_ratio: float
    """ln(far / near)"""


@wp.struct
class FogBoxGPU:
    center: wp.vec3
    half_size: wp.vec3
    density: float
    noise_amount: float
    noise_frequency: float
    seed: int


@wp.struct
class FogGPU:
    extinction: float
    albedo: wp.vec3
    emission: wp.vec3
    g: float
    density: float
    height_density: float
    height_falloff: float
    height_base: float
    boxes: wp.array(dtype=FogBoxGPU)


def froxel_grid(cam: Camera, tile: int, slices: int, near: float, far: float) -> FroxelGrid:
    g = FroxelGrid()
    g.nx, g.ny = math.ceil(cam.width / tile), math.ceil(cam.height / tile)
    g.slices, g.tile, g.near, g.far = slices, tile, near, far
    g.log_ratio = math.log(far / near)
    return g


def fog_struct(fog: Fog, device: str) -> FogGPU:
    s = FogGPU()
    s.extinction, s.albedo, s.emission, s.g = fog.extinction, wp.vec3(*fog.albedo), wp.vec3(*fog.emission), fog.g
    s.density, s.height_density = fog.density, fog.height_density
    s.height_falloff, s.height_base = fog.height_falloff, fog.height_base
    boxes = []
    for b in fog.boxes:
        box = FogBoxGPU()
        box.center, box.half_size = wp.vec3(*b.center), wp.vec3(*b.half_size)
        box.density, box.noise_amount, box.noise_frequency, box.seed = (b.density, b.noise_amount,
                                                                        b.noise_frequency, b.seed)
        boxes.append(box)
    s.boxes = wp.array(boxes, dtype=FogBoxGPU, device=device) if boxes else wp.zeros(0, dtype=FogBoxGPU,
                                                                                       device=device)
    return s


@wp.func
def slice_depth(grid: FroxelGrid, w: float) -> float:
    """Linear depth at continuous slice coordinate w in [0, slices]."""
    return grid.near * wp.exp(w / float(grid.slices) * grid.log_ratio)


@wp.func
def depth_slice(grid: FroxelGrid, z: float) -> float:
    """Continuous slice coordinate of linear depth z, clamped to [0, slices]."""
    w = wp.log(wp.max(z, grid.near) / grid.near) / grid.log_ratio * float(grid.slices)
    return wp.min(w, float(grid.slices))


@wp.func
def froxel_ray(cam: CameraGPU, grid: FroxelGrid, ix: int, iy: int) -> wp.vec3:
    """Unit world direction through the centre of froxel column (ix, iy)."""
    px = wp.min((float(ix) + 0.5) * float(grid.tile), float(cam.width))
    py = wp.min((float(iy) + 0.5) * float(grid.tile), float(cam.height))
    x = (px / float(cam.width) * 2.0 - 1.0) * cam.tan_half_fov * cam.aspect
    y = (1.0 - py / float(cam.height) * 2.0) * cam.tan_half_fov
    return wp.normalize(cam.forward + x * cam.right + y * cam.up)


@wp.func
def froxel_coords(cam: CameraGPU, grid: FroxelGrid, x: wp.vec3) -> wp.vec3:
    """Continuous froxel coordinates (ix, iy, k), cell centres at +1/2, of world point x (depth may be < 0)."""
    v = x - cam.origin
    z = wp.dot(v, cam.forward)
    zc = wp.max(z, 1.0e-6)
    col = (wp.dot(v, cam.right) / (zc * cam.tan_half_fov * cam.aspect) + 1.0) * 0.5 * float(cam.width)
    row = (1.0 - wp.dot(v, cam.up) / (zc * cam.tan_half_fov)) * 0.5 * float(cam.height)
    k = float(-1.0)
    if z > 0.0:
        k = depth_slice(grid, z)
    return wp.vec3(col / float(grid.tile), row / float(grid.tile), k)


@wp.func
def fog_density(fog: FogGPU, x: wp.vec3) -> float:
    """Global + exponential height fog + noisy local boxes at world point x."""
    rho = fog.density
    if fog.height_density > 0.0:
        rho += fog.height_density * wp.exp(-fog.height_falloff * wp.max(x[1] - fog.height_base, 0.0))
    for b in range(fog.boxes.shape[0]):
        box = fog.boxes[b]
        q = x - box.center
        if wp.abs(q[0]) <= box.half_size[0] and wp.abs(q[1]) <= box.half_size[1] and wp.abs(q[2]) <= box.half_size[2]:
            n = wp.noise(wp.rand_init(box.seed), q * box.noise_frequency)
            rho += box.density * (1.0 - box.noise_amount + box.noise_amount * 0.5 * (n + 1.0))
    return rho


@wp.func
def inscatter_source(fog: FogGPU, rho: float, radiance: wp.vec3) -> wp.vec4:
    """(S, sigma_t) of a froxel: S = sigma_s radiance + emission rho, where ``radiance`` is sum phase vis E plus the
    isotropic ambient, and sigma_s = albedo sigma_t."""
    sigma_t = fog.extinction * rho
    s = wp.cw_mul(fog.albedo, radiance) * sigma_t + fog.emission * rho
    return wp.vec4(s[0], s[1], s[2], sigma_t)


@wp.func
def light_phase(fog: FogGPU, travel: wp.vec3, d: wp.vec3) -> float:
    """HG phase for light travelling along ``travel`` scattered back along -d towards the viewer."""
    return hg_phase(wp.dot(travel, -d), fog.g)


def froxel_bytes(grids: list[FroxelGrid]) -> int:
    """Device memory of the lighting and integrated volumes (vec4 float32 each) of these grids."""
    return int(sum(g.nx * g.ny * (2 * g.slices + 1) * 16 for g in grids))


def halton(index: int, base: int) -> float:
    """Radical inverse of ``index`` in ``base``: the froxel depth jitter of frame ``index`` (low discrepancy)."""
    f, r, i = 1.0, 0.0, index + 1
    while i > 0:
        f /= base
        r += f * (i % base)
        i //= base
    return r

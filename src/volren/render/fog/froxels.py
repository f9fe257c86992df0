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
from volren.kernels.common import CameraGPU, corner_weight, hg_phase
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
    offset: int
    """first cell of this box's baked density in FogGPU.baked"""
    res: wp.vec3i


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
    baked: wp.array(dtype=float)
    """every box's density on its own grid (x fastest), baked once from the noise (Hillaire's media volumes)"""


def froxel_grid(cam: Camera, tile: int, slices: int, near: float, far: float) -> FroxelGrid:
    g = FroxelGrid()
    g.nx, g.ny = math.ceil(cam.width / tile), math.ceil(cam.height / tile)
    g.slices, g.tile, g.near, g.far = slices, tile, near, far
    g.log_ratio = math.log(far / near)
    return g


BAKE_CELLS_PER_PERIOD = 4
MAX_BAKE_CELLS = 64
"""per axis and box"""


def bake_resolution(half_size: tuple[float, float, float], frequency: float) -> tuple[int, int, int]:
    """Cells per axis of a box's baked density: 4 per noise period, 4 to 64."""
    return tuple(int(min(max(math.ceil(2 * h * frequency * BAKE_CELLS_PER_PERIOD), 4), MAX_BAKE_CELLS))
                 for h in half_size)


@wp.func
def box_noise_density(box: FogBoxGPU, q: wp.vec3) -> float:
    """The box's density at q (relative to its centre): density (1 - a + a (noise + 1) / 2), Perlin noise."""
    n = wp.noise(wp.rand_init(box.seed), q * box.noise_frequency)
    return box.density * (1.0 - box.noise_amount + box.noise_amount * 0.5 * (n + 1.0))


@wp.kernel
def bake_box_kernel(box: FogBoxGPU, baked: wp.array(dtype=float)):
    k, j, i = wp.tid()
    cell = wp.vec3(float(i) + 0.5, float(j) + 0.5, float(k) + 0.5)
    res = wp.vec3(float(box.res[0]), float(box.res[1]), float(box.res[2]))
    q = wp.cw_mul(wp.cw_div(cell, res) * 2.0 - wp.vec3(1.0), box.half_size)
    baked[box.offset + (k * box.res[1] + j) * box.res[0] + i] = box_noise_density(box, q)


def fog_struct(fog: Fog, device: str) -> FogGPU:
    """The fog on the device, each box's noisy density baked into its grid."""
    s = FogGPU()
    s.extinction, s.albedo, s.emission, s.g = fog.extinction, wp.vec3(*fog.albedo), wp.vec3(*fog.emission), fog.g
    s.density, s.height_density = fog.density, fog.height_density
    s.height_falloff, s.height_base = fog.height_falloff, fog.height_base
    boxes, offset = [], 0
    for b in fog.boxes:
        box = FogBoxGPU()
        box.center, box.half_size = wp.vec3(*b.center), wp.vec3(*b.half_size)
        box.density, box.noise_amount, box.noise_frequency, box.seed = (b.density, b.noise_amount,
                                                                        b.noise_frequency, b.seed)
        res = bake_resolution(b.half_size, b.noise_frequency)
        box.offset, box.res = offset, wp.vec3i(*res)
        offset += math.prod(res)
        boxes.append(box)
    s.boxes = wp.array(boxes, dtype=FogBoxGPU, device=device) if boxes else wp.zeros(0, dtype=FogBoxGPU,
                                                                                       device=device)
    s.baked = wp.zeros(max(offset, 1), dtype=float, device=device)
    for box in boxes:
        wp.launch(bake_box_kernel, dim=(box.res[2], box.res[1], box.res[0]), inputs=[box, s.baked], device=device)
    return s


@wp.func
def baked_density(fog: FogGPU, box: FogBoxGPU, q: wp.vec3) -> float:
    """Trilinear lookup of a box's baked density at q (relative to its centre, inside the box)."""
    res = wp.vec3(float(box.res[0]), float(box.res[1]), float(box.res[2]))
    f = wp.cw_mul(wp.cw_div(q, box.half_size) * 0.5 + wp.vec3(0.5), res) - wp.vec3(0.5)
    i0 = int(wp.floor(f[0]))
    j0 = int(wp.floor(f[1]))
    k0 = int(wp.floor(f[2]))
    a = f - wp.vec3(float(i0), float(j0), float(k0))
    acc = float(0.0)
    for n in range(8):
        i = wp.clamp(i0 + n % 2, 0, box.res[0] - 1)
        j = wp.clamp(j0 + (n / 2) % 2, 0, box.res[1] - 1)
        k = wp.clamp(k0 + n / 4, 0, box.res[2] - 1)
        acc += corner_weight(n, a) * fog.baked[box.offset + (k * box.res[1] + j) * box.res[0] + i]
    return acc


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
    """Global + exponential height fog + noisy local boxes (their baked grids) at world point x."""
    rho = fog.density
    if fog.height_density > 0.0:
        rho += fog.height_density * wp.exp(-fog.height_falloff * wp.max(x[1] - fog.height_base, 0.0))
    for b in range(fog.boxes.shape[0]):
        box = fog.boxes[b]
        q = x - box.center
        if wp.abs(q[0]) <= box.half_size[0] and wp.abs(q[1]) <= box.half_size[1] and wp.abs(q[2]) <= box.half_size[2]:
            rho += baked_density(fog, box, q)
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

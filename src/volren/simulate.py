"""Animated densities for the dynamic GI tests (paper 000 Fig. 11): per-voxel semi-Lagrangian advection in Warp.

The velocity field is a swirl about the volume's vertical axis, strongest at mid radius, plus a slow rise, so the
smoke shears into new filaments every frame (every voxel's density changes, as in a fluid simulation) while staying
inside the box. A fixed time step per frame reproduces V-sync at a frame rate: at 30 fps each frame moves the smoke
twice as far as at 60 fps.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np
import warp as wp

from volren.errors import VolrenError
from volren.kernels.common import sample_grid, voxel_center
from volren.scene import Scene


@wp.kernel
def advect_kernel(src: wp.array(dtype=float), dst: wp.array(dtype=float), res: wp.vec3i, dt: float, swirl: float,
                  rise: float):
    """dst(p) = src(p - dt v(p)) (one semi-Lagrangian step; outside the box the border value, ~0 for smoke)."""
    i, j, k = wp.tid()
    p = voxel_center(i, j, k, res)
    r2 = p[0] * p[0] + p[2] * p[2]
    v = wp.vec3(-p[2], 0.0, p[0]) * (swirl * wp.exp(-2.0 * r2)) + wp.vec3(0.0, rise, 0.0)
    dst[(k * res[1] + j) * res[0] + i] = sample_grid(src, 0, res, p - dt * v)


def advected_frames(scene: Scene, frames: int, fps: float = 60.0, swirl: float = 1.5, rise: float = 0.05,
                    device: str = "cpu") -> Iterator[Scene]:
    """The scene at each of ``frames`` frames, its first volume's density advected by ``1 / fps`` s per frame
    (swirl [rad/s] at the axis, rise [box half-widths/s])."""
    if not scene.volumes:
        raise VolrenError("advection needs a scene with a volume")
    if not (math.isfinite(fps) and 1 <= fps <= 240):
        raise VolrenError(f"fps must lie in [1, 240], got {fps}")
    vol = scene.volumes[0]
    nz, ny, nx = vol.density.shape
    res = wp.vec3i(nx, ny, nz)
    a = wp.array(vol.density.reshape(-1), dtype=float, device=device)
    b = wp.empty_like(a)
    for f in range(frames):
        if f > 0:
            wp.launch(advect_kernel, dim=(nx, ny, nz), inputs=[a, b, res, 1.0 / fps, swirl, rise], device=device)
            a, b = b, a
        moved = dataclasses.replace(vol, density=np.maximum(a.numpy().reshape(nz, ny, nx), 0.0))
        yield dataclasses.replace(scene, volumes=(moved, *scene.volumes[1:]))

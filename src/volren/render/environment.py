"""The environment as a light for path tracing: importance sampling of an equirectangular map by luminance.

A direction is drawn with probability proportional to the map's luminance times sin(theta) (the solid angle of a
pixel row): a row from the marginal CDF, then a column from that row's conditional CDF, both by binary search, and
uniformly inside the pixel. Its solid-angle pdf is p(row, col) H W / (2 pi^2 sin theta). A constant environment is
sampled uniformly over the sphere (pdf 1 / 4 pi). Convention: `volren.scene.Environment`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from volren.scene import Environment

ENV_NONE = wp.constant(0)
ENV_CONSTANT = wp.constant(1)
ENV_IMAGE = wp.constant(2)


@wp.struct
class EnvironmentLight:
    mode: int
    radiance: wp.vec3
    """constant mode"""
    image: wp.array2d(dtype=wp.vec3)
    marginal: wp.array(dtype=float)
    """CDF over rows, H + 1 entries from 0 to 1"""
    conditional: wp.array2d(dtype=float)
    """per row, CDF over columns, W + 1 entries from 0 to 1"""


def environment_light(env: Environment | None, device: str) -> EnvironmentLight:
    """The sampling tables of ``env`` (None or black: no environment light)."""
    e = EnvironmentLight()
    e.mode, e.radiance = ENV_NONE, wp.vec3(0.0)
    image = np.zeros((1, 1, 3), np.float32)
    marginal, conditional = np.array([0.0, 1.0]), np.array([[0.0, 1.0]])
    if env is not None and env.image is not None:
        image = env.image.astype(np.float32)
        h = image.shape[0]
        theta = (np.arange(h) + 0.5) / h * np.pi
        weight = (image @ np.array([0.2126, 0.7152, 0.0722])) * np.sin(theta)[:, None] + 1e-12
        rows = weight.sum(axis=1)
        conditional = np.concatenate([np.zeros((h, 1)), np.cumsum(weight, axis=1) / rows[:, None]], axis=1)
        marginal = np.concatenate([[0.0], np.cumsum(rows) / rows.sum()])
        e.mode = ENV_IMAGE
    elif env is not None and max(env.radiance) > 0:
        e.mode, e.radiance = ENV_CONSTANT, wp.vec3(*env.radiance)
    e.image = wp.array(image, dtype=wp.vec3, device=device)
    e.marginal = wp.array(marginal.astype(np.float32), dtype=float, device=device)
    e.conditional = wp.array(conditional.astype(np.float32), dtype=float, device=device)
    return e


@wp.func
def cdf_find(cdf: wp.array(dtype=float), n: int, xi: float) -> int:
    """The bin i in [0, n) with cdf[i] <= xi < cdf[i + 1] (binary search over n + 1 entries)."""
    lo = int(0)
    hi = n
    while hi - lo > 1:
        mid = (lo + hi) / 2
        if cdf[mid] <= xi:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def row_find(cdf: wp.array2d(dtype=float), row: int, n: int, xi: float) -> int:
    lo = int(0)
    hi = n
    while hi - lo > 1:
        mid = (lo + hi) / 2
        if cdf[row, mid] <= xi:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def sample_environment(env: EnvironmentLight, state: wp.uint32):
    """(unit direction towards the environment, its radiance / pdf, state); radiance / pdf = 0 for no light."""
    if env.mode == ENV_NONE:
        return wp.vec3(0.0, 1.0, 0.0), wp.vec3(0.0), state
    if env.mode == ENV_CONSTANT:
        z = 1.0 - 2.0 * wp.randf(state)
        phi = 2.0 * wp.pi * wp.randf(state)
        r = wp.sqrt(wp.max(1.0 - z * z, 0.0))
        return wp.vec3(r * wp.cos(phi), r * wp.sin(phi), z), env.radiance * (4.0 * wp.pi), state
    h = env.image.shape[0]
    w = env.image.shape[1]
    row = cdf_find(env.marginal, h, wp.randf(state))
    col = row_find(env.conditional, row, w, wp.randf(state))
    p = (env.marginal[row + 1] - env.marginal[row]) * (env.conditional[row, col + 1] - env.conditional[row, col])
    theta = wp.pi * (float(row) + wp.randf(state)) / float(h)
    phi = 2.0 * wp.pi * (float(col) + wp.randf(state)) / float(w)
    s = wp.sin(theta)
    direction = wp.vec3(s * wp.cos(phi), wp.cos(theta), s * wp.sin(phi))
    pdf = p * float(h * w) / (2.0 * wp.pi * wp.pi * wp.max(s, 1.0e-6))
    return direction, env.image[row, col] / wp.max(pdf, 1.0e-12), state


@wp.func
def environment_radiance(env: EnvironmentLight, d: wp.vec3) -> wp.vec3:
    """Radiance arriving from unit direction ``d`` (towards the environment): the map's pixel holding ``d``."""
    if env.mode == ENV_NONE:
        return wp.vec3(0.0)
    if env.mode == ENV_CONSTANT:
        return env.radiance
    h = env.image.shape[0]
    w = env.image.shape[1]
    phi = wp.atan2(d[2], d[0])
    if phi < 0.0:
        phi += 2.0 * wp.pi
    row = wp.min(int(wp.acos(wp.clamp(d[1], -1.0, 1.0)) / wp.pi * float(h)), h - 1)
    col = wp.min(int(phi / (2.0 * wp.pi) * float(w)), w - 1)
    return env.image[row, col]

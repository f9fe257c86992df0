"""Sci-vis modes of the light-map march (DSSRM, CMSRM's texel rays, CACRM): per-sample functions that the one march
loop (`volren.render.marching.march.mode_step`) selects by ``MarchParams.mode``; no kernel is copied per mode.

A ray's state is the march's ``acc = (r, g, b, T)`` (premultiplied colour, transmittance), so every mode composites,
resolves and writes pixels through the code DVR uses:

- ``dvr``: today's volume rendering (single scattering from the light map, emission, front to back).
- ``mip``: maximum intensity projection. The intensity of a sample is P = min(rho / rho_max, 1), rho_max the scene's
  largest density (the normalisation of `volren.transfer`'s u). The state is the running maximum resolved as a grey
  pixel with coverage P: acc = (P, P, P, 1 - P), i.e. a grey level P over the background (exactly P on black). In cube
  space: the max is order independent, so a texel ray stores the max over its segment (its resolved acc) and the
  resample pass combines a pixel's segments by max instead of "over" (`combine_segment`): the pixel's max is the max
  over the texel segments it crosses, and bilinear interpolation of texel maxima blurs as DVR's texel interpolation
  does. Empty-space skipping leaves out every skip cell whose conservative max P does not exceed the running max.
  The depth buffer holds, as in DVR, where T fell to 1/2: where the running max first passed P = 1/2.
- ``mida``: maximum intensity difference accumulation (Bruckner and Groeller 2009, Eq. 5-6 with gamma = 0):
  delta_i = max(P_i - P_max,i-1, 0), beta_i = 1 - delta_i, C_i = beta_i C_i-1 + (1 - beta_i A_i-1) alpha_i c_i,
  A_i = beta_i A_i-1 + (1 - beta_i A_i-1) alpha_i, with DVR's lit sample as alpha_i c_i (the paper's transfer
  function and shading). In volren's form: scale the accumulated colour and opacity by beta_i (`mida_weight`), then
  composite the sample as DVR does. The running max starts at 0 where a box's march starts, in every method: in cube
  space a texel ray is the whole chord of its box, so one box per ray is the paper's recurrence exactly, and several
  boxes along a ray composite by "over" box after box (the max does not cross box boundaries, as a texel cannot know
  the max in front of its box).
- ``iso``: the first crossing of density V (``iso_value``, in the grid's density units) along the ray, refined by
  ``ISO_BISECTIONS`` bisection steps between the last step below V and the first at or above it, shaded by Lambert
  with the scene's lights (unshadowed) and the ambient, gradient normal by central differences; opaque (T = 0 ends
  the ray). Skipping leaves out cells whose conservative max is below V. Cube space: a texel holds its ray's shaded
  hit, resampled like DVR's texels (opaque, so "over" is the first hit).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import warp as wp

from volren.errors import VolrenError
from volren.kernels.common import (
    Medium,
    VolumeGPU,
    light_irradiance,
    light_travel_dir,
    sample_density,
)

MODES = ("dvr", "mip", "mida", "iso")
MODE_DVR = wp.constant(0)
MODE_MIP = wp.constant(1)
MODE_MIDA = wp.constant(2)
MODE_ISO = wp.constant(3)
ISO_BISECTIONS = wp.constant(8)
"""bisection steps of an iso crossing: the hit lies within 1/256 of a step of the true crossing"""
ISO_FETCHES = 8 + 6
"""density fetches of one iso hit: the bisection steps and the six central differences of its normal"""
OTSU_VOXELS = 1 << 21
"""about this many voxels make the histogram of `otsu_iso_value` (a 512^3 grid is read every 4th voxel per axis)"""
MIN_ISO_VALUE = 1e-6
"""the smallest V `otsu_iso_value` gives (V must be > 0)"""


def mode_index(mode: str) -> int:
    """``MarchParams.mode`` of a mode name."""
    return MODES.index(mode)


def check_mode(mode: str, iso_value: float) -> None:
    """One-line refusals of a config's mode and iso value."""
    if mode not in MODES:
        raise VolrenError(f"mode must be one of {', '.join(MODES)}, got '{mode}'")
    if isinstance(iso_value, bool) or not isinstance(iso_value, int | float) or not (
            math.isfinite(iso_value) and iso_value > 0):
        raise VolrenError(f"iso_value (--iso-value) must be a finite density > 0, got {iso_value}")


def iso_range_message(iso_value: float, lo: float, hi: float) -> str | None:
    """What is wrong with an iso value V outside the scene's densities [lo, hi], in one line; None inside. Above hi
    no ray crosses V (an empty image); at or below lo every sample is at or above V (the surface is the box)."""
    if iso_value > hi:
        return (f"iso_value (--iso-value) {iso_value:g} is above the densities {lo:.4g} to {hi:.4g}: the isosurface "
                "is empty")
    if iso_value <= lo:
        return (f"iso_value (--iso-value) {iso_value:g} is at or below the densities {lo:.4g} to {hi:.4g}: the "
                "isosurface is the volume's box")
    return None


def otsu_iso_value(densities: Sequence[np.ndarray]) -> float:
    """A data-driven V for mode iso: Otsu's threshold (the split of the density histogram, 256 bins, that maximises
    the variance between the two classes; `skimage.filters.threshold_otsu`) of the grids' voxels together, each read
    at a stride that keeps about `OTSU_VOXELS` of them. CT: between air and tissue; smoke: the edge of the occupied
    voxels. A grid with one value gives that value (at least `MIN_ISO_VALUE`)."""
    from skimage.filters import threshold_otsu  # lazy: scipy's ndimage comes with it (0.4 s)

    total = sum(d.size for d in densities)
    stride = max(1, math.ceil((total / OTSU_VOXELS) ** (1 / 3)))
    values = np.concatenate([np.ravel(d[::stride, ::stride, ::stride]) for d in densities])
    lo, hi = float(values.min()), float(values.max())
    value = float(threshold_otsu(values)) if hi > lo else hi
    return max(value, MIN_ISO_VALUE)


@wp.func
def intensity(rho: float, inv_max: float) -> float:
    """P: the density normalised by the scene's largest (inv_max = 1 / rho_max), at most 1."""
    return wp.min(rho * inv_max, 1.0)


@wp.func
def skippable(mode: int, value: float, acc: wp.vec4, inv_max: float, iso_value: float) -> bool:
    """Whether a skip cell of conservative max ``value`` (<= 0: an empty cube, `volren.upload.skip_grid`) can change
    nothing: empty (DVR, MIDA: every sample composites), below V (iso), or not above the running max acc[0] (MIP)."""
    if mode == MODE_ISO:
        return value < iso_value
    if mode == MODE_MIP:
        return value * inv_max <= acc[0]
    return value <= 0.0


@wp.func
def mip_step(acc: wp.vec4, rho: float, inv_max: float) -> wp.vec4:
    """The running max as a grey pixel with coverage P: (P, P, P, 1 - P)."""
    p = intensity(rho, inv_max)
    if p > acc[0]:
        return wp.vec4(p, p, p, 1.0 - p)
    return acc


@wp.func
def mida_weight(acc: wp.vec4, peak: float, p: float) -> wp.vec4:
    """MIDA's beta_i = 1 - max(P_i - P_max, 0) applied to the accumulated colour and opacity A = 1 - T (Bruckner and
    Groeller 2009, Eq. 5-6, gamma = 0), before the sample composites as in DVR."""
    beta = 1.0 - wp.max(p - peak, 0.0)
    return wp.vec4(beta * acc[0], beta * acc[1], beta * acc[2], 1.0 - beta * (1.0 - acc[3]))


@wp.func
def combine_segment(mode: int, acc: wp.vec4, c: wp.vec4) -> wp.vec4:
    """A pixel's state after the (resolved) cube texel segment ``c`` behind it: max for MIP (order independent),
    front-to-back "over" otherwise."""
    if mode == MODE_MIP:
        if c[0] > acc[0]:
            return c
        return acc
    return wp.vec4(acc[0] + acc[3] * c[0], acc[1] + acc[3] * c[1], acc[2] + acc[3] * c[2], acc[3] * c[3])


@wp.func
def iso_crossing(density: wp.array(dtype=float), vol: VolumeGPU, o_l: wp.vec3, d_l: wp.vec3, lo: float, hi: float,
                 iso_value: float) -> float:
    """Ray distance of the crossing of V in [lo, hi] (density < V at lo, >= V at hi) by bisection."""
    a = lo
    b = hi
    for _k in range(ISO_BISECTIONS):
        m = 0.5 * (a + b)
        if sample_density(density, vol, o_l + m * d_l) >= iso_value:
            b = m
        else:
            a = m
    return 0.5 * (a + b)


@wp.func
def iso_normal(density: wp.array(dtype=float), vol: VolumeGPU, p: wp.vec3) -> wp.vec3:
    """Unit world normal at local p: minus the density gradient (central differences one voxel apart, each over its
    own axis's spacing 2 / n: a grid of 32 x 20 x 12 voxels put normals 9% off in median before issue 47), which
    points out of the surface towards lower density; world gradient = (M^-1)^T grad_local."""
    g = wp.vec3(0.0)
    for a in range(3):
        h = wp.vec3(0.0)
        h[a] = 1.0 / float(vol.res[a])
        g[a] = (sample_density(density, vol, p + h)
                - sample_density(density, vol, p - h)) * float(vol.res[a])
    g_w = wp.transform_vector(wp.transpose(vol.to_local), g)
    return -wp.normalize(g_w)


@wp.func
def iso_shade(vol: VolumeGPU, medium: Medium, n: wp.vec3, x: wp.vec3, ambient: wp.vec3) -> wp.vec3:
    """Lambert radiance of the surface at world x: albedo (ambient + sum_l E_l max(n . -l, 0) / pi), lights
    unshadowed."""
    radiance = ambient
    for li in range(medium.lights.shape[0]):
        light = medium.lights[li]
        cos_l = wp.max(wp.dot(n, -light_travel_dir(light, x)), 0.0)
        radiance += light_irradiance(light, x) * (cos_l / wp.pi)
    return wp.cw_mul(vol.albedo, radiance)

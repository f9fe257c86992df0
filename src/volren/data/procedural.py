"""Built-in procedural scenes: smoke plume, cumulus cloud, 3D Shepp-Logan phantom, and a grid of puffs.

Every field is deterministic: randomness comes from ``np.random.default_rng([seed, stream])`` (never the global
state), and the noise lattices are drawn coarse octave first, so the same seed gives the same large-scale shape at
every resolution. Grids are float32 ``[z, y, x]`` in [0, 1]; voxel i of n sits at local ``-1 + (i + 0.5) * 2 / n``
(DESIGN.md). Fields are built in z-slabs so that 512^3 needs about the output array plus a few hundred MiB.

Materials are calibrated on the fields built here (seeds 0-2, resolution 64, rays along z as the default camera
looks): the optical depth ``density_scale * integral(density)`` of the densest columns is about 3-5 for smoke,
cloud and puffs, so images are neither blown out nor invisible, and about 1 through the phantom, so its inside
shows (`PHANTOM_DENSITY_SCALE`).
"""

from __future__ import annotations

import dataclasses
import functools
import operator
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from volren.errors import VolrenError
from volren.scene import DirectionalLight, Environment, Plane, Scene, Volume, scale_translate

MIN_RESOLUTION = 64
MAX_RESOLUTION = 512
MULTI_COUNTS = (4, 16, 36)

_SLAB_VOXELS = 1 << 23
"""Voxels per z-slab: bounds every full-size temporary to 32 MiB of float32 whatever the resolution."""
_MARGIN_INNER, _MARGIN_OUTER = 0.88, 0.95
"""Noise fields fade to exactly 0 between these |local| coordinates, so a box face never cuts the medium."""

CLASSIC_LIGHTS = (DirectionalLight(direction=(-0.5, -1.0, -0.35), irradiance=(3.0, 3.0, 3.0)),)
_SKY = Environment(radiance=(0.05, 0.065, 0.09))
"""the instances' sky, and the smoke's, phantom's and puffs' before their key light (`classic_look`)"""
_BACKGROUND = (0.015, 0.015, 0.02)
KEY_LIGHT = DirectionalLight(direction=(0.8, -0.5, 0.1), irradiance=(8.0, 8.0, 8.0))
"""The smoke's, the phantom's and the puffs' key light (issue 45.6): from the upper left and a little behind, as the
papers' figures light a volume, so its shape reads as a gradient from the lit left to the shaded right. The light
they had before (3 from behind the camera, where g > 0 scatters least back) left each a flat grey shape."""
KEY_SKY = Environment(radiance=(0.1, 0.12, 0.16))
"""the key light's cool sky: it fills the shaded side (twice the old sky's 0.05-0.09)"""
PHANTOM_DENSITY_SCALE = 2.0
"""[1/m] the phantom's extinction per unit density (issue 45.6): the brain (0.2) has optical depth about 0.6 across
the head, so the ventricles (0) show as dark lobes and the skull (1) as a rim; at the 6 it had, every pixel of the
head was about as opaque as the next (alpha 0.79 on average, a grey ellipse)"""


def _check_resolution(resolution: int) -> int:
    try:
        if isinstance(resolution, bool):
            raise TypeError
        n = operator.index(resolution)
    except TypeError:
        raise VolrenError(f"resolution must be an integer, got {resolution!r}") from None
    if not MIN_RESOLUTION <= n <= MAX_RESOLUTION:
        raise VolrenError(f"resolution must lie in {MIN_RESOLUTION}..{MAX_RESOLUTION} voxels per axis, got {n}")
    return n


def _check_seed(seed: int) -> int:
    try:
        if isinstance(seed, bool):
            raise TypeError
        s = operator.index(seed)
    except TypeError:
        raise VolrenError(f"seed must be an integer, got {seed!r}") from None
    if s < 0:
        raise VolrenError(f"seed must be >= 0, got {s}")
    return s


def _centres(n: int) -> np.ndarray:
    """Local coordinates of the n voxel centres along one axis (DESIGN.md)."""
    return (-1.0 + (np.arange(n) + 0.5) * (2.0 / n)).astype(np.float32)


def _slabs(n: int) -> Iterator[slice]:
    step = max(1, _SLAB_VOXELS // (n * n))
    for z0 in range(0, n, step):
        yield slice(z0, min(n, z0 + step))


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at ``edge0`` to 1 at ``edge1`` (either order); a new float32 array."""
    t = np.subtract(x, np.float32(edge0), dtype=np.float32)
    t *= np.float32(1.0 / (edge1 - edge0))
    np.clip(t, 0.0, 1.0, out=t)
    return t * t * (np.float32(3.0) - np.float32(2.0) * t)


def _margin(n: int) -> np.ndarray:
    """1D window: 1 inside |u| <= 0.88, smoothly 0 from |u| >= 0.95; the product over axes keeps box faces clear."""
    return _smoothstep(_MARGIN_OUTER, _MARGIN_INNER, np.abs(_centres(n)))


class _Fbm:
    """Fractal sum of value noise on seeded random lattices, in [-1, 1], sampled at the voxel centres.

    Value noise with a quintic fade is separable, so each octave interpolates its small lattice along x and y once
    (arrays of lattice_z x n x n) and only the z-interpolation touches full-size slabs: two gathers and a multiply-add
    per octave, instead of 8 hashed corners per voxel for gradient noise. Each octave gets a random sub-cell offset
    so lattice planes of different octaves do not line up.
    """

    def __init__(
        self,
        rng: np.random.Generator,
        n: int,
        base_freq: float,
        gain: float = 0.5,
        stretch: tuple[float, float, float] = (1, 1, 1),
    ) -> None:
        # Finest wavelength about 4 voxels: more octaves would only alias.
        octaves = max(1, int(np.floor(np.log2(n / (4.0 * base_freq)))) + 1)
        u = (np.arange(n) + 0.5) / n
        self._octaves: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]] = []
        amp, total = 1.0, 0.0
        for k in range(octaves):
            freq = base_freq * 2.0**k * np.asarray(stretch, dtype=np.float64)  # (x, y, z) cells across the box
            offset = rng.random(3)
            size = np.floor(freq + offset).astype(int) + 2
            lattice = rng.random((size[2], size[1], size[0]), dtype=np.float32) * 2.0 - 1.0
            (ix, wx), (iy, wy), (iz, wz) = (self._axis(u * freq[a] + offset[a]) for a in range(3))
            a_xy = lattice[:, :, ix] + (lattice[:, :, ix + 1] - lattice[:, :, ix]) * wx
            b = a_xy[:, iy, :] + (a_xy[:, iy + 1, :] - a_xy[:, iy, :]) * wy[:, None]
            self._octaves.append((b[:-1], b[1:] - b[:-1], iz, wz, amp))
            total += amp
            amp *= gain
        self._norm = 1.0 / total

    @staticmethod
    def _axis(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        i = np.floor(p).astype(np.intp)
        t = (p - i).astype(np.float32)
        return i, t * t * t * (t * (t * 6 - 15) + 10)

    def slab(self, zs: slice) -> np.ndarray:
        out: np.ndarray | None = None
        for base, diff, iz, wz, amp in self._octaves:
            idx = iz[zs]
            term = diff[idx]
            term *= (wz[zs] * np.float32(amp))[:, None, None]
            term += np.float32(amp) * base[idx]
            if out is None:
                out = term
            else:
                out += term
        assert out is not None
        out *= np.float32(self._norm)
        return out


def smoke_density(resolution: int = 64, seed: int = 0) -> np.ndarray:
    """A rising plume: a column that widens and thins with height, wandering sideways, with fBm-turbulent edges.

    The plume stays well inside the box: it rises from y = -0.75 and dissipates under a rounded, noise-torn cap
    (lower at the plume's edge than on its axis) that ends by y = 0.75, so no box face cuts it flat.
    """
    return _smoke_field(_check_resolution(resolution), np.random.default_rng([_check_seed(seed), 1]))


def _smoke_field(n: int, rng: np.random.Generator) -> np.ndarray:
    """:func:`smoke_density` at any size ``n`` (instances of the ``instances`` scenes are n/2 per axis)."""
    phases = rng.random(4) * 2 * np.pi
    noise = _Fbm(rng, n, base_freq=2.5, gain=0.6, stretch=(1.0, 0.6, 1.0))  # stretched along y: wisps rise
    c = _centres(n)
    y_base, y_top = -0.75, 0.75
    t = np.clip((c - y_base) / (y_top - y_base), 0.0, 1.0)  # height along the plume, per y row
    radius = (0.1 + 0.42 * t**1.2).astype(np.float32)
    sway = 0.12 * t**1.5  # the column drifts more the higher it rises
    cx = (sway * np.sin(2.6 * np.pi * t + phases[0]) + 0.04 * np.sin(5.3 * np.pi * t + phases[1])).astype(np.float32)
    cz = (sway * np.sin(2.2 * np.pi * t + phases[2]) + 0.04 * np.sin(4.7 * np.pi * t + phases[3])).astype(np.float32)
    # fades in above the source and dilutes as the plume spreads (the top is the cap below)
    profile = _smoothstep(y_base - 0.05, y_base + 0.12, c) * (1.0 - 0.45 * t)
    row = (profile * _margin(n)).astype(np.float32)[:, None]  # (y, x) factor
    win_x = _margin(n)

    out = np.empty((n, n, n), dtype=np.float32)
    for zs in _slabs(n):
        dz = c[zs, None, None] - cz[None, :, None]
        dx = c[None, None, :] - cx[None, :, None]
        q = np.sqrt(dz * dz + dx * dx) / radius[None, :, None]
        f = noise.slab(zs)
        q -= 0.45 * f  # turbulent edge: the noise moves the plume's surface in and out
        d = _smoothstep(1.0, 0.3, q)
        d *= np.clip(0.7 + 0.8 * f, 0.0, 1.0)  # internal eddies
        # dissipating cap: ends at y_top on the axis, 0.4 lower at the edge, torn up and down by the noise
        cap = np.float32(y_top) - np.float32(0.4) * np.minimum(q, np.float32(1.0)) ** 2 + np.float32(0.2) * f
        d *= _smoothstep(0.0, 0.45, cap - c[None, :, None])
        d *= row * win_x
        d *= _margin(n)[zs, None, None]
        out[zs] = d
    np.clip(out, 0.0, 1.0, out=out)
    return out


def fire_fields(resolution: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A flame: (soot density, temperature), both [z, y, x] in [0, 1].

    The temperature is a hot core over a burner at y = -0.8 that narrows, cools and flickers (fBm) as it rises into
    a tongue ending near y = 0.2; the soot is thin in the flame (0.12-0.2: it glows through it) and thickens into a
    smoke column above it, to y = 0.8. The soot covers the flame everywhere, as blackbody emission needs
    density > 0 (`volren.scene`, "Fire")."""
    n = _check_resolution(resolution)
    rng = np.random.default_rng([_check_seed(seed), 5])
    noise = _Fbm(rng, n, base_freq=3.0, gain=0.6, stretch=(1.0, 0.5, 1.0))  # stretched along y: tongues rise
    c = _centres(n)
    y_base = -0.8
    t = np.clip((c - y_base) / 1.6, 0.0, 1.0)  # height along the column, per y row
    radius = (0.36 + 0.2 * t).astype(np.float32)
    flame_len = np.float32(1.3)  # the tongue's height above the burner
    win = _margin(n)
    base = _smoothstep(y_base - 0.05, y_base + 0.08, c) * win  # (y,) the burner and the box margin
    density = np.empty((n, n, n), dtype=np.float32)
    temperature = np.empty((n, n, n), dtype=np.float32)
    h = np.clip((c - y_base) / flame_len, 0.0, 1.0).astype(np.float32)[None, :, None]  # height in the tongue
    for zs in _slabs(n):
        f = noise.slab(zs)
        q = np.sqrt(c[zs, None, None] ** 2 + c[None, None, :] ** 2) / radius[None, :, None] - 0.35 * f
        envelope = _smoothstep(1.0, 0.4, q)
        # hot core: widest at the burner, a tongue whose edge (q at 1 - h) closes in as it rises; flicker by f
        edge = 1.0 - 0.75 * h  # the tongue narrows as it rises
        core = _smoothstep(edge, 0.4 * edge, q - 0.3 * f) * (1.0 - h) ** 0.3 * np.clip(0.8 + 0.6 * f, 0.0, 1.0)
        smoke = _smoothstep(0.2, 0.7, c)[None, :, None] * _smoothstep(0.95, 0.7, c)[None, :, None]
        soot = envelope * (0.12 + 0.08 * (1.0 - core) + 0.3 * smoke * np.clip(0.7 + 0.8 * f, 0.0, 1.0))
        window = base[None, :, None] * win[None, None, :] * win[zs, None, None]
        density[zs] = soot * window
        temperature[zs] = core * envelope * window
    np.clip(density, 0.0, 1.0, out=density)
    np.clip(temperature, 0.0, 1.0, out=temperature)
    return density, temperature


def _spheres_field(spheres: np.ndarray, c: np.ndarray, zs: slice) -> np.ndarray:
    """max_i (1 - |p - c_i| / r_i) on a z-slab: 1 at a centre, 0 on a surface, -1 far out (clamped there).

    Each sphere is evaluated only on the voxels of its bounding box, which keeps the union cheap.
    """
    n = c.size
    field = np.full((zs.stop - zs.start, n, n), -1.0, dtype=np.float32)
    for x0, y0, z0, r in spheres:
        lo = np.searchsorted(c, np.array([x0, y0, z0]) - 2 * r)
        hi = np.searchsorted(c, np.array([x0, y0, z0]) + 2 * r)
        z_lo, z_hi = max(lo[2], zs.start), min(hi[2], zs.stop)
        if z_lo >= z_hi:
            continue
        dz = (c[z_lo:z_hi] - z0)[:, None, None]
        dy = (c[lo[1] : hi[1]] - y0)[None, :, None]
        dx = (c[lo[0] : hi[0]] - x0)[None, None, :]
        s = 1.0 - np.sqrt(dz * dz + dy * dy + dx * dx) / np.float32(r)
        view = field[z_lo - zs.start : z_hi - zs.start, lo[1] : hi[1], lo[0] : hi[0]]
        np.maximum(view, s, out=view)
    return field


def _billow(n: int, spheres: np.ndarray, noise: _Fbm, floor: float | None) -> np.ndarray:
    """Soft-sphere union eroded by fBm, denser towards the core; cut flat at ``y = floor`` when given."""
    c = _centres(n)
    win = _margin(n)
    row = win if floor is None else win * _smoothstep(floor, floor + 0.08, c)
    out = np.empty((n, n, n), dtype=np.float32)
    for zs in _slabs(n):
        s = _spheres_field(spheres, c, zs)
        f = noise.slab(zs)
        e = s - 0.6 * (0.5 + 0.5 * f)  # erosion only removes: the medium stays inside the spheres
        d = _smoothstep(0.0, 0.15, e)
        d *= 0.45 + 0.55 * _smoothstep(0.1, 0.7, s)  # denser core
        d *= row[None, :, None] * win[None, None, :] * win[zs, None, None]
        out[zs] = d
    np.clip(out, 0.0, 1.0, out=out)
    return out


def cloud_density(resolution: int = 64, seed: int = 0) -> np.ndarray:
    """A cumulus: a row of broad billows at the base, smaller ones stacked on top, a flat base, fBm-eroded edges."""
    return _cloud_field(_check_resolution(resolution), np.random.default_rng([_check_seed(seed), 2]))


def _cloud_field(n: int, rng: np.random.Generator) -> np.ndarray:
    """:func:`cloud_density` at any size ``n``."""
    # (count, x range or row, y range, z half-range, radius range) per tier: base row, middle, towers
    base_x = np.linspace(-0.5, 0.5, 5) + rng.uniform(-0.05, 0.05, 5)
    tiers = [
        (base_x, rng.uniform(-0.16, -0.08, 5), rng.uniform(-0.15, 0.15, 5), rng.uniform(0.26, 0.32, 5)),
        (rng.uniform(-0.3, 0.3, 4), rng.uniform(0.05, 0.2, 4), rng.uniform(-0.15, 0.15, 4), rng.uniform(0.22, 0.3, 4)),
        (rng.uniform(-0.15, 0.15, 2), rng.uniform(0.3, 0.4, 2), rng.uniform(-0.1, 0.1, 2), rng.uniform(0.16, 0.22, 2)),
    ]
    spheres = np.concatenate([np.stack(t, axis=1) for t in tiers])
    return _billow(n, spheres, _Fbm(rng, n, base_freq=8.0, gain=0.6), floor=-0.35)


def _puff_density(n: int, seed: int, index: int) -> np.ndarray:
    """A small round cloud puff (a few soft spheres, no flat base): instance ``index`` of the ``multi`` scene."""
    rng = np.random.default_rng([seed, 3, index])
    k = 5
    centres = rng.uniform(-0.25, 0.25, (k, 3))
    r = rng.uniform(0.25, 0.4, (k, 1))
    spheres = np.concatenate([[[0.0, 0.0, 0.0, 0.45]], np.concatenate([centres, r], axis=1)])
    return _billow(n, spheres, _Fbm(rng, n, base_freq=6.0, gain=0.6), floor=None)


# 3D modified Shepp-Logan (Toft's intensities, Schabel's phantom3d ellipsoids after Kak & Slaney):
# A (additive intensity), half-axes a, b, c, centre x0, y0, z0, Euler angles phi, theta, psi in degrees (zxz).
SHEPP_LOGAN_3D = np.array(
    [
        [1.0, 0.6900, 0.920, 0.810, 0.00, 0.0000, 0.00, 0.0, 0.0, 0.0],
        [-0.8, 0.6624, 0.874, 0.780, 0.00, -0.0184, 0.00, 0.0, 0.0, 0.0],
        [-0.2, 0.1100, 0.310, 0.220, 0.22, 0.0000, 0.00, -18.0, 0.0, 10.0],
        [-0.2, 0.1600, 0.410, 0.280, -0.22, 0.0000, 0.00, 18.0, 0.0, 10.0],
        [0.1, 0.2100, 0.250, 0.410, 0.00, 0.3500, -0.15, 0.0, 0.0, 0.0],
        [0.1, 0.0460, 0.046, 0.050, 0.00, 0.1000, 0.25, 0.0, 0.0, 0.0],
        [0.1, 0.0460, 0.046, 0.050, 0.00, -0.1000, 0.25, 0.0, 0.0, 0.0],
        [0.1, 0.0460, 0.023, 0.050, -0.08, -0.6050, 0.00, 0.0, 0.0, 0.0],
        [0.1, 0.0230, 0.023, 0.020, 0.00, -0.6060, 0.00, 0.0, 0.0, 0.0],
        [0.1, 0.0230, 0.046, 0.020, 0.06, -0.6050, 0.00, 0.0, 0.0, 0.0],
    ]
)


def _euler_zxz(phi: float, theta: float, psi: float) -> np.ndarray:
    """Schabel's phantom3d rotation (x-convention): maps world offsets into the ellipsoid's axes frame."""
    cf, sf = np.cos(np.radians(phi)), np.sin(np.radians(phi))
    ct, st = np.cos(np.radians(theta)), np.sin(np.radians(theta))
    cp, sp = np.cos(np.radians(psi)), np.sin(np.radians(psi))
    return np.array(
        [
            [cp * cf - ct * sf * sp, cp * sf + ct * cf * sp, sp * st],
            [-sp * cf - ct * sf * cp, -sp * sf + ct * cf * cp, cp * st],
            [st * sf, -st * cf, ct],
        ]
    )


_PHANTOM_EDGE_VOXELS = 1.5
"""Width of the skull's edges in voxels: its ellipsoids add their intensity times the share of a ramp this wide
across their surface that lies inside (a partial-volume edge, as a CT scanner's point spread gives), so gradients and
a path tracer's surfaces are smooth instead of voxel staircases with pinholes through the one-voxel skull."""


def phantom_density(resolution: int = 64, edge_voxels: float = _PHANTOM_EDGE_VOXELS) -> np.ndarray:
    """The 3D modified Shepp-Logan head as a CT-like field in [0, 1]: skull 1, brain 0.2, ventricles 0. The skull's
    two surfaces are ramps ``edge_voxels`` wide (partial volume; 0: hard edges); the inner ellipsoids keep hard edges,
    so the table's values hold right up to them.

    The phantom's y is our up axis, so the small ellipsoids (y = -0.6) sit at the bottom as in the 2D figure, and
    slices z = const are the familiar axial images. Departure from phantom3d.m: each ellipsoid is rotated about its
    own centre (q = R (p - c)) rather than about the origin, so the table's centres are where the ellipsoids are.
    """
    n = _check_resolution(resolution)
    c = _centres(n).astype(np.float64)
    ramp_skull = max(edge_voxels, 1e-6) * 2.0 / n  # local width of the skull's edge ramps
    out = np.zeros((n, n, n), dtype=np.float32)
    for index, (amp, a, b, cc, x0, y0, z0, phi, theta, psi) in enumerate(SHEPP_LOGAN_3D):
        ramp = ramp_skull if index < 2 else 1e-6 * 2.0 / n  # the skull: ellipsoids 0 and 1
        rot = _euler_zxz(phi, theta, psi) / np.array([a, b, cc])[:, None]  # rows scaled: q_i / half-axis_i
        reach = max(a, b, cc) + ramp
        lo = np.searchsorted(c, np.array([x0, y0, z0]) - reach)
        hi = np.searchsorted(c, np.array([x0, y0, z0]) + reach)
        dx = (c[lo[0] : hi[0]] - x0)[None, None, :]
        dy = (c[lo[1] : hi[1]] - y0)[None, :, None]
        for zs in _slabs(n):
            z_lo, z_hi = max(lo[2], zs.start), min(hi[2], zs.stop)
            if z_lo >= z_hi:
                continue
            dz = (c[z_lo:z_hi] - z0)[:, None, None]
            q = [rot[i, 0] * dx + rot[i, 1] * dy + rot[i, 2] * dz for i in range(3)]
            r = np.sqrt(sum(qi * qi for qi in q)) + 1e-12
            # distance to the surface to first order, (r - 1) / |grad r| with grad r = rot^T q / r
            grad = np.sqrt(sum(sum(q[i] * rot[i, k] for i in range(3)) ** 2 for k in range(3))) / r
            cover = np.clip(0.5 - (r - 1.0) / (grad * ramp + 1e-12), 0.0, 1.0)
            view = out[z_lo:z_hi, lo[1] : hi[1], lo[0] : hi[0]]
            view += (amp * cover).astype(np.float32)
    np.clip(out, 0.0, 1.0, out=out)
    return out


def _smoke_scene(resolution: int, *, count: int = 4, seed: int = 0) -> Scene:
    volume = Volume(smoke_density(resolution, seed), density_scale=13.0, albedo=(0.85, 0.85, 0.85), g=0.2, name="smoke")
    return Scene((volume,), (KEY_LIGHT,), KEY_SKY, _BACKGROUND, name="smoke")


CLASSIC_PHANTOM_DENSITY_SCALE = 6.0
"""[1/m] the phantom's density scale before `PHANTOM_DENSITY_SCALE` (`classic_look`)"""


def classic_look(scene: Scene) -> Scene:
    """A built-in scene with the light, sky and phantom opacity that the smoke, smoke-floor, phantom and multi scenes
    had before their key light (`KEY_LIGHT`, `KEY_SKY`, `PHANTOM_DENSITY_SCALE`): the benchmark suites render these,
    so that their figures stay comparable with those recorded. Other scenes (their own light) are returned as
    they are."""
    if scene.lights != (KEY_LIGHT,) or scene.environment is not KEY_SKY:  # Environment compares by identity
        return scene
    volumes = tuple(dataclasses.replace(v, density_scale=CLASSIC_PHANTOM_DENSITY_SCALE)
                    if v.name == "phantom" and v.density_scale == PHANTOM_DENSITY_SCALE else v for v in scene.volumes)
    return dataclasses.replace(scene, volumes=volumes, lights=CLASSIC_LIGHTS, environment=_SKY)


def _smoke_floor_scene(resolution: int, *, count: int = 4, seed: int = 0) -> Scene:
    """The smoke over a grey floor at its box's base: the plume's shadow and ambient occlusion on the floor. Its own
    light is the smoke's old one from above the camera's right: the key light's low angle (`KEY_LIGHT`) throws the
    shadow 2.8 m to the right, out of the picture, and lights the floor white."""
    scene = _smoke_scene(resolution, seed=seed)
    return dataclasses.replace(scene, name="smoke-floor", opaque=(Plane((0.0, -1.0, 0.0), (0.0, 1.0, 0.0), 0.35),),
                               lights=CLASSIC_LIGHTS, environment=_SKY)


FIRE_TEMPERATURES = (1200.0, 2500.0)
"""[K] the fire scene's temperature range: deep red at the tongue's tips to yellow-white in the core"""


def _fire_scene(resolution: int, *, count: int = 4, seed: int = 0) -> Scene:
    """`fire_fields` as dark soot (albedo 0.5) with blackbody emission, under a dim light so that the flame reads."""
    soot, temperature = fire_fields(resolution, seed)
    volume = Volume(soot, density_scale=8.0, albedo=(0.5, 0.5, 0.5), g=0.3, name="fire", emission_grid=temperature,
                    temperature_range=FIRE_TEMPERATURES, emission_scale=10.0)
    light = DirectionalLight(direction=(-0.5, -1.0, -0.35), irradiance=(0.3, 0.3, 0.3))
    return Scene((volume,), (light,), Environment(radiance=(0.01, 0.012, 0.016)), _BACKGROUND, name="fire")


CLOUD_SUN = DirectionalLight(direction=(0.6, -1.0, 0.3), irradiance=(12.0, 12.0, 12.0))
"""A high sun from the upper left, a little behind: tops lit, base shaded. With the shared light (3 from the camera's
side, where g = 0.5 scatters least back) the cloud showed as dull grey (issue 22.10)"""
CLOUD_SKY = Environment(radiance=(0.2, 0.225, 0.25))
"""A daylight sky's ambient, standing in for the multiple scattering that makes a real cloud white (the marchers
scatter once)"""


def _cloud_scene(resolution: int, *, count: int = 4, seed: int = 0) -> Scene:
    volume = Volume(cloud_density(resolution, seed), density_scale=11.0, albedo=(0.97, 0.97, 0.97), g=0.5, name="cloud")
    return Scene((volume,), (CLOUD_SUN,), CLOUD_SKY, _BACKGROUND, name="cloud")


def _phantom_scene(resolution: int, *, count: int = 4, seed: int = 0) -> Scene:
    volume = Volume(phantom_density(resolution), density_scale=PHANTOM_DENSITY_SCALE, albedo=(0.8, 0.8, 0.8), g=0.0,
                    name="phantom")
    return Scene((volume,), (KEY_LIGHT,), KEY_SKY, _BACKGROUND, name="phantom")


def multi_layout(count: int) -> list[np.ndarray]:
    """``to_world`` matrices of a k x k grid (k = sqrt(count)) of cubes in the x-y plane, facing the default camera.

    The grid spans [-1.1, 1.1] in x and y; each cube's half-extent is 0.4 of the cell pitch, so neighbours are
    separated by a gap of 0.2 pitch and every box lies inside [-1.2, 1.2]^3.
    """
    if isinstance(count, bool) or count not in MULTI_COUNTS:
        raise VolrenError(f"multi scene count must be one of {', '.join(map(str, MULTI_COUNTS))}, got {count!r}")
    k = round(np.sqrt(count))
    pitch = 2.2 / k
    centres = -1.1 + (np.arange(k) + 0.5) * pitch
    return [scale_translate(0.4 * pitch, (x, y, 0.0)) for y in centres[::-1] for x in centres]


def _multi_scene(resolution: int, *, count: int = 4, seed: int = 0) -> Scene:
    """Instances are puffs at resolution n // 2 each, so the work grows with ``count`` alone (bench scaling)."""
    n = _check_resolution(resolution)
    seed = _check_seed(seed)
    layout = multi_layout(count)
    volumes = []
    for i, to_world in enumerate(layout):
        half = to_world[0, 0]
        volumes.append(
            Volume(
                _puff_density(n // 2, seed, i),
                to_world=to_world,
                density_scale=6.0 / half,  # same optical depth across every box whatever its size
                albedo=(0.95, 0.95, 0.95),
                g=0.5,
                name=f"puff{i}",
            )
        )
    return Scene(tuple(volumes), (KEY_LIGHT,), KEY_SKY, _BACKGROUND, name=f"multi{count}")


INSTANCE_FILL = {False: 0.4, True: 0.6}
"""Box half-extent over the grid pitch of the ``instances`` scenes: disjoint (gaps of 0.2 pitch) or overlapping
(neighbours share 0.2 pitch along x and along z)"""
_OVERHEAD_LIGHT = (DirectionalLight(direction=(0.0, -1.0, 0.0), irradiance=(3.0, 3.0, 3.0)),)
"""Straight down: the light map shades each volume alone (unless GI is on) while the reference shadows across
volumes, and in a one-layer grid no box lies above another, so the disjoint scene's images differ from the
reference by order and sampling only"""


def instances_layout(count: int, overlap: bool = False) -> list[np.ndarray]:
    """``to_world`` matrices of a k x k grid (k = sqrt(count)) of cubes in the ground (x-z) plane, rows receding in
    depth from the default camera (paper 000 Table 3 / Fig. 9's crowd of instances), so that most view rays cross
    several boxes front to back. Half-extent ``INSTANCE_FILL[overlap]`` of the pitch; the outer faces lie on
    |x|, |z| = 1.2 (pitch p = 2.4 / (k - 1 + 2 fill)), the boxes' centres at y = 0.
    """
    if isinstance(count, bool) or count not in MULTI_COUNTS:
        raise VolrenError(f"instances scene count must be one of {', '.join(map(str, MULTI_COUNTS))}, got {count!r}")
    k = round(np.sqrt(count))
    fill = INSTANCE_FILL[bool(overlap)]
    pitch = 2.4 / (k - 1 + 2 * fill)
    centres = -1.2 + fill * pitch + np.arange(k) * pitch
    return [scale_translate(fill * pitch, (x, 0.0, z)) for z in centres for x in centres]


def _instances_scene(resolution: int, *, count: int = 16, seed: int = 0, overlap: bool = False) -> Scene:
    """Smoke plumes and clouds alternating (a checkerboard), each n // 2 per axis: ``resolution`` 256 gives the
    paper's 128^3 instances. Optical depth about half the single scenes' through each box (density scale over the
    half-extent), so instances behind others show through."""
    n = _check_resolution(resolution)
    seed = _check_seed(seed)
    layout = instances_layout(count, overlap)
    k = round(np.sqrt(count))
    volumes = []
    for i, to_world in enumerate(layout):
        half = to_world[0, 0]
        rng = np.random.default_rng([seed, 4, i])
        if (i // k + i % k) % 2 == 0:
            volumes.append(Volume(_smoke_field(n // 2, rng), to_world=to_world, density_scale=6.5 / half,
                                  albedo=(0.85, 0.85, 0.85), g=0.2, name=f"smoke{i}"))
        else:
            volumes.append(Volume(_cloud_field(n // 2, rng), to_world=to_world, density_scale=5.5 / half,
                                  albedo=(0.97, 0.97, 0.97), g=0.5, name=f"cloud{i}"))
    name = f"instances{'-overlap' if overlap else ''}{count}"
    return Scene(tuple(volumes), _OVERHEAD_LIGHT, _SKY, _BACKGROUND, name=name)


@dataclass(frozen=True)
class BuiltinScene:
    """A named procedural scene; ``build(resolution, *, count, seed)`` returns a ready ``Scene``."""

    name: str
    description: str
    """one line, shown by ``volren scenes``"""
    build: Callable[..., Scene]


BUILTIN_SCENES: dict[str, BuiltinScene] = {
    s.name: s
    for s in (
        BuiltinScene("smoke", "rising fBm smoke plume, grey, mildly forward scattering (g 0.2), lit from the "
                     "upper left under a cool sky", _smoke_scene),
        BuiltinScene("cloud", "cumulus billow with a flat base, bright (albedo 0.97, g 0.5)", _cloud_scene),
        BuiltinScene("phantom", "3D modified Shepp-Logan head phantom, CT-like and semi-transparent: its "
                     "ventricles show through the skull", _phantom_scene),
        BuiltinScene("multi", "grid of 4, 16 or 36 cloud puffs (each n/2 per axis) in the x-y plane", _multi_scene),
        BuiltinScene("instances", "4, 16 or 36 smoke and cloud instances (each n/2 per axis) in rows receding in "
                     "depth, disjoint boxes, lit from overhead", _instances_scene),
        BuiltinScene("instances-overlap", "the instances grid with boxes overlapping their neighbours by 0.2 of the "
                     "pitch", functools.partial(_instances_scene, overlap=True)),
        BuiltinScene("smoke-floor", "the smoke plume over a grey floor that it shadows and occludes",
                     _smoke_floor_scene),
        BuiltinScene("fire", "a flame: a hot blackbody core (1200-2500 K) in thin soot under a smoke column, dimly lit",
                     _fire_scene),
    )
}


COUNTED_SCENES = ("multi", "instances", "instances-overlap")
"""built-in scenes whose number of instances ``count`` (one of MULTI_COUNTS) chooses"""


def _lookup(name: str) -> BuiltinScene:
    try:
        return BUILTIN_SCENES[name]
    except (KeyError, TypeError):
        raise VolrenError(f"unknown scene {name!r}: choose from {', '.join(BUILTIN_SCENES)}") from None


def builtin_scene(name: str, resolution: int = 64, *, count: int = 4, seed: int = 0) -> Scene:
    """Build a built-in scene; ``count`` is used by the scenes in :data:`COUNTED_SCENES` only, and ignored by the
    single-volume scenes."""
    return _lookup(name).build(_check_resolution(resolution), count=count, seed=_check_seed(seed))


def density_field(name: str, resolution: int = 64, seed: int = 0) -> np.ndarray:
    """The density grid of a single-volume built-in scene, without building the Scene (for tests and tools)."""
    fields: dict[str, Callable[[int, int], np.ndarray]] = {
        "smoke": smoke_density,
        "cloud": cloud_density,
        "phantom": lambda n, _seed: phantom_density(n),
    }
    _lookup(name)
    if name not in fields:
        raise VolrenError(f"scene {name!r} has several volumes: build it with builtin_scene() instead")
    return fields[name](_check_resolution(resolution), _check_seed(seed))

"""Blackbody emission: Planck's law seen through the CIE 1931 observer, as linear sRGB radiance (fire, issue 21).

The spectral radiance of a blackbody at temperature T [K] is Planck's law,

    B(lambda, T) = 2 h c^2 / lambda^5 / (exp(h c / (lambda k_B T)) - 1)   [W/(m^2 sr m)],

whose integral over all wavelengths is the Stefan-Boltzmann radiance sigma T^4 / pi. Its colour is the integral
against the CIE 1931 2-degree colour matching functions, XYZ(T) = integral B(lambda, T) (x, y, z)-bar(lambda) dlambda
over 360-830 nm, with the matching functions tabulated by the CIE at 1 nm (``cie1931_2deg.csv``, source named there),
then XYZ -> linear sRGB by the IEC 61966-2-1 matrix. (Wyman, Sloan and Shirley's multi-lobe Gaussian fit, used
before issue 47, put the 1000 K chromaticity 0.015 off the tabulated one in xy, 0.004 at 2000 K: the dim parts of a
flame.) Below about 1900 K (and above about 10000 K) a blackbody lies outside the sRGB gamut: the negative
components are clipped to 0.

`blackbody_table` samples that colour at temperatures spaced evenly from K0 to K1 and scales it so that the hottest
entry has luminance Y = ``scale``: ``--emission-scale`` is the luminance [W/(m^3 sr)] of the radiance emitted per
metre at K1, and cooler entries keep their physical ratio to it (a 1000 K flame is ~1e-4 of a 2000 K one in Y).

Reading a temperature grid (issue 45 item 2): `kelvin_span` decides whether a grid's values are kelvin (its positive
values run from at least `KELVIN_COLDEST` to a hottest in `KELVIN_HOTTEST`: ambient air near 300 K up to a flame's
1000-3000 K) or relative (a simulation's 0..1 or 0..a few, mapped onto a temperature range). `flame_emission_scale`
is the default ``--emission-scale`` of a loaded flame: the hottest blackbody radiance, integrated through the flame's
thickness d with its own extinction sigma, is `FLAME_CONTRAST` times the radiance of a white surface facing the
scene's lights, W = sum(Y(E_light)) / pi + Y(L_environment):

    scale = FLAME_CONTRAST * W * sigma / (1 - exp(-sigma d))      (-> FLAME_CONTRAST * W / d for a thin flame),

d the cube root of the hot region's volume (voxels emitting at least `HOT_SHARE` of the hottest's luminance, where
the density is > 0) and sigma its mean extinction.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

H = 6.62607015e-34
"""Planck constant [J s]"""
C = 2.99792458e8
"""speed of light [m/s]"""
K_B = 1.380649e-23
"""Boltzmann constant [J/K]"""
SIGMA = 2.0 * np.pi**5 * K_B**4 / (15.0 * H**3 * C**2)
"""Stefan-Boltzmann constant [W/(m^2 K^4)]"""

TABLE_SIZE = 256
"""entries of a blackbody table: one every (K1 - K0) / 255 kelvin, interpolated linearly between them"""

WAVELENGTHS = np.arange(360.0, 831.0, 1.0) * 1e-9
"""[m] the visible range the colour integrals run over (1 nm steps, trapezoid rule)"""

KELVIN_COLDEST = 200.0
"""[K] a grid is read as kelvin only if its coldest positive value is at least this (ambient air is ~300 K; a
relative grid's faint edges come down to near 0)"""
KELVIN_HOTTEST = (500.0, 10000.0)
"""[K] ... and its hottest value lies in this range (a flame glows from ~800 K; none is 10,000 K hot)"""
FLAME_CONTRAST = 4.0
"""the default emission scale makes the hottest flame, through its thickness, this many times as bright (luminance) as
a white surface facing the scene's lights (`flame_emission_scale`)"""
HOT_SHARE = 0.1
"""the flame's thickness is that of its voxels emitting at least this share of the hottest's luminance"""

XYZ_TO_SRGB = np.array([[3.2406, -1.5372, -0.4986],
                        [-0.9689, 1.8758, 0.0415],
                        [0.0557, -0.2040, 1.0570]])
"""CIE XYZ to linear sRGB (IEC 61966-2-1, D65 white)"""


def planck(wavelength: np.ndarray, temperature: float | np.ndarray) -> np.ndarray:
    """B(lambda, T) [W/(m^2 sr m)] at ``wavelength`` [m] (broadcast against ``temperature`` [K])."""
    lam = np.asarray(wavelength, dtype=np.float64)
    with np.errstate(divide="ignore"):  # T = 0 K (a kelvin grid's table starts there): x = inf, B = 0
        x = H * C / (lam * K_B * np.asarray(temperature, dtype=np.float64))
    return 2.0 * H * C**2 / lam**5 / np.expm1(np.minimum(x, 700.0))


@functools.cache
def _cmf_table() -> np.ndarray:
    """(471, 4): nm, x-bar, y-bar, z-bar at 360, 361, ..., 830 nm."""
    return np.loadtxt(Path(__file__).with_name("cie1931_2deg.csv"), delimiter=",", comments="#")


def cie_xyz_bar(wavelength: np.ndarray) -> np.ndarray:
    """The CIE 1931 2-degree colour matching functions at ``wavelength`` [m], shape (..., 3): the CIE's 1 nm table,
    linear between its rows, 0 outside 360-830 nm."""
    table = _cmf_table()
    nm = np.asarray(wavelength, dtype=np.float64) * 1e9
    return np.stack([np.interp(nm, table[:, 0], table[:, k], left=0.0, right=0.0) for k in (1, 2, 3)], axis=-1)


def blackbody_xyz(temperature: float | np.ndarray) -> np.ndarray:
    """XYZ(T) = integral B(lambda, T) cmf(lambda) dlambda [W/(m^2 sr)], shape (..., 3)."""
    t = np.asarray(temperature, dtype=np.float64)[..., None]
    spectrum = planck(WAVELENGTHS, t)[..., None] * cie_xyz_bar(WAVELENGTHS)
    return np.trapezoid(spectrum, WAVELENGTHS, axis=-2)


def blackbody_rgb(temperature: float | np.ndarray) -> np.ndarray:
    """Linear sRGB radiance [W/(m^2 sr)] of a blackbody at ``temperature``, negative components clipped to 0."""
    return np.maximum(blackbody_xyz(temperature) @ XYZ_TO_SRGB.T, 0.0)


def blackbody_table(k0: float, k1: float, scale: float = 1.0, size: int = TABLE_SIZE) -> np.ndarray:
    """(size, 3) float32 radiance per metre [W/(m^3 sr)] at T_i = k0 + (k1 - k0) i / (size - 1): the linear sRGB
    colour of each T_i scaled by ``scale`` / Y(k1), so the entry at k1 has luminance Y = ``scale``."""
    temperatures = np.linspace(k0, k1, size)
    return (blackbody_rgb(temperatures) * (scale / blackbody_xyz(k1)[1])).astype(np.float32)


def positive_range(values) -> tuple[float, float] | None:
    """(smallest, largest) positive value of a grid (a dense array or a `volren.sparse.SparseGrid`), None if none."""
    v = values.stored_values() if hasattr(values, "stored_values") else np.asarray(values)
    positive = v[v > 0]
    return (float(positive.min()), float(positive.max())) if positive.size else None


def kelvin_span(values) -> tuple[float, float] | None:
    """(coldest, hottest) of a temperature grid's positive values (`positive_range`) when they read as kelvin:
    coldest >= `KELVIN_COLDEST` and hottest within `KELVIN_HOTTEST`; None when they read as relative (or none is
    positive)."""
    span = positive_range(values)
    if span is None:
        return None
    lo, hi = span
    return (lo, hi) if lo >= KELVIN_COLDEST and KELVIN_HOTTEST[0] <= hi <= KELVIN_HOTTEST[1] else None


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Y of linear sRGB colours (..., 3)."""
    return np.asarray(rgb, dtype=np.float64) @ np.linalg.inv(XYZ_TO_SRGB)[1]


def flame_emission_scale(u: np.ndarray, density: np.ndarray, density_scale: float, k0: float, k1: float,
                         voxel_volume: float, white: float) -> float:
    """The default emission scale (module docstring): FLAME_CONTRAST * white * sigma / (1 - exp(-sigma d)), with ``u``
    the emission grid normalised to [0, 1] (`volren.scene.Volume.emission_u`) over the temperatures k0..k1,
    ``density`` its density grid (sigma_t = density_scale * density), ``voxel_volume`` [m^3] and ``white`` the
    luminance [W/(m^2 sr)] of a white surface facing the lights. Read on at most ~64^3 voxels (a stride); 1 where
    nothing glows."""
    stride = max(1, int(np.ceil((u.size / 64**3) ** (1 / 3))))
    u, rho = u[::stride, ::stride, ::stride], density[::stride, ::stride, ::stride]
    table = luminance(blackbody_table(k0, k1, 1.0))  # Y per metre, 1 at u = 1
    y = np.where(u > 0, np.interp(u, np.linspace(0.0, 1.0, table.size), table), 0.0)
    hot = (y >= HOT_SHARE) & (rho > 0)
    if not hot.any():
        return 1.0
    thickness = float(np.cbrt(hot.sum() * stride**3 * voxel_volume))
    sigma = density_scale * float(rho[hot].mean())
    path = thickness if sigma * thickness < 1e-6 else -float(np.expm1(-sigma * thickness)) / sigma
    return FLAME_CONTRAST * white / path

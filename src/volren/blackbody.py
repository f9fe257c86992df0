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

XYZ_TO_SRGB = np.array([[3.2406, -1.5372, -0.4986],
                        [-0.9689, 1.8758, 0.0415],
                        [0.0557, -0.2040, 1.0570]])
"""CIE XYZ to linear sRGB (IEC 61966-2-1, D65 white)"""


def planck(wavelength: np.ndarray, temperature: float | np.ndarray) -> np.ndarray:
    """B(lambda, T) [W/(m^2 sr m)] at ``wavelength`` [m] (broadcast against ``temperature`` [K])."""
    lam = np.asarray(wavelength, dtype=np.float64)
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

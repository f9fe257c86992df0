"""Blackbody emission: Planck's law seen through the CIE 1931 observer, as linear sRGB radiance (fire, issue 21).

The spectral radiance of a blackbody at temperature T [K] is Planck's law,

    B(lambda, T) = 2 h c^2 / lambda^5 / (exp(h c / (lambda k_B T)) - 1)   [W/(m^2 sr m)],

whose integral over all wavelengths is the Stefan-Boltzmann radiance sigma T^4 / pi. Its colour is the integral
against the CIE 1931 2-degree colour matching functions, XYZ(T) = integral B(lambda, T) (x, y, z)-bar(lambda) dlambda
over 360-830 nm, with the matching functions in Wyman, Sloan and Shirley's multi-lobe Gaussian fit (JCGT 2(2), 2013,
Eq. 2-4; within about 1% of the tabulated CIE data), then XYZ -> linear sRGB by the IEC 61966-2-1 matrix. Below about
1900 K (and above about 10000 K) a blackbody lies outside the sRGB gamut: the negative components are clipped to 0.

`blackbody_table` samples that colour at temperatures spaced evenly from K0 to K1 and scales it so that the hottest
entry has luminance Y = ``scale``: ``--emission-scale`` is the luminance [W/(m^3 sr)] of the radiance emitted per
metre at K1, and cooler entries keep their physical ratio to it (a 1000 K flame is ~1e-4 of a 2000 K one in Y).
"""

from __future__ import annotations

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


def _lobe(lam_nm: np.ndarray, mu: float, s1: float, s2: float) -> np.ndarray:
    s = np.where(lam_nm < mu, s1, s2)
    return np.exp(-0.5 * ((lam_nm - mu) / s) ** 2)


def cie_xyz_bar(wavelength: np.ndarray) -> np.ndarray:
    """The CIE 1931 colour matching functions at ``wavelength`` [m], shape (..., 3): Wyman et al. 2013, Eq. 2-4."""
    nm = np.asarray(wavelength, dtype=np.float64) * 1e9
    x = 1.056 * _lobe(nm, 599.8, 37.9, 31.0) + 0.362 * _lobe(nm, 442.0, 16.0, 26.7) - 0.065 * _lobe(nm, 501.1, 20.4,
                                                                                                    26.2)
    y = 0.821 * _lobe(nm, 568.8, 46.9, 40.5) + 0.286 * _lobe(nm, 530.9, 16.3, 31.1)
    z = 1.217 * _lobe(nm, 437.0, 11.8, 36.0) + 0.681 * _lobe(nm, 459.0, 26.0, 13.8)
    return np.stack([x, y, z], axis=-1)


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

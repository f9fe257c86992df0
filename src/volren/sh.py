"""Real spherical harmonics up to order 4 (bands l = 0..3, n^2 = 16 coefficients) for ambient GI (paper 000 §3.2).

Conventions: the orthonormal real basis Y_lm in the common graphics ordering (index l^2 + l + m, m = -l..l), with
the Condon-Shortley phase folded in as in Sloan's "Stupid SH tricks", evaluated at unit directions (x, y, z) in world
space. Environments project with solid-angle weights (equirect pixels: sin(theta) dtheta dphi, `volren.scene`'s
direction convention); rotations of coefficients are the band-wise matrices R_l[i, j] = integral of
Y_li(R^-1 w) Y_lj(w) dw, computed once per rotation by an exact quadrature (Gauss-Legendre in cos theta times a
uniform azimuth grid integrates the degree <= 6 products exactly). Henyey-Greenstein scattering of SH radiance
multiplies band l by g^l (its zonal coefficients).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from volren.errors import VolrenError
from volren.scene import Environment

MAX_ORDER = 4
vec16 = wp.types.vector(length=16, dtype=wp.float32)


def check_order(order: int) -> None:
    if int(order) != order or not 1 <= order <= MAX_ORDER:
        raise VolrenError(f"SH order must be an integer in [1, {MAX_ORDER}] (n^2 coefficients), got {order}")


def basis(d: np.ndarray, order: int = MAX_ORDER) -> np.ndarray:
    """Y_lm at unit directions d (..., 3) -> (..., order^2)."""
    check_order(order)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [np.full_like(x, 0.5 * math.sqrt(1 / math.pi))]
    if order > 1:
        c1 = math.sqrt(3 / (4 * math.pi))
        out += [c1 * y, c1 * z, c1 * x]
    if order > 2:
        out += [0.5 * math.sqrt(15 / math.pi) * x * y, 0.5 * math.sqrt(15 / math.pi) * y * z,
                0.25 * math.sqrt(5 / math.pi) * (3 * z * z - 1), 0.5 * math.sqrt(15 / math.pi) * x * z,
                0.25 * math.sqrt(15 / math.pi) * (x * x - y * y)]
    if order > 3:
        out += [0.25 * math.sqrt(35 / (2 * math.pi)) * y * (3 * x * x - y * y),
                0.5 * math.sqrt(105 / math.pi) * x * y * z,
                0.25 * math.sqrt(21 / (2 * math.pi)) * y * (5 * z * z - 1),
                0.25 * math.sqrt(7 / math.pi) * z * (5 * z * z - 3),
                0.25 * math.sqrt(21 / (2 * math.pi)) * x * (5 * z * z - 1),
                0.25 * math.sqrt(105 / math.pi) * z * (x * x - y * y),
                0.25 * math.sqrt(35 / (2 * math.pi)) * x * (x * x - 3 * y * y)]
    return np.stack(out, axis=-1)


def sphere_quadrature(n_theta: int = 8, n_phi: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Directions (N, 3) and weights (N,) integrating polynomials of degree < min(2 n_theta, n_phi) exactly."""
    mu, w_mu = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) / n_phi * 2 * np.pi
    s = np.sqrt(1 - mu**2)
    d = np.stack([s[:, None] * np.cos(phi), np.repeat(mu[:, None], n_phi, 1), s[:, None] * np.sin(phi)], -1)
    return d.reshape(-1, 3), np.repeat(w_mu * (2 * np.pi / n_phi), n_phi)


def equirect_directions(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre directions (h, w, 3) and solid angles (h, w) of an h x w equirect map (`volren.scene`)."""
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    s = np.sin(theta)[:, None]
    d = np.stack([s * np.cos(phi), np.repeat(np.cos(theta)[:, None], w, 1), s * np.sin(phi)], -1)
    solid = np.repeat((np.sin(theta) * (np.pi / h) * (2 * np.pi / w))[:, None], w, 1)
    return d, solid


def project_environment(env: Environment, order: int = 3) -> np.ndarray:
    """(order^2, 3) SH coefficients of the environment's radiance."""
    check_order(order)
    if env.image is None:
        out = np.zeros((order * order, 3))
        out[0] = np.asarray(env.radiance) * math.sqrt(4 * math.pi)
        return out
    d, solid = equirect_directions(*env.image.shape[:2])
    return np.einsum("hwk,hw,hwc->kc", basis(d, order), solid, env.image.astype(np.float64))


def evaluate(coefficients: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Radiance (..., 3) of SH coefficients (n^2, 3) at unit directions d (..., 3)."""
    order = math.isqrt(len(coefficients))
    return basis(d, order) @ coefficients


def rotation(matrix: np.ndarray, order: int = 3) -> np.ndarray:
    """(order^2, order^2) block-diagonal matrix taking the coefficients of f to those of f rotated by ``matrix``
    (f_rot(w) = f(R^-1 w))."""
    check_order(order)
    d, w = sphere_quadrature()
    rotated = basis(d @ np.asarray(matrix, float), order)  # Y(R^-1 w): rows of d times R = R^T d = R^-1 d
    full = np.einsum("nk,nj,n->jk", rotated, basis(d, order), w)
    out = np.zeros_like(full)
    for band in range(order):
        s = slice(band * band, (band + 1) ** 2)
        out[s, s] = full[s, s]
    return out


def hg_convolution(g: float, order: int = 3) -> np.ndarray:
    """Per coefficient, the factor g^l that Henyey-Greenstein scattering applies to band l."""
    check_order(order)
    return np.array([g**band for band in range(order) for _ in range(2 * band + 1)])


@wp.func
def sh_basis16(d: wp.vec3) -> vec16:
    """All 16 Y_lm (bands 0..3) at unit direction d, as `basis`."""
    x = d[0]
    y = d[1]
    z = d[2]
    return vec16(
        0.28209479, 0.48860251 * y, 0.48860251 * z, 0.48860251 * x,
        1.09254843 * x * y, 1.09254843 * y * z, 0.31539157 * (3.0 * z * z - 1.0), 1.09254843 * x * z,
        0.54627422 * (x * x - y * y),
        0.59004359 * y * (3.0 * x * x - y * y), 2.89061144 * x * y * z, 0.45704580 * y * (5.0 * z * z - 1.0),
        0.37317633 * z * (5.0 * z * z - 3.0), 0.45704580 * x * (5.0 * z * z - 1.0),
        1.44530572 * z * (x * x - y * y), 0.59004359 * x * (x * x - 3.0 * y * y))

"""Spherical harmonics (paper 000 §3.2's SH lighting): projections against closed forms, orthonormality, rotation,
Henyey-Greenstein convolution, and the Warp basis against numpy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from conftest import DEVICE
from volren.errors import VolrenError
from volren.scene import Environment
from volren.sh import (
    basis,
    equirect_directions,
    evaluate,
    hg_convolution,
    project_environment,
    rotation,
    sh_basis16,
    sphere_quadrature,
    vec16,
)


def test_basis_is_orthonormal():
    d, w = sphere_quadrature()
    y = basis(d, 4)
    np.testing.assert_allclose(np.einsum("nk,nj,n->kj", y, y, w), np.eye(16), atol=1e-10)


def test_constant_environment_projects_to_band_zero():
    c = project_environment(Environment((0.5, 1.0, 2.0)), 4)
    np.testing.assert_allclose(c[0], np.array([0.5, 1.0, 2.0]) * math.sqrt(4 * math.pi))
    assert np.abs(c[1:]).max() == 0.0


def test_clamped_cosine_lobe_matches_its_zonal_closed_form():
    """L(w) = max(w.y, 0): zonal coefficients sqrt(pi) / 2, sqrt(pi / 3), sqrt(5 pi) / 8, 0 on the +y axis; in this
    basis the axis is y, so the l = 1 coefficient sits at index 1 (Y_1,-1 = c y), l = 2 spreads over its band by
    rotation and l = 3's zonal term is 0. Checked through the rotation-invariant band energies."""
    h, w = 256, 512
    d, _ = equirect_directions(h, w)
    image = np.repeat(np.maximum(d[..., 1], 0)[..., None], 3, -1).astype(np.float32)
    c = project_environment(Environment(image=image), 4)[:, 0]
    expected = [math.sqrt(math.pi) / 2, math.sqrt(math.pi / 3), math.sqrt(5 * math.pi) / 8, 0.0]
    for band, e in enumerate(expected):
        energy = math.sqrt(np.sum(c[band * band:(band + 1) ** 2] ** 2))
        assert abs(energy - e) < 2e-3, band
    assert abs(c[1] - expected[1]) < 2e-3


def test_rotation_preserves_band_energy_and_equals_projecting_the_rotated_environment():
    h, w = 128, 256
    d, _ = equirect_directions(h, w)
    lobe = np.array([0.3, 0.8, -0.52]) / np.linalg.norm([0.3, 0.8, -0.52])

    def image_of(axis):
        return np.repeat(np.maximum(d @ axis, 0)[..., None] ** 2, 3, -1).astype(np.float32)

    a = np.radians(40.0)
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    original = project_environment(Environment(image=image_of(lobe)), 3)
    rotated = project_environment(Environment(image=image_of(rot @ lobe)), 3)
    np.testing.assert_allclose(rotation(rot, 3) @ original, rotated, atol=5e-3)
    for band in range(3):
        s = slice(band * band, (band + 1) ** 2)
        assert abs(np.linalg.norm(original[s, 0]) - np.linalg.norm((rotation(rot, 3) @ original)[s, 0])) < 1e-9


def test_hg_convolution_scales_bands_and_keeps_the_mean():
    f = hg_convolution(0.5, 4)
    np.testing.assert_allclose(f, [1, .5, .5, .5, .25, .25, .25, .25, .25, .125, .125, .125, .125, .125, .125, .125])
    c = project_environment(Environment((1.0, 1.0, 1.0)), 4)
    d, _ = sphere_quadrature()
    np.testing.assert_allclose(evaluate(c * f[:, None], d), 1.0, atol=1e-12)  # isotropic light stays isotropic


@wp.kernel
def basis_kernel(d: wp.array(dtype=wp.vec3), out: wp.array(dtype=vec16)):
    i = wp.tid()
    out[i] = sh_basis16(d[i])


def test_warp_basis_matches_numpy():
    d, _ = sphere_quadrature()
    out = wp.zeros(len(d), dtype=vec16, device=DEVICE)
    wp.launch(basis_kernel, dim=len(d), inputs=[wp.array(d.astype(np.float32), dtype=wp.vec3, device=DEVICE), out],
              device=DEVICE)
    np.testing.assert_allclose(out.numpy(), basis(d, 4), atol=1e-5)


def test_bad_order():
    with pytest.raises(VolrenError, match="order"):
        basis(np.zeros((1, 3)), 5)

"""Spot cone profiles (issue 19 item 8): `light_irradiance`, the one function every renderer evaluates spots with
(the light-map marchers, the reference, VPT, fog and the surfaces), against the closed forms of both profiles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from conftest import DEVICE, homogeneous_volume
from volren.errors import VolrenError
from volren.kernels.common import LightGPU, light_irradiance
from volren.scene import Scene, SpotLight
from volren.upload import light_structs

INNER, OUTER, DIST, INTENSITY = 5.0, 25.0, 2.0, 8.0


@wp.kernel
def irradiance_kernel(lights: wp.array(dtype=LightGPU), points: wp.array(dtype=wp.vec3),
                      out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = light_irradiance(lights[0], points[i])


def irradiance(falloff: str, angles_deg: np.ndarray) -> np.ndarray:
    """Irradiance at DIST from a spot at the origin pointing along +x, at the given angles from its axis."""
    spot = SpotLight((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (INTENSITY,) * 3, INNER, OUTER, falloff=falloff)
    a = np.radians(angles_deg)
    pts = DIST * np.stack([np.cos(a), np.sin(a) * 0.6, np.sin(a) * 0.8], axis=1)
    out = wp.zeros(len(a), dtype=wp.vec3, device=DEVICE)
    wp.launch(irradiance_kernel, len(a), [light_structs(Scene((homogeneous_volume(1.0),), (spot,)), DEVICE),
                                          wp.array(pts, dtype=wp.vec3, device=DEVICE), out], device=DEVICE)
    return out.numpy()[:, 0] * DIST**2 / INTENSITY


ANGLES = np.array([0.0, INNER, 10.0, 15.0, 20.0, OUTER, 30.0])


def test_smoothstep_profile_is_cubic_in_the_cosine():
    """Default: s = smoothstep(cos outer, cos inner, cos theta), 1 inside the inner cone, 0 beyond the outer; at the
    mid-angle 15 degrees s = 0.7362 (the cosine is nearer cos inner than the angle is to inner)."""
    c = np.cos(np.radians(ANGLES))
    t = np.clip((c - math.cos(math.radians(OUTER))) / (math.cos(math.radians(INNER)) - math.cos(math.radians(OUTER))),
                0, 1)
    expected = t * t * (3 - 2 * t)
    np.testing.assert_allclose(irradiance("smoothstep", ANGLES), expected, atol=2e-5)
    assert expected[3] == pytest.approx(0.7362, abs=1e-4)


def test_linear_profile_is_linear_in_the_angle():
    """``falloff="linear"``: (outer - theta) / (outer - inner): 1, 1, 0.75, 0.5, 0.25, 0, 0 at the test angles."""
    np.testing.assert_allclose(irradiance("linear", ANGLES), [1.0, 1.0, 0.75, 0.5, 0.25, 0.0, 0.0], atol=2e-4)


def test_spot_falloff_is_validated():
    with pytest.raises(VolrenError, match="falloff"):
        SpotLight(falloff="cosine")

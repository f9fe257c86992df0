"""Closed forms for homogeneous media: transmittance, single scattering, emission; the camera inside a volume."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import DOWN, axis_camera, chords, homogeneous_volume, render, scene_of


@pytest.mark.parametrize("position", [(0.0, 0.0, 3.0), (2.0, 2.0, 2.0), (-1.7, 2.2, 0.9)])
def test_transmittance_matches_beer_lambert(method, position):
    """alpha = 1 - exp(-sigma_t L) for every pixel, axis-aligned and diagonal (corner to corner) rays included."""
    sigma = 1.3
    cam = axis_camera(position)
    frame = render(method, scene_of(homogeneous_volume(sigma)), [cam], samples=256, min_transmittance=0.0)
    _, chord = chords(cam)
    expected = 1.0 - np.exp(-sigma * chord)
    alpha = frame.images[0][..., 3]
    # Pixels whose rays graze an edge have chords that change within float32 rounding; skip the shortest chords.
    mask = chord > 0.05
    np.testing.assert_allclose(alpha[mask], expected[mask], atol=1e-3)
    assert np.all(alpha[chord == 0] == 0)
    if position == (2.0, 2.0, 2.0):
        assert alpha[16, 16] == pytest.approx(1 - np.exp(-sigma * 2 * np.sqrt(3)), abs=1e-4)


def single_scattering_closed_form(cam, sigma, albedo, g, irradiance, ambient):
    """L = int sigma_s (p(theta) E exp(-sigma (1 - y(t))) + L_amb) exp(-sigma (t - t0)) dt for light travelling -y
    through the cube [-1, 1]^3: the exponent is linear in t, so the integral is exact."""
    d = cam.ray_directions()
    o = np.asarray(cam.position)
    t0, chord = chords(cam)
    cos = -d @ np.array([0.0, -1.0, 0.0])  # dot(light travel, -view)
    phase = (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * cos) ** 1.5)
    # exponent(t) = -sigma (t - t0) - sigma (1 - o_y - d_y t) = a + b t
    b = -sigma * (1 - d[..., 1])
    a = sigma * t0 - sigma * (1 - o[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = np.where(np.abs(b) > 1e-12, (np.exp(a + b * (t0 + chord)) - np.exp(a + b * t0)) / b,
                          np.exp(a) * chord)
    amb = (1 - np.exp(-sigma * chord)) / sigma
    return sigma * albedo * (phase * irradiance * direct + ambient * amb), chord


@pytest.mark.parametrize("g", [0.0, 0.6])
def test_single_scattering_matches_closed_form(method, g):
    sigma, albedo, ambient = 1.5, 0.8, 0.1
    cam = axis_camera((0.0, 0.3, 3.0), size=(41, 31))
    scene = scene_of(homogeneous_volume(sigma, albedo=albedo, g=g, n=16), lights=[DOWN], ambient=ambient)
    config = {"samples": 256, "light_samples": 256, "min_transmittance": 0.0}
    if method == "dssrm":
        config["light_grid"] = 128
    frame = render(method, scene, [cam], **config)
    expected, chord = single_scattering_closed_form(cam, sigma, albedo, g, 2.0, ambient)
    got = frame.images[0][..., 0]
    mask = chord > 0.2
    np.testing.assert_allclose(got[mask], expected[mask], rtol=0.01)
    assert np.count_nonzero(mask) > 200


@pytest.mark.parametrize("sigma", [0.0, 0.8])
def test_emission_only_matches_integral(method, sigma):
    """No scattering: L = e (1 - exp(-sigma L)) / sigma, and e L when sigma = 0 (alpha then stays 0)."""
    e = np.array([0.5, 0.2, 0.1])
    cam = axis_camera((0.4, -0.3, 2.5))
    frame = render(method, scene_of(homogeneous_volume(sigma, emission=e)), [cam], samples=128, min_transmittance=0)
    _, chord = chords(cam)
    expected = chord * 1.0 if sigma == 0 else (1 - np.exp(-sigma * chord)) / sigma
    np.testing.assert_allclose(frame.images[0][..., :3], expected[..., None] * e, rtol=2e-3, atol=1e-6)
    if sigma == 0:
        assert np.all(frame.images[0][..., 3] == 0)


def test_camera_inside_volume(method):
    """From the centre of the cube, rays start at the near plane and run to the far face."""
    sigma = 0.9
    cam = axis_camera((0.0, 0.0, 0.0), look_at=(0.0, 0.0, -1.0), near=0.05)
    frame = render(method, scene_of(homogeneous_volume(sigma)), [cam], samples=128, min_transmittance=0)
    _, chord = chords(cam)
    np.testing.assert_allclose(frame.images[0][..., 3], 1 - np.exp(-sigma * chord), atol=1e-4)
    assert chord[16, 16] == pytest.approx(0.95)
    assert np.isfinite(frame.depths[0]).all()


def test_depth_is_where_transmittance_halves():
    sigma = 2.0
    cam = axis_camera((0.0, 0.0, 6.0))
    frame = render("reference", scene_of(homogeneous_volume(sigma)), [cam], samples=512, min_transmittance=0)
    # T = 1/2 at ln 2 / sigma into the box; the step that crosses it is recorded (within one step of 2 sqrt 3 / 512).
    assert frame.depths[0][16, 16] == pytest.approx(5.0 + np.log(2) / sigma, abs=2 * np.sqrt(3) / 512 + 1e-4)
    assert np.isinf(frame.depths[0][0, 0])


def test_point_light_inverse_square(method):
    """Optically thin cube (sigma 1e-3), isotropic phase, point light at (0, D, 0): along the central ray (x = y = 0)
    L = sigma_s I / (4 pi) int_{-1}^{1} dz / (D^2 + z^2) = sigma_s I / (4 pi) (2 / D) atan(1 / D), up to e^-0.002."""
    from volren.scene import PointLight

    sigma, albedo, intensity, dist = 1e-3, 1.0, 50.0, 3.0
    scene = scene_of(homogeneous_volume(sigma, albedo=albedo, n=16),
                     lights=[PointLight((0.0, dist, 0.0), (intensity,) * 3)])
    frame = render(method, scene, [axis_camera()], samples=256, light_samples=64, min_transmittance=0)
    expected = sigma * albedo * intensity / (4 * np.pi) * (2 / dist) * np.arctan(1 / dist)
    assert frame.images[0][16, 16, 1] == pytest.approx(expected, rel=3e-3)


def test_spot_light_cone(method):
    """A spot pointing down from (0, D, 0) over the thin cube of the test above: the central ray's point (0, 0, z)
    sees the axis at cos theta = D / sqrt(D^2 + z^2), so L = sigma_s I / (4 pi) int s(cos theta) T / (D^2 + z^2) dz
    over [-1, 1] with s = smoothstep(cos_outer, cos_inner, .) and T the view and light attenuation (1-D quadrature
    here). Measured within 4e-6 of it (0.32% under before thin steps were composited by their series, see
    `composite_step`). Pointing the spot up leaves the cube dark."""
    from volren.scene import SpotLight

    sigma, intensity, dist, inner, outer = 1e-3, 50.0, 3.0, 5.0, 10.0
    z = (np.arange(200_000) + 0.5) / 200_000 * 2 - 1
    c = dist / np.sqrt(dist**2 + z**2)
    s = np.clip((c - np.cos(np.radians(outer))) / (np.cos(np.radians(inner)) - np.cos(np.radians(outer))), 0, 1)
    attenuation = np.exp(-sigma * ((1 - z) + 1 / c))
    expected = sigma * intensity / (4 * np.pi) * np.mean(s * s * (3 - 2 * s) * attenuation / (dist**2 + z**2)) * 2
    for direction, value in (((0.0, -1.0, 0.0), expected), ((0.0, 1.0, 0.0), 0.0)):
        spot = SpotLight((0.0, dist, 0.0), direction, (intensity,) * 3, inner, outer)
        frame = render(method, scene_of(homogeneous_volume(sigma, albedo=1.0, n=16), lights=[spot]), [axis_camera()],
                       samples=512, light_samples=64, min_transmittance=0)
        assert frame.images[0][16, 16, 1] == pytest.approx(value, rel=1e-3, abs=1e-12)


def test_early_termination_stops_the_march(method):
    """A dense cube (sigma 50) seen along its axis by one pixel: T falls under min_transmittance 1e-3 after
    ln(1000) / 50 = 0.138 m of the 2 m chord, so the march stops after about 7% of its N samples."""
    sigma, samples = 50.0, 512
    cam = axis_camera(size=(1, 1))
    frame = render(method, scene_of(homogeneous_volume(sigma)), [cam], samples=samples, light_samples=8,
                   min_transmittance=1e-3)
    steps = 2.0 / (2 * np.sqrt(3) / samples)
    expected = np.log(1e3) / sigma / 2.0 * steps
    assert frame.images[0][0, 0, 3] == pytest.approx(1.0, abs=1.1e-3)
    assert expected <= frame.stats.counters["density_samples"] <= expected + 3

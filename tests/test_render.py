"""Compositing order, overlapping volumes, stereo, determinism and exact work counters."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import DOWN, axis_camera, chords, homogeneous_volume, render, scene_of
from volren.camera import Camera, StereoRig
from volren.scene import DirectionalLight, Scene, Volume


def emitter(sigma, colour, z):
    return homogeneous_volume(sigma, emission=colour, scale=0.5, translate=(0.0, 0.0, z))


def emission_absorption(segments):
    """Front-to-back closed form of piecewise-homogeneous emission-absorption segments [(sigma, e, length), ...]."""
    out, trans = np.zeros(3), 1.0
    for sigma, e, length in segments:
        out += trans * np.asarray(e) * ((1 - np.exp(-sigma * length)) / sigma if sigma else length)
        trans *= np.exp(-sigma * length)
    return out


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_two_volumes_composite_front_to_back_from_both_sides(method, side):
    red, blue = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    scene = scene_of(emitter(1.2, red, 0.8), emitter(0.7, blue, -0.8))
    cam = axis_camera((0.0, 0.0, 3.0 * side))
    got = render(method, scene, [cam], samples=64, min_transmittance=0).images[0][16, 16, :3]
    near, far = ((1.2, red, 1.0), (0.7, blue, 1.0))[:: int(side)]
    np.testing.assert_allclose(got, emission_absorption([near, far]), rtol=2e-4)


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_reference_sums_overlapping_volumes(side):
    """Boxes z in [-1, 1] (red, sigma 1) and [0, 2] (blue, sigma 2) overlap on [0, 1]: extinction and emission add."""
    a = homogeneous_volume(1.0, emission=(1.0, 0.0, 0.0))
    b = homogeneous_volume(2.0, emission=(0.0, 0.0, 1.0), translate=(0.0, 0.0, 1.0))
    cam = axis_camera((0.0, 0.0, 4.0 * side))
    got = render("reference", scene_of(a, b), [cam], samples=256, min_transmittance=0).images[0][16, 16, :3]
    segments = [(2.0, (0, 0, 1), 1.0), (3.0, (1, 0, 1), 1.0), (1.0, (1, 0, 0), 1.0)]
    np.testing.assert_allclose(got, emission_absorption(segments[:: int(side)]), rtol=2e-4)


def test_reference_shadows_between_volumes():
    """An absorbing slab above a scattering cube darkens it by exp(-sigma_slab * thickness) in the reference."""
    lit = homogeneous_volume(1.0, albedo=0.9)
    blocker = Volume(np.ones((4, 4, 4), np.float32), np.diag([2.0, 0.25, 2.0, 1.0]) + np.diag([0, 0, 0, 0]),
                     density_scale=2.0, albedo=0.0)
    blocker = Volume(blocker.density, blocker.to_world @ _translate(0, 8.0, 0), density_scale=2.0, albedo=0.0)
    cam = axis_camera((0.0, 0.0, 3.0))
    alone = render("reference", scene_of(lit, lights=[DOWN]), [cam], samples=128, light_samples=256).images[0]
    shadowed = render("reference", scene_of(lit, blocker, lights=[DOWN]), [cam], samples=128,
                      light_samples=256).images[0]
    ratio = shadowed[16, 16, 0] / alone[16, 16, 0]
    assert ratio == pytest.approx(np.exp(-2.0 * 0.5), rel=2e-3)


def _translate(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def mirror_scene() -> Scene:
    """A scene symmetric under x -> -x: a ball off-centre in y, lit from a direction in the y-z plane."""
    z, y, x = np.mgrid[-1:1:48j, -1:1:48j, -1:1:48j]
    ball = np.clip(1.2 - np.sqrt(x**2 + (y - 0.2) ** 2 + z**2) * 1.6, 0, 1).astype(np.float32)
    return Scene((Volume(ball, density_scale=6.0, albedo=0.8, g=0.3),),
                 (DirectionalLight((0.0, -1.0, -0.5), (2.0, 2.0, 2.0)),))


def test_stereo_eyes_differ_and_mirror(method):
    cams = StereoRig(Camera(position=(0.0, 0.3, 2.6), width=48, height=32), ipd=0.2).eyes()
    left, right = render(method, mirror_scene(), cams, samples=96, light_samples=64).images
    assert np.abs(left - right).max() > 0.01
    np.testing.assert_allclose(left[:, ::-1], right, atol=2e-4 * left.max())


def test_same_seed_same_image_bit_for_bit():
    cam = [Camera(position=(0.5, 0.3, 2.6), width=40, height=24)]
    scene = mirror_scene()
    a = render("dssrm", scene, cam, samples=48, jitter=True, seed=7).images[0]
    b = render("dssrm", scene, cam, samples=48, jitter=True, seed=7).images[0]
    c = render("dssrm", scene, cam, samples=48, jitter=True, seed=8).images[0]
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_counters_counted_by_hand():
    """One pixel through the centre of a homogeneous cube, light straight down, V = 100, L = 8, 4^3 light grid.

    View: chord 2 of diagonal 2 sqrt 3 -> ceil(100 / sqrt 3) = 58 samples, each lit once from the light map.
    Light map: nodes at y = -1, -1/3, 1/3, 1 lie 2, 4/3, 2/3, 0 below the top (the top ones marched from just inside
    it); steps of 2 sqrt 3 / 8 = 0.433 give 5 + 4 + 2 + 1 = 12 samples per column, times 16 columns = 192.
    """
    scene = scene_of(homogeneous_volume(0.5, albedo=0.5), lights=[DOWN])
    frame = render("dssrm", scene, [axis_camera(size=(1, 1))], samples=100, light_samples=8, light_grid=4,
                   min_transmittance=0)
    assert frame.stats.counters == {"density_samples": 58, "light_samples": 192, "lightmap_lookups": 58, "rays": 1,
                                    "shared_samples": 0, "interleaved_samples": 0,
                                    "shadow_rays": 0, "shadow_voxels": 0, "skipped_steps": 0,
                                    "light_skipped": 0,  # a homogeneous cube: no empty cell to skip
                                    # the tiled OIT: one tile ray (one BVH query, one box test), one box per pixel
                                    "box_tests": 1, "tile_box_tests": 1, "bvh_queries": 1, "ao_bvh_queries": 0,
                                    "joint_rays": 0, "jumped_steps": 0, "idle_runs": 0}


def test_counters_match_host_count_per_pixel(method):
    """density_samples = sum over pixels of ceil(chord V / diagonal) (the reference, one volume: same rule)."""
    cam = axis_camera((1.1, 0.7, 2.4), size=(37, 29))
    frame = render(method, scene_of(homogeneous_volume(0.1)), [cam], samples=50, min_transmittance=0)
    _, chord = chords(cam)
    hit = chord > 0
    steps = np.maximum(np.ceil(chord * 50 / (2 * np.sqrt(3)) - 1e-6), 1)
    assert frame.stats.counters["rays"] == int(hit.sum())
    assert frame.stats.counters["density_samples"] == int(steps[hit].sum())

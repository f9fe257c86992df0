"""VPT against closed forms for what issue 19 found missing: emission (items 1), the environment counted once (item 2,
the furnace at the default settings) and opaque surfaces shadowed by the volumes (item 9)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import DEVICE, DOWN, axis_camera, homogeneous_volume, scene_of
from test_cli import assert_error, ok
from test_surface_shading import ALBEDO, COS, SIGMA, UNDER, E, floor_scene, shadowed_floor, slab
from volren.camera import Camera
from volren.render import VPT, Reference, ReferenceConfig, VPTConfig
from volren.scene import Environment, Scene, Volume
from volren.transfer import ControlPoint, TransferFunction

EMITTER = axis_camera(position=(0.0, 0.0, 4.0), size=(9, 9), fov_y=20.0)
"""the centre pixel's ray crosses the box [-1, 1]^3 along z: chord 2 m"""
SIGMA_E, EMISSION = 2.0, 1.0
EMISSION_CLOSED_FORM = EMISSION / SIGMA_E * (1.0 - np.exp(-2.0 * SIGMA_E))
"""L = integral_0^2 e^(-sigma t) E dt = (E / sigma)(1 - e^-4) = 0.4908, albedo 0, nothing lit"""


def emitting_box(albedo: float = 0.0, emission=EMISSION) -> Scene:
    return scene_of(homogeneous_volume(SIGMA_E, albedo=albedo, emission=emission))


def emission_tf(tmp_path) -> str:
    """The same medium as a transfer function with an emission column (and surface-like particles, which must not
    matter at albedo 0), written and read back as JSON."""
    point = ControlPoint(1.0, SIGMA_E, (0.0, 0.0, 0.0), 0.5, (EMISSION,) * 3)
    tf = TransferFunction((ControlPoint(0.0, 0.0, (0.0, 0.0, 0.0), 0.5), point), "emitter")
    path = tmp_path / "emitter.json"
    path.write_text(tf.to_json())
    assert TransferFunction.from_json(path.read_text()).points[1].emission == (EMISSION,) * 3
    return str(path)


@pytest.mark.parametrize("shading", ["coexist", "er"])
@pytest.mark.parametrize("source", ["volume", "tf"])
def test_emission_matches_the_closed_form(tmp_path, shading, source):
    """Uniform box, sigma_t 2, albedo 0, emission 1, no light or environment: the centre pixel is 0.4908 (VPT gave 0
    before). Each path's estimate is E / sigma_t = 0.5 when it collides, so its standard deviation is
    0.5 sqrt(a (1 - a)), a = 1 - e^-4; 5 standard errors at 1024 paths is 0.011 (2%)."""
    transfer = emission_tf(tmp_path) if source == "tf" else None
    spp = 1024
    config = VPTConfig(spp=spp, shading=shading, transfer=transfer)
    image = VPT(config, device=DEVICE).render(emitting_box(), [EMITTER]).images[0]
    a = 1.0 - np.exp(-2.0 * SIGMA_E)
    err = 0.5 * np.sqrt(a * (1 - a) / spp)
    assert abs(image[4, 4, 0] - EMISSION_CLOSED_FORM) < 5 * err
    assert abs(image[4, 4, 3] - a) < 5 * err / 0.5


def test_emission_with_scattering_matches_the_reference():
    """Albedo 0.6, coloured emission, a light from above, one scattering: emission and single scattering add as in
    the reference (which models exactly these), per channel within 2% over the image."""
    scene = scene_of(homogeneous_volume(SIGMA_E, albedo=0.6, g=0.3, emission=(1.0, 0.5, 0.2)), lights=[DOWN])
    cam = Camera(position=(0.0, 0.5, 3.5), width=24, height=16)
    ref = Reference(ReferenceConfig(samples=128, light_samples=128), device=DEVICE).render(scene, [cam]).images[0]
    image = VPT(VPTConfig(spp=128, max_bounces=1), device=DEVICE).render(scene, [cam]).images[0]
    np.testing.assert_allclose(image.mean(axis=(0, 1)), ref.mean(axis=(0, 1)), rtol=0.02)
    # the test's power: emission is a large share of the colour
    dark = VPT(VPTConfig(spp=16, max_bounces=1), device=DEVICE).render(
        scene_of(homogeneous_volume(SIGMA_E, albedo=0.6, g=0.3), lights=[DOWN]), [cam]).images[0]
    assert ref[..., 0].mean() > 1.3 * dark[..., 0].mean()


def furnace_ratio(vol: Volume) -> float:
    """Colour / alpha over the pixels that see ``vol`` in a constant environment of radiance 1 (no lights), default
    VPT settings with 64 spp and 64 bounces, 24x16."""
    scene = Scene((vol,), lights=(), environment=Environment((1.0, 1.0, 1.0)))
    cam = Camera(position=(0.0, 0.3, 3.2), width=24, height=16)
    image = VPT(VPTConfig(spp=64, max_bounces=64), device=DEVICE).render(scene, [cam]).images[0]
    seen = image[..., 3] > 0.5
    assert seen.sum() > 40
    return float(image[..., 0][seen].sum() / image[..., 3][seen].sum())


def test_emitting_furnace():
    """Albedo 0.5, sigma_t 2, emission 1 in a constant environment of radiance L = E / (sigma_t (1 - albedo)) = 1:
    the equilibrium of the transport equation (E + sigma_s L = sigma_t L), so every pixel's colour / alpha is 1 with
    enough bounces (0.5^64 left). Emission at later vertices must carry the throughput of the scatterings before it
    but not its own albedo (either slip: 0.75-0.83)."""
    vol = homogeneous_volume(SIGMA_E, n=16, albedo=0.5, g=0.3, emission=EMISSION)
    assert furnace_ratio(vol) == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("denoise", ["ours", "svgf", "wrls"])
def test_denoisers_keep_the_emission_of_an_albedo_0_medium(denoise):
    """The first collision's emission is its own denoiser part (not divided by the albedo, 0 here): after 4 frames at
    4 spp the denoised box (pixels whose ray crosses it far from the silhouette) matches the closed form within 3%
    (without the part: 0)."""
    cam = axis_camera(position=(0.0, 0.0, 4.0), size=(15, 15), fov_y=20.0)
    r = VPT(VPTConfig(spp=4, denoise=denoise), device=DEVICE)
    for frame in range(4):
        image = r.render(emitting_box(), [cam], frame).images[0]
    inner = image[5:10, 5:10]
    expected = EMISSION / SIGMA_E * (1.0 - np.exp(-2.0 * SIGMA_E))
    np.testing.assert_allclose(inner[..., 0].mean(), expected, rtol=0.03)


def test_furnace_at_the_default_settings():
    """Albedo 1, constant environment 1, no lights, the default config (but enough bounces): colour / alpha = 1. The
    environment is sampled as a light only; the old default also added its mean as an ambient (3.43). 64 bounces
    leave < 1e-4 of the energy in this optically thin cube (optical radius 1.5: each scattering escapes with
    probability > 0.2); noise at 64 spp on 24x16 pixels: ~0.3%."""
    vol = homogeneous_volume(1.5, n=16, albedo=1.0, g=0.3)
    assert furnace_ratio(vol) == pytest.approx(1.0, abs=0.02)


def test_floor_under_a_slab_is_shadowed_by_the_volume():
    """test_surface_shading's slab over a floor, for VPT: L = albedo / pi * E * cos * exp(-sigma 0.5 / cos) (unshadowed:
    2.2x that, what VPT drew before). Each pixel's transmittance is the mean of spp ratio-tracked estimates; the mean
    over the shadowed floor within 4 standard errors (from the pixels' spread), every pixel within 6 of its own."""
    spp = 16
    image = VPT(VPTConfig(spp=spp), device=DEVICE).render(floor_scene(slab(0.5, 1.0)), [UNDER]).images[0]
    mask = shadowed_floor(UNDER, 1.0)
    values = image[mask][:, 0]
    expected = ALBEDO / np.pi * E * COS * np.exp(-SIGMA * 0.5 / COS)
    assert abs(values.mean() - expected) < 4 * values.std() / np.sqrt(mask.sum())
    # the estimates are Bernoulli here (majorant = sigma): per pixel sd = sqrt(T (1 - T) / spp) of the unshadowed
    t = np.exp(-SIGMA * 0.5 / COS)
    assert np.abs(values - expected).max() < 6 * np.sqrt(t * (1 - t) / spp) * expected / t
    # the same renderer draws the floor unshadowed with the slab below it
    lit = VPT(VPTConfig(spp=spp), device=DEVICE).render(floor_scene(slab(-1.0, -0.5)), [UNDER]).images[0]
    np.testing.assert_allclose(lit[mask][:, 0], expected / t, rtol=1e-5)
    # the denoiser composites over the shadowed surface too
    den = VPT(VPTConfig(spp=spp, denoise="ours"), device=DEVICE).render(floor_scene(slab(0.5, 1.0)), [UNDER])
    assert abs(den.images[0][mask][:, 0].mean() - expected) < 4 * values.std() / np.sqrt(mask.sum())


def test_cli_vpt_emission_and_ambient(capfd, tmp_path):
    """``--emission`` now lights VPT (it was accepted and ignored), ``--vpt-ambient`` adds §6.1's ambient on top of
    the same paths (the ambient draws no random numbers), and other methods refuse the flag."""
    base = ["render", "--method", "vpt", "--scene", "cloud", "--resolution", "64", "--width", "16", "--height", "12",
            "--spp", "4", "--views", "mono", "--save-linear", "--device", "cpu"]
    for name, extra in (("plain", []), ("glow", ["--emission", "5"]), ("ambient", ["--vpt-ambient"])):
        ok(capfd, *base, *extra, "--out", tmp_path / name)
    plain, glow, ambient = (np.load(tmp_path / name / "view0.npy")[..., :3] for name in ("plain", "glow", "ambient"))
    assert glow.sum() > 1.5 * plain.sum()
    assert (ambient >= plain - 1e-6).all() and ambient.sum() > 1.05 * plain.sum()
    assert_error(capfd, ["render", "--method", "dssrm", "--scene", "cloud", "--vpt-ambient", "--device", "cpu",
                         "--out", tmp_path / "o"], "does not take --vpt-ambient")
    # a transfer function replaces the material: the material flags would do nothing beside it
    for flag, value in (("--emission", "5"), ("--albedo", "0.5"), ("--density-scale", "3")):
        assert_error(capfd, [*base, "--tf", "smoke", flag, value, "--out", tmp_path / "o"],
                     f"--tf gives the extinction, albedo and emission: {flag} would do nothing")
    assert not (tmp_path / "o").exists()


def test_emission_needs_extinction_and_bad_emission_is_refused(tmp_path):
    """The tracker finds emitters only where it collides: emission at a control point without extinction, and a
    volume that emits with density_scale 0, are refused (one-line errors); negative emission too."""
    from volren.errors import VolrenError

    with pytest.raises(VolrenError, match="emission needs extinction > 0"):
        TransferFunction((ControlPoint(0.0, 0.0, emission=(1.0, 0.0, 0.0)), ControlPoint(1.0, 2.0)))
    with pytest.raises(VolrenError, match="emission must be 3 values >= 0"):
        TransferFunction((ControlPoint(0.0, 1.0, emission=(-1.0, 0.0, 0.0)),))
    with pytest.raises(VolrenError, match="density_scale 0"):
        VPT(VPTConfig(spp=1), device=DEVICE).render(scene_of(homogeneous_volume(0.0, emission=1.0)), [EMITTER])
    # files without "emission" stay valid, and a function without emission writes none
    doc = '{"points": [{"position": 0, "extinction": 0}, {"position": 1, "extinction": 3, "albedo": [1, 1, 1]}]}'
    tf = TransferFunction.from_json(doc)
    assert tf.points[1].emission == (0.0, 0.0, 0.0) and "emission" not in tf.to_json()
    assert tf.table().shape == (1024, 8) and not tf.table()[:, 5:].any()

"""DSSRM against the reference on the built-in scenes (paper 000 §4.1 methodology, at CPU test sizes).

Measured on 64^3 scenes, 96x64 views (PSNR of DSSRM:256:256 with a full-resolution light grid against the
reference at 256:256): smoke 68.7, cloud 60.4, phantom 61.0, multi 73.4 dB (63.0, 58.7, 57.4, 70.4 with the
voxel-centre light map before issue 19 item 3). At matched dense steps the methods differ only in the light map:
optical depth interpolated trilinearly between light-map nodes instead of marched from each sample, a bias that no
step count removes. The 45 dB floor sits 15 dB under the worst measured scene, and far above what a wrong light
direction, phase sign or compositing order gives (< 30 dB).
"""

from __future__ import annotations

import itertools
from functools import cache

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera
from volren.data import builtin_scene
from volren.metrics import psnr, ssim
from volren.render import DSSRM, DSSRMConfig, Reference, ReferenceConfig

VIEWS = [Camera(position=(0.0, 0.4, 3.2), width=96, height=64)]
SCENES = ["smoke", "cloud", "phantom", "multi"]


@cache
def scene(name: str):
    return builtin_scene(name, 64, count=4)


@cache
def reference(name: str, samples: int = 256) -> np.ndarray:
    return Reference(ReferenceConfig(samples=samples, light_samples=samples), device=DEVICE).render(
        scene(name), VIEWS).images[0]


def dssrm(name: str, view_samples: int, light_samples: int) -> np.ndarray:
    config = DSSRMConfig(samples=view_samples, light_samples=light_samples, light_grid=64)
    return DSSRM(config, device=DEVICE).render(scene(name), VIEWS).images[0]


@pytest.mark.parametrize("name", SCENES)
def test_dssrm_matches_reference_at_dense_settings(name):
    ref = reference(name)
    assert ref[..., 3].max() > 0.5, "the scene must be visible for the comparison to mean anything"
    img = dssrm(name, 256, 256)
    assert psnr(ref, img) > 45.0
    assert ssim(ref, img) > 0.999


def test_wrong_light_direction_fails_the_floor():
    """The floor can fail: the same scene lit from below instead of above drops far under it."""
    from dataclasses import replace

    from volren.scene import DirectionalLight

    s = scene("cloud")
    flipped = replace(s, lights=(DirectionalLight((0.5, 1.0, 0.35), s.lights[0].irradiance),))
    img = DSSRM(DSSRMConfig(samples=256, light_samples=256, light_grid=64), device=DEVICE).render(flipped, VIEWS)
    assert psnr(reference("cloud"), img.images[0]) < 35.0


SWEEPS = {
    "V and L": [(16, 8), (32, 16), (64, 32), (128, 64)],
    "V alone": [(16, 256), (32, 256), (64, 256), (128, 256)],
    "L alone": [(256, 4), (256, 8), (256, 16), (256, 32), (256, 64)],
}


@pytest.mark.parametrize("sweep", SWEEPS)
@pytest.mark.parametrize("name", ["cloud", "phantom"])
def test_dssrm_quality_rises_with_v_and_l(name, sweep):
    """Coarse to fine, up to where the light-map bias (above) takes over; measured steps are 3.5 to 15 dB apart."""
    ref = reference(name, 512)
    scores = [psnr(ref, dssrm(name, v, lv)) for v, lv in SWEEPS[sweep]]
    assert all(b > a + 1.0 for a, b in itertools.pairwise(scores)), scores

"""CACRM's coupled march, faster (issue 24, first item): idle steps and runs of them over empty space.

Most of a coupled pair's steps cross empty space together (smoke 128^3, 480x270 stereo, defaults: 11.3 M eye steps
skipped for 0.62 M density fetches). The texel kernel walks a run of steps where every live eye sits in an empty skip
cell in `idle_run` (VSA's ramp over a constant product, unit steps jumped in one go) instead of its full loop. What
that must not change: the lattice and the counts (skipping on and off give the same image and fetched + skipped =
fetched without skipping: `test_skipping`), and each eye's march (below; the images are bit-identical to the
kernel's before the change, checked on the smoke, cloud and phantom at 128^3, 480x270 and 960x540 stereo).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.metrics import psnr
from volren.render import CACRM, CMSRM, CACRMConfig, CMSRMConfig
from volren.scene import Scene

VIEWS = make_views(Camera(position=(0.3, 0.5, 2.4), width=48, height=32), "stereo")
BASE = {"samples": 128, "light_samples": 16, "light_grid": 16, "hybrid": False, "adaptive_lod": False,
        "interleave": False}


def test_coupled_pair_equals_each_eye_alone_with_skipping_and_jumps():
    """Uniform steps, no voxel sharing: one loop over the eyes marches each eye as it marches alone (eye 1 through
    the same code as eye 0), with the idle runs on (skipped steps differ: a pair's tiles are culled for both eyes);
    and the pair's image is CMSRM's within the lattices' difference (texel-anchored against CMSRM's: 62.9 dB)."""
    scene = builtin_scene("cloud", 64)
    config = CACRMConfig(**BASE, vsa=False, share_voxels=False)
    coupled = CACRM(config, DEVICE).render(scene, VIEWS)
    alone = CACRM(dataclasses.replace(config, coupling=False), DEVICE).render(scene, VIEWS)
    for a, b in zip(coupled.images, alone.images, strict=True):
        np.testing.assert_array_equal(a, b)
    for key in ("density_samples", "lightmap_lookups"):
        assert coupled.stats.counters[key] == alone.stats.counters[key], key
    assert coupled.stats.counters["skipped_steps"] > 5 * coupled.stats.counters["density_samples"]
    cmsrm = CMSRM(CMSRMConfig(**{k: v for k, v in BASE.items() if k != "interleave"}), DEVICE).render(scene, VIEWS)
    worst = min(psnr(b, a) for a, b in zip(coupled.images, cmsrm.images, strict=True))
    assert worst > 50.0, worst


def half_smoke() -> Scene:
    """The smoke with its front half (towards +z, the camera) emptied: long empty runs in front of the medium that
    cross t = t_max / k_a, where VSA's ramp starts to lengthen the steps."""
    scene = builtin_scene("smoke", 64)
    density = scene.volumes[0].density.copy()
    density[density.shape[0] // 2:] = 0.0
    return dataclasses.replace(scene, volumes=(dataclasses.replace(scene.volumes[0], density=density),))


def slabs() -> Scene:
    """A dense slab, empty space, a thin slab: runs behind a medium (T < 1, f_A large), whose first sample in the
    thin slab is dense at once and smooth enough that VSA's product (not the ramp or 1) decides the step there, so
    that rho', taken from the run's last distance, matters."""
    scene = builtin_scene("smoke", 64)
    density = np.zeros_like(scene.volumes[0].density)
    density[40:52] = 0.6
    density[8:20] = 0.01
    return dataclasses.replace(scene, volumes=(dataclasses.replace(scene.volumes[0], density=density),))


@pytest.mark.parametrize("name", ["half-smoke", "slabs"])
def test_idle_runs_walk_the_lattice_of_the_steps(name):
    """With the fitted VSA, the idle runs (unit steps jumped, ramp steps walked) give the image and counts of the
    loop that fetches every step: the same image with skipping on and off, fetched + skipped = fetched without
    skipping. The half-emptied smoke's runs cross the ramp's start; the slabs put runs between media, where VSA's
    product and previous distance matter."""
    scene = half_smoke() if name == "half-smoke" else slabs()
    views = make_views(Camera(position=(0.2, 0.4, 2.2), width=48, height=32), "stereo")
    config = CACRMConfig(**BASE)
    on = CACRM(config, DEVICE).render(scene, views)
    off = CACRM(dataclasses.replace(config, skip_empty=False), DEVICE).render(scene, views)
    for a, b in zip(on.images, off.images, strict=True):
        np.testing.assert_array_equal(a, b)
    c_on, c_off = on.stats.counters, off.stats.counters
    assert c_on["density_samples"] + c_on["skipped_steps"] == c_off["density_samples"]
    assert c_on["skipped_steps"] > 0.5 * c_on["density_samples"], (c_on, c_off)  # slabs: 0.68

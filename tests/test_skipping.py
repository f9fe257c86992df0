"""Empty-space skipping in the light-map pass (issue 15 item 4, `volren.kernels.common.optical_depth_skipping`): the
light map is the same bit for bit with skipping on and off, in the volume's own march and across volumes (GI's
cross-volume march through the BVH), and the fetches plus the skipped steps are the fetches without skipping."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.render import Reference, ReferenceConfig
from volren.render.frame import PassClock
from volren.render.lightmap import compute_light_map
from volren.render.marching.cacrm import CACRM, CACRMConfig
from volren.upload import upload_scene


@pytest.fixture(scope="module")
def multi():
    return builtin_scene("multi", 64, count=4)


def light_map(scene, skip: bool, cross_volume: bool) -> tuple[np.ndarray, dict[str, int]]:
    ds = upload_scene(scene, DEVICE, light_grid=16)
    ds.skip_empty = skip
    clock = PassClock(DEVICE)
    compute_light_map(ds, 48, clock, cross_volume=cross_volume)
    return ds.lightmap.numpy(), clock.counter_values()


@pytest.mark.parametrize("cross_volume", [False, True], ids=["own-volume", "cross-volume"])
def test_light_map_skipping_is_bit_identical_with_exact_counters(multi, cross_volume: bool) -> None:
    """Four instances, 16^3 light grids, L = 48: same light map; skipped + fetched = fetched without skipping. The
    skipped share (measured below) shows the skip grid is used; its floor is well under the measured value."""
    on, c_on = light_map(multi, True, cross_volume)
    off, c_off = light_map(multi, False, cross_volume)
    assert len(multi.lights) > 0 and 0.0 < np.exp(-on).min() < 1.0  # lit and partly shadowed (it holds tau)
    np.testing.assert_array_equal(on, off)
    assert c_off["light_skipped"] == 0
    assert c_on["light_samples"] + c_on["light_skipped"] == c_off["light_samples"]
    assert c_on["light_skipped"] > 0.3 * c_off["light_samples"], (c_on, c_off)


def test_one_launch_for_every_volume_matches_each_volume_alone(multi) -> None:
    """The pass launches once over every volume's light-grid rows (``row_start``): with light grids of different
    shapes (boxes of different aspect), each volume's part of the light map equals, bit for bit, the light map of
    that volume uploaded alone (own-volume march: nothing else casts a shadow)."""
    rng = np.random.default_rng(4)
    shapes = ((6, 14, 22), (20, 9, 12), (11, 11, 5))
    volumes = tuple(dataclasses.replace(multi.volumes[0], density=rng.uniform(0, 1, s).astype(np.float32))
                    for s in shapes)
    together, _ = light_map(dataclasses.replace(multi, volumes=volumes), True, False)
    ds = upload_scene(dataclasses.replace(multi, volumes=volumes), DEVICE, light_grid=16)
    assert len(set(ds.light_res)) == 3
    alone = np.concatenate([light_map(dataclasses.replace(multi, volumes=(v,)), True, False)[0] for v in volumes])
    np.testing.assert_array_equal(together, alone)


@pytest.mark.parametrize("vsa", [False, True], ids=["uniform", "vsa"])
def test_cacrm_coupled_march_skipping_keeps_the_image_with_exact_counters(multi, vsa: bool) -> None:
    """CACRM's coupled march (both eyes per texel, shared cells) skips empty cells per eye: the same stereo images
    with skipping on and off, uniform or VSA steps (a skipped step reads the 0 a fetch would read, so VSA's proposals
    are unchanged; VSA's runs of empty steps are jumped in closed form, `ramp_jump`, which moves the lattice by float
    rounding: images within 1e-6 there), and the steps fetched plus skipped are the fetches without skipping."""
    views = make_views(Camera(position=(0.3, 0.5, 2.2), width=64, height=40), "stereo")
    # hybrid off: every pixel through the cube map (hybrid marches some pixels directly, DSSRM's march)
    config = CACRMConfig(samples=160, light_samples=16, light_grid=16, vsa=vsa, interleave=False, hybrid=False)
    on = CACRM(config, DEVICE).render(multi, views)
    off = CACRM(dataclasses.replace(config, skip_empty=False), DEVICE).render(multi, views)
    for a, b in zip(on.images, off.images, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 if vsa else 0)
    c_on, c_off = on.stats.counters, off.stats.counters
    assert c_off["skipped_steps"] == 0 and c_off["shared_samples"] > 0  # the coupled kernel ran
    assert c_on["density_samples"] + c_on["skipped_steps"] == c_off["density_samples"]
    assert c_on["skipped_steps"] > 10 * c_on["density_samples"], (c_on, c_off)  # measured 12.9x (uniform), 13.1x
    assert c_on["lightmap_lookups"] == c_off["lightmap_lookups"]


def test_reference_shadow_rays_skip_with_the_same_image(multi) -> None:
    """The reference's dense shadow marches (L per lit sample, through every volume) skip empty cells: the same
    image and depth with skipping on and off, and fetched + skipped = fetched without skipping."""
    view = [Camera(position=(0.3, 0.5, 2.2), width=32, height=20)]
    config = ReferenceConfig(samples=64, light_samples=64)
    on = Reference(config, DEVICE).render(multi, view)
    off = Reference(dataclasses.replace(config, skip_empty=False), DEVICE).render(multi, view)
    np.testing.assert_array_equal(on.images[0], off.images[0])
    np.testing.assert_array_equal(on.depths[0], off.depths[0])
    c_on, c_off = on.stats.counters, off.stats.counters
    assert c_off["light_skipped"] == 0
    assert c_on["light_samples"] + c_on["light_skipped"] == c_off["light_samples"]
    assert c_on["light_skipped"] > c_on["light_samples"], (c_on, c_off)

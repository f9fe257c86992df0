"""The light-map cache (`volren.render.lightmap.LightMapCache`, on by default): the pass is skipped only while the
lights, volumes, light grid, L and GI on/off are those the map was computed with, and a reused map is the recomputed
one bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from volren.camera import Camera
from volren.data import builtin_scene
from volren.render import DSSRM, DSSRMConfig
from volren.render.gi.ambient import GIConfig
from volren.scene import DirectionalLight, Volume

CONFIG = DSSRMConfig(samples=48, light_samples=16, light_grid=8)
CAMERA = Camera(position=(0.0, 0.4, 3.2), width=32, height=24)


@pytest.fixture(scope="module")
def smoke():
    return builtin_scene("smoke", 64)


def fresh(scene, config=CONFIG) -> np.ndarray:
    """The image of a renderer that has never rendered: its light map computed for this frame."""
    return DSSRM(config, "cpu").render(scene, [CAMERA]).images[0]


def ran_light_map(frame) -> bool:
    return "light_map" in frame.stats.times_ms


def test_reuse_is_default_and_bit_identical_to_recomputing(smoke):
    assert DSSRMConfig().reuse_light_map
    cached = DSSRM(CONFIG, "cpu")
    first, second = (cached.render(smoke, [CAMERA], frame=i) for i in range(2))
    assert ran_light_map(first) and not ran_light_map(second)
    assert second.stats.counters["light_samples"] == 0 < first.stats.counters["light_samples"]
    every = DSSRM(dataclasses.replace(CONFIG, reuse_light_map=False), "cpu")
    recomputed = [every.render(smoke, [CAMERA], frame=i) for i in range(2)]
    assert ran_light_map(recomputed[1])
    assert np.array_equal(second.images[0], recomputed[1].images[0])
    assert np.array_equal(cached._device_scene.lightmap.numpy(), every._device_scene.lightmap.numpy())


def test_a_scene_changed_only_where_the_map_does_not_look_reuses_it(smoke):
    """A new scene object with the same volumes and equal lights (another background: `upload_lights`' path, the
    light-map storage shared) keeps the map."""
    r = DSSRM(CONFIG, "cpu")
    r.render(smoke, [CAMERA])
    again = r.render(dataclasses.replace(smoke, background=(0.3, 0.1, 0.1),
                                         lights=tuple(dataclasses.replace(li) for li in smoke.lights)), [CAMERA])
    assert not ran_light_map(again)


def test_a_moved_light_recomputes_the_map_and_moving_it_back_too(smoke):
    r = DSSRM(CONFIG, "cpu")
    stale = r.render(smoke, [CAMERA]).images[0]
    moved = dataclasses.replace(smoke, lights=(DirectionalLight(direction=(0.8, -0.2, -0.5), irradiance=(3, 3, 3)),))
    frame = r.render(moved, [CAMERA])
    assert ran_light_map(frame) and np.array_equal(frame.images[0], fresh(moved))
    assert not np.allclose(frame.images[0], stale, atol=1e-3)
    back = r.render(smoke, [CAMERA])  # the shared storage now holds the moved light's map
    assert ran_light_map(back) and np.array_equal(back.images[0], stale)


def test_changed_density_transform_or_light_grid_recomputes_the_map(smoke):
    r = DSSRM(CONFIG, "cpu")
    r.render(smoke, [CAMERA])
    vol = smoke.volumes[0]
    for changed in (Volume(vol.density * 0.5, vol.to_world, vol.density_scale, vol.albedo, vol.g),
                    Volume(vol.density, np.diag([1.0, 0.6, 1.0, 1.0]), vol.density_scale, vol.albedo, vol.g),
                    Volume(vol.density, vol.to_world, 3.0, vol.albedo, vol.g)):
        scene = dataclasses.replace(smoke, volumes=(changed,))
        frame = r.render(scene, [CAMERA])
        assert ran_light_map(frame) and np.array_equal(frame.images[0], fresh(scene))
    r.config = dataclasses.replace(CONFIG, light_grid=12)
    frame = r.render(scene, [CAMERA])
    assert ran_light_map(frame) and np.array_equal(frame.images[0], fresh(scene, r.config))


def test_changed_light_samples_or_gi_recomputes_the_map(smoke):
    r = DSSRM(CONFIG, "cpu")
    r.render(smoke, [CAMERA])
    r.config = dataclasses.replace(CONFIG, light_samples=40)
    frame = r.render(smoke, [CAMERA])
    assert ran_light_map(frame) and np.array_equal(frame.images[0], fresh(smoke, r.config))
    # GI on marches the light map across volumes (`compute_light_map`'s cross_volume)
    r.config = dataclasses.replace(r.config, gi=GIConfig(method="sresir"))
    assert ran_light_map(r.render(smoke, [CAMERA]))


def test_a_frame_recomputed_without_reuse_is_remembered(smoke):
    """A frame with the cache off still records what it filled the storage with: turning the cache back on with the
    earlier inputs recomputes, as the storage holds the later map."""
    r = DSSRM(CONFIG, "cpu")
    r.render(smoke, [CAMERA])
    r.config = dataclasses.replace(CONFIG, light_samples=40, reuse_light_map=False)
    r.render(smoke, [CAMERA])
    r.config = CONFIG
    frame = r.render(smoke, [CAMERA])
    assert ran_light_map(frame) and np.array_equal(frame.images[0], fresh(smoke))

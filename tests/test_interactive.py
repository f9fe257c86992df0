"""Issue 15 item 4: empty-space skipping in the light-map march and the quality presets."""

from __future__ import annotations

import dataclasses
import itertools
from math import inf

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera
from volren.data import builtin_scene
from volren.errors import VolrenError
from volren.metrics import psnr
from volren.plan import render_parser
from volren.plan.renderer import renderer_from_args
from volren.presets import QUALITIES, QUALITY_PRESETS, quality_config
from volren.render import CMSRM, DSSRM, CMSRMConfig, DSSRMConfig, Reference, ReferenceConfig
from volren.upload import skip_grid

VIEW = Camera(position=(0.0, 0.4, 3.2), width=480, height=270)
"""The interactive goal's view: 480x270 of the default scene (smoke 64^3) from the CLI's default eye."""


def trilinear(density: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Host trilinear samples of a [z, y, x] grid at local points p (N, 3), clamped as `sample_grid`."""
    res = np.array(density.shape[::-1])
    f = np.clip((p + 1) * 0.5 * res - 0.5, 0, res - 1)
    c = np.minimum(f.astype(int), res - 2)
    a = f - c
    out = np.zeros(len(p))
    for dx, dy, dz in itertools.product((0, 1), repeat=3):
        w = np.where(dx, a[:, 0], 1 - a[:, 0]) * np.where(dy, a[:, 1], 1 - a[:, 1]) * np.where(dz, a[:, 2], 1 - a[:, 2])
        out += w * density[c[:, 2] + dz, c[:, 1] + dy, c[:, 0] + dx]
    return out


def test_skip_grid_bounds_every_sample_of_its_empty_cubes():
    """Every trilinear sample in the footprint of an empty cell's cube (radius r = -value), widened by half a voxel,
    is zero; a cell is empty exactly when its dilated block max is 0. Odd sizes leave partial cells at the ends."""
    rng = np.random.default_rng(3)
    density = np.zeros((21, 18, 27), np.float32)
    density[rng.integers(0, 21, 6), rng.integers(0, 18, 6), rng.integers(0, 27, 6)] = rng.uniform(0.1, 1, 6)
    density[14:17, 3:6, 20:23] = 0.5
    cell = 4
    grid, _ = skip_grid(density, cell)
    assert grid.shape == (6, 5, 7)
    res = np.array(density.shape[::-1])
    empty = 0
    for z, y, x in zip(*np.nonzero(grid <= 0), strict=True):
        r = -grid[z, y, x]
        assert r == int(r)
        lo = (np.array([x, y, z]) - r) * cell - 0.5
        hi = (np.array([x, y, z]) + r + 1) * cell + 0.5
        q = rng.uniform(np.maximum(lo, 0), np.minimum(hi, res), (200, 3))  # voxel-footprint coordinates
        assert trilinear(density, q / res * 2 - 1).max() == 0.0, (x, y, z, r)
        empty += 1
    assert 0 < empty < grid.size
    # the radius is the largest: one more and the cube would take in an occupied cell
    occupied = np.argwhere(grid > 0)
    for z, y, x in zip(*np.nonzero(grid <= 0), strict=True):
        assert np.abs(occupied - [z, y, x]).max(axis=1).min() == -grid[z, y, x] + 1


@pytest.fixture(scope="module")
def smoke():
    return builtin_scene("smoke", 64)


def test_skip_grid_is_the_max_pyramid_where_occupied(smoke):
    """On the smoke 64^3 the occupied cells hold level 2 of the volume's conservative max-density pyramid."""
    vol = smoke.volumes[0]
    grid, _ = skip_grid(vol.density, 4)
    np.testing.assert_array_equal(np.where(grid > 0, grid, 0), vol.max_pyramid[2])
    assert (grid <= 0).mean() > 0.5  # the plume fills less than half the box


def test_skipping_on_the_smoke_samples_12x_fewer_and_keeps_the_image_bit_identical(smoke):
    """The interactive goal's frame (DSSRM:160:48): every step is sampled or skipped (exact counters), 12.3x fewer
    density samples (measured 4,342,977 -> 354,282 on the CPU), and not one pixel or depth changes."""
    config = quality_config("dssrm", "interactive")
    off = DSSRM(quality_config("dssrm", "interactive", skip_empty=False), DEVICE).render(smoke, [VIEW])
    on = DSSRM(config, DEVICE).render(smoke, [VIEW])
    np.testing.assert_array_equal(on.images[0], off.images[0])
    np.testing.assert_array_equal(on.depths[0], off.depths[0])
    c_on, c_off = on.stats.counters, off.stats.counters
    assert c_off["skipped_steps"] == 0
    assert c_on["density_samples"] + c_on["skipped_steps"] == c_off["density_samples"]
    assert c_off["density_samples"] >= 12 * c_on["density_samples"]
    assert c_on["lightmap_lookups"] == c_off["lightmap_lookups"]  # the same samples were lit


@pytest.mark.parametrize(
    ("method", "config"),
    [
        (DSSRM, DSSRMConfig(samples=200, light_grid=16, jitter=True, seed=5)),  # random offsets: off the midpoints
        (CMSRM, CMSRMConfig(samples=200, light_grid=16, hybrid=False)),  # texel rays
        (CMSRM, CMSRMConfig(samples=200, light_grid=16, hybrid=True)),  # pixels marched directly
    ],
    ids=["dssrm-jitter", "cmsrm-texels", "cmsrm-direct"],
)
def test_skipping_leaves_every_light_map_march_unchanged(method, config):
    """Stereo views of the multi-instance scene at 64x40, inside and outside boxes: same images, and the steps
    sampled plus skipped are the steps of the march without skipping."""
    scene = builtin_scene("multi", 64, count=4)
    views = [Camera(position=(0.3, 0.5, 2.2), width=64, height=40), Camera(position=(0.0, 0.1, 0.2), width=64,
                                                                            height=40)]
    on = method(config, DEVICE).render(scene, views)
    off = method(dataclasses.replace(config, skip_empty=False), DEVICE).render(scene, views)
    for a, b in zip(on.images, off.images, strict=True):
        np.testing.assert_array_equal(a, b)
    c_on, c_off = on.stats.counters, off.stats.counters
    assert c_on["density_samples"] + c_on["skipped_steps"] == c_off["density_samples"]
    assert c_on["skipped_steps"] > c_on["density_samples"]


def test_presets_are_frozen_and_cover_every_method():
    from volren.render import METHODS

    assert QUALITIES == ("interactive", "default", "high")
    for quality in QUALITIES:
        for method in METHODS:
            quality_config(method, quality)
    with pytest.raises(TypeError):
        QUALITY_PRESETS["interactive"]["dssrm"]["samples"] = 1  # type: ignore[index]
    assert quality_config("dssrm", "default") == DSSRMConfig()
    with pytest.raises(VolrenError, match="unknown quality 'fast'"):
        quality_config("dssrm", "fast")
    with pytest.raises(VolrenError, match="no setting spp"):
        quality_config("dssrm", "interactive", spp=4)


def test_cli_quality_sets_the_preset_and_flags_override_it():
    def config(*argv):
        args = render_parser().parse_args(["render", "--device", "cpu", *argv])
        return renderer_from_args(args, args.method).config

    interactive = config("--quality", "interactive")
    assert interactive == quality_config("dssrm", "interactive")
    assert (interactive.samples, interactive.light_samples, interactive.light_grid) == (160, 48, 32)
    mixed = config("--quality", "interactive", "--samples", "200", "--no-skip")
    assert (mixed.samples, mixed.light_grid, mixed.skip_empty) == (200, 32, False)
    assert config("--method", "vpt", "--quality", "high").spp == 32
    assert config() == DSSRMConfig()


def test_interactive_preset_keeps_the_reference_psnr(smoke):
    """At 120x68 against a 512-sample reference the interactive preset (DSSRM:160:48, 32^3 light grid) is within
    0.5 dB of the default DSSRM:360:96 (measured 52.16 and 52.22 dB)."""
    cam = Camera(position=(0.0, 0.4, 3.2), width=120, height=68)
    ref = Reference(ReferenceConfig(samples=512, light_samples=512), DEVICE).render(smoke, [cam]).images[0]
    quality = {q: psnr(ref, DSSRM(quality_config("dssrm", q), DEVICE).render(smoke, [cam]).images[0])
               for q in ("interactive", "default")}
    assert quality["default"] > 51.0
    assert quality["interactive"] > quality["default"] - 0.5


def test_interactive_bench_rows_at_toy_size():
    """The suite's rows at 48x27 (timings unchecked): skipping changes the work, never the image."""
    from volren.bench.interactive import RUNS, run_config

    result = run_config({"resolution": 64, "size": (48, 27), "views": "mono", "repeats": 1, "reference": 64}, "cpu")
    rows = {(r["method"], r["quality"], r["skip"]): r for r in result["rows"]}
    assert len(rows) == len(RUNS) + 2  # and fog on hall: default, interactive
    fog = rows["fog", "interactive", ""]
    assert fog["scene"] == "hall" and fog["psnr_against"] == "fog default" and rows["fog", "default", ""]["psnr"] == inf
    on, off = rows["dssrm", "interactive", "on"], rows["dssrm", "interactive", "off"]
    assert on["psnr"] == off["psnr"] and off["skipped_steps"] == 0
    assert on["density_samples"] + on["skipped_steps"] == off["density_samples"]
    assert all(r["fps"] == pytest.approx(1e3 / r["render_ms"]) for r in rows.values())


def test_kept_render_targets_are_cleared_and_frames_keep_their_images(smoke):
    """A renderer keeps its views' render targets between frames: a frame clipped by a depth image, then one without
    it from another eye, each equal a fresh renderer's, and the first frame's arrays are not overwritten."""
    cams = [Camera(position=(0.0, 0.4, 3.2), width=40, height=24), Camera(position=(0.5, 0.2, 3.0), width=40,
                                                                          height=24)]
    wall = np.full((24, 40), 3.0, np.float32)
    config = DSSRMConfig(samples=64, light_samples=16, light_grid=16)
    kept = DSSRM(config, DEVICE)
    first = kept.render(smoke, cams[:1], occluder_depth=[wall])
    image, depth = first.images[0].copy(), first.depths[0].copy()
    second = kept.render(smoke, cams[1:])
    np.testing.assert_array_equal(first.images[0], image)
    np.testing.assert_array_equal(first.depths[0], depth)
    np.testing.assert_array_equal(second.images[0], DSSRM(config, DEVICE).render(smoke, cams[1:]).images[0])
    np.testing.assert_array_equal(image, DSSRM(config, DEVICE).render(smoke, cams[:1], occluder_depth=[wall]).images[0])
    assert not np.array_equal(image, second.images[0])

"""Viewer rigs of paper 003's evaluation (wandering viewers, fixed frustum overlap) and the fog CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera
from volren.errors import VolrenError
from volren.viewers import EYE_HEIGHT, overlap_viewers, wandering_viewers

BASE = Camera(position=(0.0, 1.7, 5.0), look_at=(0.0, 1.7, 0.0), width=160, height=90, fov_y=60.0)


def yaw(cam: Camera) -> float:
    d = np.subtract(cam.look_at, cam.position)
    return math.atan2(d[0], -d[2])


def test_wandering_viewers_stay_in_the_area_and_move():
    lo, hi = (-10.0, 0.0, -5.0), (10.0, 7.0, 5.0)
    for t in (0.0, 3.0, 40.0):
        views = wandering_viewers(BASE, 16, lo, hi, time=t, seed=1)
        p = np.array([v.position for v in views])
        assert np.all(p[:, [0, 2]] > np.array(lo)[[0, 2]]) and np.all(p[:, [0, 2]] < np.array(hi)[[0, 2]])
        assert np.allclose(p[:, 1], EYE_HEIGHT)
    a = wandering_viewers(BASE, 4, lo, hi, time=0.0)
    b = wandering_viewers(BASE, 4, lo, hi, time=1.0)
    step = np.linalg.norm(np.subtract(a[0].position, b[0].position))
    assert 0.5 < step < 2.0  # about walking speed


@pytest.mark.parametrize("overlap", [0.1, 0.5, 1.0])
def test_overlap_rig_shares_the_requested_fraction_of_the_horizontal_fov(overlap):
    views = overlap_viewers(BASE, 4, overlap)
    h_fov = 2 * math.atan(BASE.tan_half_fov * BASE.width / BASE.height)
    steps = np.diff([yaw(v) for v in views])
    np.testing.assert_allclose(np.abs(steps), (1 - overlap) * h_fov, atol=1e-9)
    assert all(v.position == BASE.position for v in views)


def test_bad_rigs():
    with pytest.raises(VolrenError, match="overlap"):
        overlap_viewers(BASE, 2, 1.5)
    with pytest.raises(VolrenError, match="viewer count"):
        wandering_viewers(BASE, 0, (0, 0, 0), (1, 1, 1))


def test_viewers_of_different_sizes_render_as_if_alone():
    from volren.data.fog_scenes import fog_scene, fog_scene_camera
    from volren.render import FogConfig, FogRenderer

    spot = fog_scene_camera("courtyard")
    big = Camera(position=spot["position"], look_at=spot["look_at"], width=64, height=36)
    small = Camera(position=(0.0, 1.7, 0.0), look_at=(5.0, 1.0, 5.0), width=40, height=40, fov_y=70.0)
    scene = fog_scene("courtyard")
    config = FogConfig(sharing="none", slices=16, temporal=False)
    both = FogRenderer(config, device=DEVICE).render(scene, [big, small])
    assert [i.shape for i in both.images] == [(36, 64, 4), (40, 40, 4)]
    for cam, image in zip([big, small], both.images, strict=True):
        alone = FogRenderer(config, device=DEVICE).render(scene, [cam]).images[0]
        np.testing.assert_array_equal(image, alone)


@pytest.mark.parametrize("rig", ["wander", "overlap"])
def test_rig_option(capfd, tmp_path, rig):
    from test_cli import ok, stats_of

    out = tmp_path / rig
    ok(capfd, "render", "--method", "fog", "--scene", "hall", "--width", "32", "--height", "18", "--slices", "16",
       "--device", "cpu", "--views", "3", "--rig", rig, "--frames", "2", "--out", out)
    frames = stats_of(out)["frames"]
    assert len(frames) == 2 and frames[0]["settings"]["views"] == 3

"""First pictures (issue 22.10): each built-in scene's default light and sky give the picture its `volren scenes`
description promises, measured on the display image (PNG values: exposure 0, no tone map, as `volren render`)."""

from __future__ import annotations

import numpy as np

import volren as vr
from volren.data.fog_scenes import fog_scene, fog_scene_camera

LUMA = np.array([0.2126, 0.7152, 0.0722])


def _display(frame: vr.Frame) -> np.ndarray:
    return frame.srgb()[..., :3].astype(np.float64) / 255.0


def test_cloud_is_bright():
    """"bright (albedo 0.97)": the covered pixels' mean display luminance was 0.29 (dull grey) under the shared
    light, 0.62 with the cloud's own sun and daylight sky; their sunlit tenth (90th percentile) 0.33, now 0.77 (0.57
    with the new sky but the old sun's irradiance 3)."""
    frame = vr.render(vr.builtin_scene("cloud", 64), vr.Camera(position=(0, 0.4, 3.2), width=96, height=72),
                      method="dssrm", quality="interactive")
    covered = frame.images[0][..., 3] > 0.5
    luminance = _display(frame) @ LUMA
    assert covered.mean() > 0.04  # the cloud fills about 7% of this frame
    assert luminance[covered].mean() > 0.5
    assert np.percentile(luminance[covered], 90) > 0.7


def test_courtyard_is_a_night_square():
    """"night square ... warm lamp-post point lights": dark overall (mean display luminance was 0.63, beige), blue
    where the lamps do not reach (the darker half), warm at the lamps (the brightest 2%)."""
    where = fog_scene_camera("courtyard")
    camera = vr.Camera(position=where["position"], look_at=where["look_at"], width=96, height=72)
    image = _display(vr.render(fog_scene("courtyard"), camera, method="fog", quality="interactive"))
    luminance = image @ LUMA
    assert luminance.mean() < 0.3
    dark = image[luminance < np.median(luminance)].mean(axis=0)
    assert dark[2] > 1.05 * dark[0]
    bright = image[luminance >= np.percentile(luminance, 98)].mean(axis=0)
    assert bright[0] > bright[2]

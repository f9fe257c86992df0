"""Interaction sequences (``volren animate``): camera orbit, light rotation, transfer-function switch, MP4."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from test_cli import assert_error, ok
from volren.animate import Sequence, frame_config, frame_scene, frame_views
from volren.camera import Camera
from volren.data import builtin_scene
from volren.errors import VolrenError
from volren.render import DSSRMConfig, VPTConfig
from volren.scene import DirectionalLight


def test_orbit_turns_cameras_and_lights_by_the_sequence_angle():
    seq = Sequence(frames=5, orbit=90.0, light_orbit=180.0)
    cam = Camera(position=(0.0, 0.5, 3.0), look_at=(0.0, 0.0, 0.0))
    first, last = frame_views(seq, [cam], 0)[0], frame_views(seq, [cam], 4)[0]
    assert first.position == cam.position
    np.testing.assert_allclose(last.position, (3.0, 0.5, 0.0), atol=1e-12)  # a quarter turn about +y
    scene = builtin_scene("smoke", 64)
    turned = frame_scene(seq, scene, 4).lights[0]
    assert isinstance(turned, DirectionalLight)
    d0, d1 = np.array(scene.lights[0].direction), np.array(turned.direction)
    np.testing.assert_allclose(d1[[0, 2]], -d0[[0, 2]], atol=1e-12)  # half a turn
    assert math.isclose(d1[1], d0[1])


def test_transfer_switch_applies_from_its_frame_and_needs_vpt():
    seq = Sequence(frames=4, switch_frame=2, switch_transfer="ct-bone")
    assert frame_config(seq, VPTConfig(), 1).transfer is None
    assert frame_config(seq, VPTConfig(), 3).transfer == "ct-bone"
    with pytest.raises(VolrenError, match="vpt"):
        frame_config(seq, DSSRMConfig(), 3)
    with pytest.raises(VolrenError, match="switch frame"):
        Sequence(frames=4, switch_frame=9, switch_transfer="ct-bone")


def test_animate_writes_frames_and_an_mp4(capfd, tmp_path: Path):
    out = tmp_path / "a"
    ok(capfd, "animate", "--method", "vpt", "--scene", "phantom", "--resolution", "64", "--tf", "ct-muscle",
       "--frames", "4", "--spp", "1", "--width", "32", "--height", "24", "--views", "mono", "--light-orbit", "90",
       "--switch-tf", "2:ct-bone", "--device", "cpu", "--out", out)
    assert all((out / f"frame{i:04d}_view0.png").exists() for i in range(4))
    with imageio.get_reader(out / "animation.mp4") as movie:
        assert movie.count_frames() == 4
    frames = json.loads((out / "stats.json").read_text())["frames"]
    assert ["majorants" in f["times_ms"] for f in frames] == [True, False, True, False]
    assert [f["settings"]["transfer"] for f in frames] == ["ct-muscle", "ct-muscle", "ct-bone", "ct-bone"]


def test_animate_bad_switch(capfd, tmp_path: Path):
    assert_error(capfd, ["animate", "--method", "vpt", "--scene", "smoke", "--switch-tf", "two:ct-bone", "--device",
                         "cpu", "--out", tmp_path / "o"], "FRAME:TF")
    assert_error(capfd, ["animate", "--method", "dssrm", "--scene", "smoke", "--switch-tf", "1:ct-bone", "--device",
                         "cpu", "--out", tmp_path / "o"], "vpt")

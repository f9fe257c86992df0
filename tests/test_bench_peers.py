"""`volren bench peers`: volren against VTK's CPU ray caster at a matched sample distance (issue 24, "Against VTK")."""

from __future__ import annotations

import builtins
import json

import imageio.v3 as iio
import numpy as np
import pytest

from volren.bench import peers
from volren.bench.runner import run_suite
from volren.camera import Camera
from volren.data import builtin_scene
from volren.errors import VolrenError
from volren.scene import Scene, Volume

TINY = {"scene": "cloud", "resolution": 64, "sizes": [(64, 36)], "frames": 2, "rounds": 1, "samples": 360}


def test_sample_distance_is_v_samples_across_the_world_diagonal():
    """V = 360 across the box's longest world diagonal: 2 sqrt(3) / 360 for the unit cube [-1, 1]^3, and for a box
    scaled (2, 1, 0.5) its diagonal sqrt(4^2 + 2^2 + 1^2) / 360; VTK's mapper gets exactly that."""
    assert peers.matched_sample_distance(Volume(np.zeros((4, 4, 4))), 360) == pytest.approx(2 * np.sqrt(3) / 360)
    box = Volume(np.ones((4, 6, 8), np.float32), np.diag([2.0, 1.0, 0.5, 1.0]))
    assert peers.matched_sample_distance(box, 360) == pytest.approx(np.sqrt(21.0) / 360)
    cloud = builtin_scene("cloud", 64)
    peer = peers.VTKPeer(Scene((box,), cloud.lights, cloud.environment, cloud.background), 360, 16, 16)
    assert peer.mapper.GetSampleDistance() == pytest.approx(np.sqrt(21.0) / 360)
    assert peer.mapper.GetImageSampleDistance() == 1.0 and not peer.mapper.GetAutoAdjustSampleDistances()


def test_vtk_volume_sits_where_volrens_voxels_do():
    """VTK's points are volren's voxel centres (-1 + (i + 1/2) 2 / n in the box): a box scaled (2, 1, 0.5) and moved
    by (0.5, 0, -1) spans [-1.5, 2.5] x [-1, 1] x [-1.5, -0.5] less half a voxel at each face."""
    m = np.diag([2.0, 1.0, 0.5, 1.0])
    m[:3, 3] = (0.5, 0.0, -1.0)
    box = Volume(np.ones((4, 6, 8), np.float32), m)
    cloud = builtin_scene("cloud", 64)
    peer = peers.VTKPeer(Scene((box,), cloud.lights, cloud.environment, cloud.background), 360, 16, 16)
    half = np.array([4.0 / 8, 2.0 / 6, 1.0 / 4]) / 2  # half a voxel per axis (x, y, z)
    lo, hi = np.array([-1.5, -1.0, -1.5]) + half, np.array([2.5, 1.0, -0.5]) - half
    assert np.allclose(np.reshape(peer.image_data.GetBounds(), (3, 2)), np.stack([lo, hi], axis=1))


def test_orbit_circles_the_look_at_point():
    cams = peers.orbit(Camera(position=(0.0, 0.4, 3.2), width=8, height=8), 4)
    assert np.allclose([c.position for c in cams], [(0, 0.4, 3.2), (3.2, 0.4, 0), (0, 0.4, -3.2), (-3.2, 0.4, 0)],
                       atol=1e-12)


def test_peers_suite_draws_the_same_view_and_keeps_the_light_map(tmp_path, monkeypatch):
    """The bench at a tiny size: VTK off-screen through EGL, the ratio of the two times, the same view (the shading
    models differ: 29.1 dB here, VTK's camera left at its default 20.2 dB, on the orbit's opposite side 23.5),
    volren's light map computed in the warm-up only (the light stands still on the orbit), both images side by side
    next to the Markdown."""
    monkeypatch.setattr(peers, "QUICK", TINY)
    json_path, md_path, _ = run_suite("peers", quick=True, device="cpu", out=tmp_path)
    (row,) = json.loads(json_path.read_text())["rows"]
    assert row["vtk_window"] == "vtkEGLRenderWindow"
    assert row["ratio"] == pytest.approx(row["volren_ms"] / row["vtk_ms"])
    assert row["cpu_ratio"] == pytest.approx(row["volren_cpu_ms"] / row["vtk_cpu_ms"])
    assert row["light_maps"] == 0
    assert row["psnr"] > 26.0
    name = "64x36-volren-left-vtk-right.png"
    assert f"![{name}](peers-cpu-quick-{name})" in md_path.read_text()
    figure = iio.imread(tmp_path / f"peers-cpu-quick-{name}")
    assert figure.shape == (36, 128, 3)


def test_without_vtk_the_suite_names_the_extra(monkeypatch):
    real_import = builtins.__import__

    def no_vtk(name, *args, **kwargs):
        if name == "vtk" or name.startswith("vtk."):
            raise ImportError(f"No module named '{name}'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_vtk)
    with pytest.raises(VolrenError, match=r"volren\[peers\]"):
        peers.import_vtk()

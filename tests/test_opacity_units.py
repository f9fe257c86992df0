"""Issue 45 item 1: a loaded volume's default opacity comes from its own box (`volren.plan.volume.box_density_scale`:
optical depth 20 at density 1 across the box's longest side), so a specimen in micrometres shows as the same array in
metres does; ``--density-scale`` (``density_scale=``) given is per metre as before; stats.json says which rule set
it; a default render that is still empty says why in one line. 32^3 volumes at 32x32 pixels: about a second each."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import volren as vr
from volren.cli import main

UM = 1e-6
N = 32
"""voxels a side: the ball's 24 um diameter in a 32 um box of 1 um voxels"""


def ball() -> np.ndarray:
    """uint8 [z, y, x]: a ball of 12 voxels' radius at 200 (density 200 / 255), zero elsewhere."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N] + 0.5 - N / 2
    return ((x**2 + y**2 + z**2) <= 12**2).astype(np.uint8) * 200


def imagej_tiff(path: Path, data: np.ndarray, voxel: float, unit: str) -> Path:
    """``data`` as an ImageJ TIFF of cubic voxels ``voxel`` ``unit`` a side (tifffile)."""
    import tifffile

    tifffile.imwrite(path, data, imagej=True, resolution=(1 / voxel, 1 / voxel),
                     metadata={"spacing": voxel, "unit": unit})
    return path


def alpha(volume: Path, out: Path, *extra: str) -> np.ndarray:
    """The default camera's mono 32x32 view of ``volume`` (a light march), its alpha."""
    assert main(["render", "--volume", str(volume), "--views", "mono", "--width", "32", "--height", "32",
                 "--samples", "64", "--light-samples", "4", "--light-grid", "8", "--device", "cpu", "--save-linear",
                 "--out", str(out), *extra]) == 0
    return np.load(out / "view0.npy")[..., 3]


def test_micrometre_tiff_renders_as_the_same_array_in_metres(tmp_path: Path, capfd) -> None:
    """A 24 um ball in an ImageJ TIFF in micrometres rendered alpha 0.0002 at its centre (10 /m over 24 um); by
    default it is opaque at the centre, clear at the corner, and the picture is the one of the same array in metres
    (1 m voxels) and without placement (a 2 m box: density_scale 10 /m, as before). stats.json says the rule."""
    um = alpha(imagej_tiff(tmp_path / "um.tif", ball(), 1.0, "um"), tmp_path / "um")
    assert um[N // 2, N // 2] > 0.9 and um[0, 0] < 0.01, (um[N // 2, N // 2], um[0, 0])
    metres = alpha(imagej_tiff(tmp_path / "m.tif", ball(), 1e6, "um"), tmp_path / "m")
    np.save(tmp_path / "plain.npy", ball())
    plain = alpha(tmp_path / "plain.npy", tmp_path / "plain")
    assert np.abs(um - metres).max() < 1e-4 and np.abs(um - plain).max() < 1e-4
    assert capfd.readouterr().err == ""  # nothing to warn of
    stats = json.loads((tmp_path / "um" / "stats.json").read_text())
    assert stats["value_mapping"] == {"source": "uint8", "range": [0.0, 255.0], "units": "raw"}
    opacity = stats["opacity"]
    assert opacity["rule"] == "box" and opacity["optical_depth"] == 20.0
    assert opacity["longest_side"] == pytest.approx(N * UM) and opacity["density_scale"] == pytest.approx(20 / (N * UM))
    plain_opacity = json.loads((tmp_path / "plain" / "stats.json").read_text())["opacity"]
    assert plain_opacity["density_scale"] == pytest.approx(10.0)  # the old default, on the unplaced 2 m box


def test_density_scale_given_is_per_metre(tmp_path: Path, capfd) -> None:
    """--density-scale 10 [1/m] is what it says: the micrometre ball all but vanishes (and one line says what to set)
    while the metre ball is opaque; stats.json names the flag."""
    um = alpha(imagej_tiff(tmp_path / "um.tif", ball(), 1.0, "um"), tmp_path / "um", "--density-scale", "10")
    metres = alpha(imagej_tiff(tmp_path / "m.tif", ball(), 1e6, "um"), tmp_path / "m", "--density-scale", "10")
    assert um.max() < 0.01 and metres[N // 2, N // 2] > 0.99, (um.max(), metres[N // 2, N // 2])
    lines = capfd.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("volren: warning: volume 'um.tif' renders all but empty"), lines
    assert "set --density-scale [1/m] to about 7.97e+05" in lines[0]
    stats = json.loads((tmp_path / "um" / "stats.json").read_text())
    assert stats["opacity"] == {"rule": "--density-scale", "density_scale": 10.0}


def test_twelve_bit_ct_tiff_in_millimetres_is_visible(tmp_path: Path) -> None:
    """A 12-bit CT-like ImageJ TIFF (uint16, 0..4095) of 0.5 mm voxels, a 16 mm box: alpha 0.09 at its centre
    before (10 /m); by default opaque at the centre and clear at the corner."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N] / (N / 2 - 0.5) - 1
    ct = np.clip(4400 * (1 - 1.5 * (x**2 + y**2 + z**2)), 0, 4095).round().astype(np.uint16)
    ct[ct > 0] = np.maximum(ct[ct > 0], 1000)
    a = alpha(imagej_tiff(tmp_path / "ct.tif", ct, 0.5, "mm"), tmp_path / "ct")
    assert a[N // 2, N // 2] > 0.9 and a[0, 0] < 0.01, (a[N // 2, N // 2], a[0, 0])
    stats = json.loads((tmp_path / "ct" / "stats.json").read_text())
    assert stats["value_mapping"]["range"] == [0.0, 4095.0]
    assert stats["opacity"]["density_scale"] == pytest.approx(20 / 0.016)


def test_load_of_a_micrometre_file_renders_visible(tmp_path: Path) -> None:
    """vr.load without density_scale: the box rule; vr.render of it from the viewer's default camera (framed, its
    near plane scaled: 1 cm would clip the ball away) shows the ball; density_scale= given is per metre."""
    from volren.notebook import default_camera

    path = imagej_tiff(tmp_path / "um.tif", ball(), 1.0, "um")
    volume = vr.load(path)
    assert volume.density_scale == pytest.approx(20 / (N * UM))
    scene = vr.Scene([volume])
    camera = default_camera(scene)
    assert camera.near < 1e-6
    camera = vr.Camera(position=camera.position, look_at=camera.look_at, near=camera.near, width=N, height=N)
    frame = vr.render(scene, camera, samples=64, light_samples=4, light_grid=8, device="cpu")
    a = frame.images[0][..., 3]
    assert a[N // 2, N // 2] > 0.9 and a[0, 0] < 0.01, (a[N // 2, N // 2], a[0, 0])
    assert vr.load(path, density_scale=10.0).density_scale == 10.0


def test_omezarr_in_micrometres_renders_visible(tmp_path: Path) -> None:
    """The ball as an OME-Zarr in micrometres written by ome-zarr's own writer: visible by default."""
    zarr = pytest.importorskip("zarr")
    writer = pytest.importorskip("ome_zarr.writer")
    axes = [{"name": n, "type": "space", "unit": "micrometer"} for n in "zyx"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # coordinate_transformations, as tests/test_omezarr.py
        writer.write_multiscale([ball()], zarr.open_group(str(tmp_path / "ball.zarr"), mode="w"), axes=axes,
                                coordinate_transformations=[[{"type": "scale", "scale": [1.0, 1.0, 1.0]}]])
    a = alpha(tmp_path / "ball.zarr", tmp_path / "out")
    assert a[N // 2, N // 2] > 0.9 and a[0, 0] < 0.01, (a[N // 2, N // 2], a[0, 0])
    assert json.loads((tmp_path / "out" / "stats.json").read_text())["opacity"]["longest_side"] == pytest.approx(
        N * UM)


def test_an_empty_default_render_says_why_in_one_line(tmp_path: Path, capfd) -> None:
    """A camera that misses the volume: one line naming the camera flags and --density-scale; all-zero data: the
    existing one line, not two."""
    np.save(tmp_path / "ball.npy", ball())
    away = alpha(tmp_path / "ball.npy", tmp_path / "away", "--camera-pos", "0,0,3", "--look-at", "0,0,6")
    assert away.max() == 0
    lines = capfd.readouterr().err.splitlines()
    assert lines == ["volren: warning: the render of volume 'ball.npy' is empty (alpha under 0.01 in every view): "
                     "the camera misses its box (check --camera-pos, --look-at, --fov) or it is too thin (raise "
                     "--density-scale [1/m], now 10)"], lines
    np.save(tmp_path / "zero.npy", np.zeros((8, 8, 8), np.float32))
    alpha(tmp_path / "zero.npy", tmp_path / "zero")
    lines = capfd.readouterr().err.splitlines()
    assert lines == ["volren: warning: volume 'zero.npy' has an all-zero density: it renders nothing"], lines

"""Issue 42 item 2: the Python door is as wide as the CLI. Each README ``volren render`` example's scene, rendered small
through ``volren render ... --out DIR`` (in process) and through the public API (`vr.render` then `Frame.save`),
gives the same PNG files byte for byte: the same scene, framing, views, renderer settings and output.

The examples are an explicit table (the README's command block is being regrouped; test_readme runs every line as
written): each row names the README line it stands for, its CLI arguments at a small size, and its Python
counterpart. README lines not here and why: ``animate`` (orbit, light orbit, --switch-tf: no Python counterpart),
``--sphere``/``--ground``/``--mesh``/``--depth-image`` (opaque geometry: `vr.Scene(opaque=...)`, whose types are not
in the public API), ``--rect-light`` (the same), ``--rig wander``/``overlap`` (viewer rigs)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from tests.conftest import DEVICE

import volren as vr
from volren.cli import main

W, H = 96, 64
SIZE = ["--width", str(W), "--height", str(H), "--device", DEVICE]
MARCH = ["--samples", "16", "--light-samples", "8", "--light-grid", "16"]
SMALL = {"samples": 16, "light_samples": 8, "light_grid": 16}
CLI_QUALITY = "default"
"""``volren render``'s quality preset; the API's default is serve's ``interactive``"""


def py(x, views=None, **kw):
    """`vr.render` as the CLI runs it: its quality, this size and device."""
    kw = {"quality": CLI_QUALITY, "device": DEVICE, **kw}
    if views is None or isinstance(views, str | int):
        kw |= {"width": W, "height": H}
    return vr.render(x, views, **kw)


def phantom_with_overrides(folder: Path):
    """``--scene phantom --camera-pos 0,2.5,2.5 --look-at 0,0,0 --fov 40 --density-scale 4 --albedo 0.9,0.8,0.7
    --g 0.3 --light-dir -1,-1,0 --light-irradiance 4 --ambient 0.05`` built by hand: material and light overrides
    are a Scene's fields in Python."""
    scene = vr.builtin_scene("phantom", 64)
    volumes = tuple(dataclasses.replace(v, density_scale=4.0, albedo=(0.9, 0.8, 0.7), g=0.3) for v in scene.volumes)
    light = dataclasses.replace(next(lt for lt in scene.lights if isinstance(lt, vr.DirectionalLight)),
                                direction=(-1.0, -1.0, 0.0), irradiance=(4.0, 4.0, 4.0))
    scene = dataclasses.replace(scene, volumes=volumes, lights=(light,), environment=vr.Environment(0.05))
    eyes = vr.views(vr.Camera(position=(0, 2.5, 2.5), look_at=(0, 0, 0), fov_y=40, width=W, height=H), "stereo")
    return vr.render(scene, eyes, quality=CLI_QUALITY, device=DEVICE, **SMALL)


# (the README line, its CLI arguments here, its Python counterpart given the folder of the test files, PNG options)
EXAMPLES: list[tuple[str, list[str], Callable[[Path], object], dict]] = [
    ("render --scene cloud --resolution 128 --views stereo",
     ["--scene", "cloud", "--resolution", "64", "--views", "stereo", *MARCH],
     lambda d: py("cloud", "stereo", resolution=64, **SMALL), {}),
    ("render --scene multi --count 16 --method reference --samples 256 --light-samples 64 --views mono",
     ["--scene", "multi", "--count", "4", "--resolution", "64", "--method", "reference", "--samples", "16",
      "--light-samples", "8", "--views", "mono"],
     lambda d: py("multi", "mono", count=4, resolution=64, method="reference", samples=16, light_samples=8), {}),
    ("render --scene phantom --camera-pos ... --ambient 0.05 --exposure 1 --tonemap aces --save-linear",
     ["--scene", "phantom", "--resolution", "64", "--camera-pos", "0,2.5,2.5", "--look-at", "0,0,0", "--fov", "40",
      "--density-scale", "4", "--albedo", "0.9,0.8,0.7", "--g", "0.3", "--light-dir", "-1,-1,0",
      "--light-irradiance", "4", "--ambient", "0.05", "--exposure", "1", "--tonemap", "aces", *MARCH],
     phantom_with_overrides, {"exposure": 1.0, "tonemap": "aces"}),
    ("render --volume head.nrrd --samples 100 --light-samples 48 --light-grid 64",
     ["--volume", "{d}/head.nrrd", *MARCH], lambda d: py(str(d / "head.nrrd"), "stereo", **SMALL), {}),
    ("render --scene cloud --environment sky.npy",
     ["--scene", "cloud", "--resolution", "64", "--environment", "{d}/sky.npy", "--views", "mono", *MARCH],
     lambda d: py("cloud", "mono", resolution=64, environment=d / "sky.npy", **SMALL), {}),
    ("render --scene smoke --environment sky --gi sresir --frames 16",
     ["--scene", "smoke", "--resolution", "64", "--environment", "sky", "--gi", "sresir", "--frames", "2",
      "--views", "mono", *MARCH],
     lambda d: py("smoke", "mono", resolution=64, environment="sky", gi=vr.GIConfig(method="sresir"), frames=2,
                  **SMALL), {}),
    ("render --volume ct.raw --shape 256,256,128 --dtype uint16 --views 4",
     ["--volume", "{d}/ct.raw", "--shape", "24,20,16", "--dtype", "uint16", "--views", "4", *MARCH],
     lambda d: py(vr.load(d / "ct.raw", shape=(24, 20, 16), dtype="uint16"), 4, **SMALL), {}),
    ("render --scene smoke --jitter --frames 8 --seed 3",
     ["--scene", "smoke", "--resolution", "64", "--jitter", "--frames", "2", "--seed", "3", "--views", "mono",
      *MARCH],
     lambda d: py("smoke", "mono", resolution=64, jitter=True, frames=2, seed=3, **SMALL), {}),
    ("render --quality interactive --views mono --width 480 --height 270",
     ["--quality", "interactive", "--resolution", "64", "--views", "mono"],
     lambda d: py("smoke", "mono", quality="interactive", resolution=64), {}),
    ("render --scene cloud --method cmsrm",
     ["--scene", "cloud", "--resolution", "64", "--method", "cmsrm", "--cube-size", "32", *MARCH],
     lambda d: py("cloud", "stereo", resolution=64, method="cmsrm", cube_size=32, **SMALL), {}),
    ("render --scene smoke --method cacrm --views stereo",
     ["--scene", "smoke", "--resolution", "64", "--method", "cacrm", "--views", "stereo", *MARCH],
     lambda d: py("smoke", "stereo", resolution=64, method="cacrm", **SMALL), {}),
    ("render --method fog --scene hall --views 16",
     ["--method", "fog", "--scene", "hall", "--views", "3", "--slices", "16", "--voxel-size", "0.5"],
     lambda d: py("hall", 3, method="fog", slices=16, voxel_size=0.5), {}),
    ("render --method vpt --scene phantom --tf ct-muscle --spp 32 --clip=-1,1,-1,0.3,-1,1",
     ["--method", "vpt", "--scene", "phantom", "--resolution", "64", "--tf", "ct-muscle", "--spp", "1",
      "--clip=-1,1,-1,0.3,-1,1", "--views", "mono"],
     lambda d: py("phantom", "mono", resolution=64, method="vpt", transfer="ct-muscle", spp=1,
                  clip=(-1, 1, -1, 0.3, -1, 1)), {}),
    ("render --volume fire.vdb --emission-grid temperature --views mono  # kelvin: glows",
     ["--volume", "{d}/fire.vdb", "--emission-grid", "temperature", "--views", "mono", *MARCH],
     lambda d: py(vr.load(d / "fire.vdb", emission_grid="temperature"), **SMALL), {}),
    ("render --volume beads.tif --views mono  # 0.5 um pixels",
     ["--volume", "{d}/beads.tif", "--views", "mono", *MARCH],
     lambda d: py(vr.load(d / "beads.tif"), **SMALL), {}),
    ("render --volume 'sim_####.npy' --frames 3 --views mono",
     ["--volume", "{d}/sim_####.npy", "--frames", "3", "--views", "mono", *MARCH],
     lambda d: py(vr.load(d / "sim_####.npy"), **SMALL), {}),
    ("render --volume fmri.nii.gz --frames N (a 4-D NIfTI's time points)",
     ["--volume", "{d}/fmri.nii.gz", "--frames", "2", "--views", "mono", *MARCH],
     lambda d: py(vr.load(d / "fmri.nii.gz"), frames=2, **SMALL), {}),
    ("render --volume cells.tif --channel-colors green,magenta --channel-opacity 4,2 --views mono",
     ["--volume", "{d}/cells.tif", "--channel-colors", "green,magenta", "--channel-opacity", "4,2", "--views",
      "mono", *MARCH],
     lambda d: py(vr.load(d / "cells.tif", channel_colors=["green", "magenta"], channel_opacity=(4, 2)), **SMALL), {}),
    ("render --volume cells.tif --mode mip (each channel's maximum in its colour)",
     ["--volume", "{d}/cells.tif", "--mode", "mip", "--views", "stereo", *MARCH],
     lambda d: py(d / "cells.tif", "stereo", mode="mip", **SMALL), {}),
    ("render --volume cells.zarr --level 1 --method cmsrm --views mono",
     ["--volume", "{d}/cells.zarr", "--level", "1", "--method", "cmsrm", "--views", "mono", "--cube-size", "32",
      *MARCH],
     lambda d: py(vr.load(d / "cells.zarr", level=1), method="cmsrm", cube_size=32, **SMALL), {}),
    ("render --scene phantom --method cmsrm --mode iso --iso-value 0.3 --views mono",
     ["--scene", "phantom", "--resolution", "64", "--method", "cmsrm", "--mode", "iso", "--iso-value", "0.3",
      "--cube-size", "32", "--views", "mono", *MARCH],
     lambda d: py("phantom", resolution=64, method="cmsrm", mode="iso", iso_value=0.3, cube_size=32, **SMALL), {}),
    ("render --scene smoke --mode mip --views mono",
     ["--scene", "smoke", "--resolution", "64", "--mode", "mip", "--views", "mono", *MARCH],
     lambda d: py("smoke", resolution=64, mode="mip", **SMALL), {}),
]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    """The examples' files, small: a NRRD, a raw uint16 stack, an environment map, a micrometre TIFF, a numbered
    .npy sequence, a 4-D NIfTI, a two-channel TIFF and OME-Zarr, an OpenVDB flame."""
    import nibabel as nib
    import nrrd
    import tifffile

    from volren.bench.load import write_with_openvdb
    from volren.data.procedural import fire_fields

    d = tmp_path_factory.mktemp("parity")
    z, y, x = np.mgrid[0:16, 0:20, 0:24]
    ball = np.exp(-((x - 12) ** 2 + (y - 10) ** 2 + (z - 8) ** 2) / 30.0)
    nrrd.write(str(d / "head.nrrd"), np.asfortranarray((ball * 1000).astype(np.int16).transpose(2, 1, 0)),
               {"space": "left-posterior-superior", "space directions": np.diag([3.0, 3.0, 3.0]).tolist()},
               index_order="F")
    (ball * 3000).astype(np.uint16).tofile(d / "ct.raw")
    np.save(d / "sky.npy", np.ones((8, 16, 3), np.float32) * np.linspace(2, 0.2, 8, dtype=np.float32)[:, None, None])
    tifffile.imwrite(d / "beads.tif", (ball * 4000).astype(np.uint16), imagej=True, resolution=(2.0, 2.0),
                     metadata={"axes": "ZYX", "spacing": 1.0, "unit": "um"})
    for i in range(3):  # a sequence: the ball moving a voxel a frame
        np.save(d / f"sim_{i:04d}.npy", np.roll(ball, i, axis=2).astype(np.float32))
    series = np.stack([np.roll(ball, 2 * t, axis=1) for t in range(3)], axis=-1)  # x, y, z, t after the transpose
    nib.save(nib.Nifti1Image(series.transpose(2, 1, 0, 3).astype(np.float32), np.diag([2.0, 2.0, 2.0, 1.0])),
             str(d / "fmri.nii.gz"))
    cells = np.stack([np.exp(-((x - cx) ** 2 + (y - 10) ** 2 + (z - 8) ** 2) / 20.0) for cx in (8, 16)])
    cells = (cells * 3000).astype(np.uint16)  # (C, Z, Y, X), 12-bit
    tifffile.imwrite(d / "cells.tif", cells.transpose(1, 0, 2, 3), imagej=True, metadata={"axes": "ZCYX"})
    write_zarr(d / "cells.zarr", cells)
    soot, temperature = (f[::4, ::4, ::4] for f in fire_fields(64))
    voxel = np.diag([2 / 16, 2 / 16, 2 / 16, 1.0]).tolist()
    write_with_openvdb({"fire.vdb": [{"name": "density", "array": soot, "matrix": voxel},
                                     {"name": "temperature", "array": 300.0 + 2200.0 * temperature, "matrix": voxel}]},
                       d)
    return d


def write_zarr(path: Path, cells: np.ndarray) -> None:
    import warnings

    import zarr

    with warnings.catch_warnings():  # ome-zarr warns of its own default Scaler even given scale_factors
        warnings.simplefilter("ignore", DeprecationWarning)
        from ome_zarr.writer import write_image

        write_image(cells, zarr.open_group(str(path), mode="w"), axes="czyx", scale_factors=(2,),
                    scale={"c": 1.0, "z": 2.0, "y": 0.5, "x": 0.5}, axes_units={a: "micrometer" for a in "zyx"})


def pngs(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.png"))}


@pytest.mark.timeout(240)
@pytest.mark.parametrize(("line", "args", "python", "png"), EXAMPLES, ids=[e[0].split("  #")[0] for e in EXAMPLES])
def test_python_renders_the_readme_example_as_the_cli_does(files, tmp_path, line, args, python, png):
    out = tmp_path / "cli"
    assert main(["render", *(a.replace("{d}", str(files)) for a in args), *SIZE, "--out", str(out)]) == 0
    cli = pngs(out)
    import imageio.v3 as iio

    shown = iio.imread(sorted(out.glob("*view0.png"))[0]).astype(float)
    assert shown[..., :3].std() > 0.5, f"{line}: the CLI's image is one flat colour: a parity of nothing"
    result = python(files)
    frames = result if isinstance(result, list) else [result]
    ours: dict[str, bytes] = {}
    for i, frame in enumerate(frames):
        frame.save(tmp_path / f"py{i}", **png)
        prefix = f"frame{i:04d}_" if len(frames) > 1 else ""
        ours |= {prefix + name: data for name, data in pngs(tmp_path / f"py{i}").items()}
    assert sorted(ours) == sorted(cli), line
    differ = [name for name in cli if ours[name] != cli[name]]
    assert not differ, f"{line}: {differ} differ between the CLI and Python"

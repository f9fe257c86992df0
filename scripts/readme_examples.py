"""Run the README's shell examples as written and time them (issue 22.5: each should finish in about a minute on
two CPU cores).

    python scripts/readme_examples.py --list                 # the examples, numbered
    python scripts/readme_examples.py --time                 # run every one in a scratch folder, print a table
    python scripts/readme_examples.py --time --only animate  # those containing a word

Each runs as a subprocess in one scratch folder holding small stand-ins for the user's files the README names
(head.nrrd, ct.raw, sky.npy, ...), in the README's order with the `volren compare` lines last (they read the renders).
Not run: `volren serve` (it listens until stopped) and the `--device cuda` lines (they need a GPU).
tests/test_readme.py runs the same lines reduced to a tiny size.
"""

from __future__ import annotations

import argparse
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
NOT_RUN = ("serve",)
"""commands that never finish on their own"""
NEEDS_GPU = "--device cuda"


def readme_examples(text: str) -> list[list[str]]:
    """Every `volren ...` and `python scripts/...` line of the sh blocks, continuation lines joined, comments cut."""
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    lines = "\n".join(blocks).replace("\\\n", " ").splitlines()
    return [words for line in lines if (words := shlex.split(line, comments=True))
            and (words[0] == "volren" or (words[0] == "python" and words[1].startswith("scripts/")))]


def stand_ins(folder: Path, width: int = 640, height: int = 360) -> None:
    """The user's files the README names, small; the depth image matches views of ``width`` x ``height``."""
    import warnings

    import nibabel as nib
    import nrrd
    import tifffile
    import zarr
    from ome_zarr.writer import write_image

    from volren.bench.load import write_with_openvdb
    from volren.data.procedural import fire_fields, phantom_density, smoke_density
    from volren.transfer import PRESETS

    head = phantom_density(64)
    nrrd.write(str(folder / "head.nrrd"), np.asfortranarray((head * 1000).astype(np.int16).transpose(2, 1, 0)),
               {"space": "left-posterior-superior", "space directions": np.diag([3.0, 3.0, 3.0]).tolist()},
               index_order="F")
    nib.save(nib.Nifti1Image(np.ascontiguousarray(head.transpose(2, 1, 0)), np.diag([3.0, 3.0, 3.0, 1.0])),
             str(folder / "ct.nii.gz"))
    raw = np.zeros((128, 256, 256), np.uint16)  # --shape 256,256,128 as the README says: the phantom, 4x up in x, y
    raw[32:96] = (np.repeat(np.repeat(head, 4, axis=1), 4, axis=2) * 60000).astype(np.uint16)
    raw.tofile(folder / "ct.raw")
    sky = np.ones((16, 32, 3), np.float32) * np.linspace(2.0, 0.2, 16, dtype=np.float32)[:, None, None]
    np.save(folder / "sky.npy", sky)
    np.save(folder / "zbuffer.npy", np.full((height, width), 3.0, np.float32))
    (folder / "bunny.obj").write_text("v 0 0 0\nv 0.2 0 0\nv 0 0 0.2\nv 0 0.2 0\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (folder / "my_tf.json").write_text(PRESETS["ct-bone"].to_json())
    (folder / "volren-token").write_text("readme-example-token-0123\n")  # serve --token-file
    for i in range(3):  # a sequence: the smoke drifting up a voxel a frame
        np.save(folder / f"sim_{i:04d}.npy", np.roll(smoke_density(64)[::2, ::2, ::2], i, axis=1))
    z, y, x = np.mgrid[0:16, 0:24, 0:24]
    cells = (np.stack([np.exp(-((x - cx) ** 2 + (y - 12) ** 2 + (z - 8) ** 2) / 20.0) for cx in (8, 16)]) * 3000
             ).astype(np.uint16)  # (C, Z, Y, X), 12-bit
    tifffile.imwrite(folder / "cells.tif", cells.transpose(1, 0, 2, 3), imagej=True, metadata={"axes": "ZCYX"})
    ball = (np.exp(-((x - 12) ** 2 + (y - 12) ** 2 + (z - 8) ** 2) / 30.0) * 4000).astype(np.uint16)  # 12-bit
    tifffile.imwrite(folder / "beads.tif", ball, imagej=True, resolution=(2.0, 2.0),  # 0.5 um pixels, 1 um slices
                     metadata={"axes": "ZYX", "spacing": 1.0, "unit": "um"})
    with warnings.catch_warnings():  # ome-zarr 0.18 warns of its own default Scaler even given scale_factors
        warnings.simplefilter("ignore", DeprecationWarning)
        write_image(cells, zarr.open_group(str(folder / "cells.zarr"), mode="w"), axes="czyx", scale_factors=(2,),
                    scale={"c": 1.0, "z": 2.0, "y": 0.5, "x": 0.5}, axes_units={a: "micrometer" for a in "zyx"})
    soot, temperature = (f[::2, ::2, ::2] for f in fire_fields(64))
    voxel = np.diag([2 / 32, 2 / 32, 2 / 32, 1.0]).tolist()
    shutil.copytree(ROOT / "examples", folder / "examples", dirs_exist_ok=True)  # the job files, as in a checkout
    write_with_openvdb({"fire.vdb": [{"name": "density", "array": soot, "matrix": voxel},
                                     {"name": "temperature", "array": 300.0 + 2200.0 * temperature,  # kelvin
                                      "matrix": voxel}],
                        "explosion.vdb": [{"name": "density", "array": head, "matrix": voxel}]}, folder)
    big_data(folder / "data")


def big_data(folder: Path) -> None:
    """Small stand-ins for the "Big data" files (the README's names; `scripts/bigdata_files.py` writes the real
    ones): two small balls written by OpenVDB, and two 32^3 pyramids of the bench's field."""
    from volren.bench.bigdata import write_pyramid
    from volren.bench.load import write_with_openvdb

    folder.mkdir(parents=True, exist_ok=True)
    z, y, x = np.mgrid[0:24, 0:24, 0:24]
    balls = sum(np.clip(1.0 - ((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2) / 16.0, 0.0, None) for c in (5, 18))
    write_with_openvdb({"two-balls-n2000-r100-v1.vdb": [{"name": "density", "array": balls.astype(np.float32)}]},
                       folder)
    for n in (512, 4096):
        write_pyramid(folder / f"outofcore-n{n}-c64-top64-s0-v1.zarr", 32, 0, 16, 8)


def command_line(words: list[str]) -> list[str]:
    """The example as a subprocess argv: `volren` and `python` are this interpreter's environment's."""
    if words[0] == "volren":
        return [str(Path(sys.executable).with_name("volren")), *words[1:]]
    return [sys.executable, str(ROOT / words[1]), *words[2:]]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="print the examples and exit")
    ap.add_argument("--time", action="store_true", help="run and time each example")
    ap.add_argument("--only", action="append", default=[], help="only examples whose line contains this (repeatable)")
    ap.add_argument("--timeout", type=float, default=600.0, help="[s] stop an example after this long")
    args = ap.parse_args()
    examples = [w for w in readme_examples(README.read_text())
                if w[1] not in NOT_RUN and NEEDS_GPU not in shlex.join(w)
                and (not args.only or any(o in shlex.join(w) for o in args.only))]
    if args.list or not args.time:
        for n, words in enumerate(examples):
            print(f"{n:3d}  {shlex.join(words)}")
        return 0
    print("| # | example | exit | wall [s] |\n| ---: | --- | ---: | ---: |", flush=True)
    worst = 0
    with tempfile.TemporaryDirectory(prefix="volren-readme-") as scratch:
        stand_ins(Path(scratch))
        # compare reads what the renders wrote, wherever the README puts it
        for n, words in enumerate(sorted(examples, key=lambda w: w[1] == "compare")):
            start = time.perf_counter()
            try:
                code = subprocess.run(command_line(words), cwd=scratch, capture_output=True, text=True,
                                      timeout=args.timeout).returncode
            except subprocess.TimeoutExpired:
                code = "timeout"
            seconds = time.perf_counter() - start
            worst = max(worst, code != 0)
            print(f"| {n} | `{shlex.join(words)}` | {code} | {seconds:.0f} |", flush=True)
    return worst


if __name__ == "__main__":
    sys.exit(main())

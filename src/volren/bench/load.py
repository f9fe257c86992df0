"""Suite ``load``: seconds and peak memory to open volume files, against the reader library's own read (issue 21).

Each case is a ``LoadCase``: a name, a function writing its file(s) into a temporary folder, the volren load and the
bare reader's load. The ``.vdb`` cases (256^3, dense and 10%-sparse; 128^3 with ``--quick``) are written by OpenVDB
itself (Debian's ``python3-openvdb`` under the system ``/usr/bin/python3``) and timed as ``load_volume`` against
tinyvdb's open + read_grids + materialize_dense. Every load runs in a fresh subprocess, so that peak memory is that
process's ``ru_maxrss`` (resident set, KiB on Linux) with the interpreter and imports subtracted (a baseline process
that only imports); seconds are the median of ``repeats`` runs, each timed inside its process. Goal: volren's time
and peak memory at most 1.2x the reader's.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np

from volren.errors import VolrenError

SYSTEM_PYTHON = "/usr/bin/python3"
"""The interpreter that has Debian's pyopenvdb (not the virtual environment's)."""
FULL = {"size": 256, "repeats": 5}
QUICK = {"size": 128, "repeats": 3}
GOAL = 1.2
"""volren's time and peak memory over the bare reader's (issue 21: overhead at most 20%)."""

_WRITER = r"""
import json, sys
import numpy as np
import pyopenvdb as vdb

spec = json.load(sys.stdin)
for name, grids in spec.items():
    out = []
    for g in grids:
        grid = vdb.Vec3SGrid() if g.get("vec3") else vdb.FloatGrid()
        grid.name = g["name"]
        if g.get("array"):
            a = np.load(g["array"])  # volren's [z, y, x] (vec3: [z, y, x, 3]); pyopenvdb takes [x, y, z]
            grid.copyFromArray(np.ascontiguousarray(np.swapaxes(a, 0, 2)), ijk=tuple(g.get("ijk", (0, 0, 0))))
        if g.get("matrix") is not None:
            grid.transform = vdb.createLinearTransform(g["matrix"])
        grid.saveFloatAsHalf = bool(g.get("half", False))
        out.append(grid)
    vdb.write(name, out)
"""


def write_with_openvdb(files: dict[str, list[dict[str, Any]]], folder: Path) -> None:
    """Write ``.vdb`` files with OpenVDB itself: ``files`` maps a file name to its grids, each a dict with ``name``,
    ``array`` (float32 ``[z, y, x]``, or ``[z, y, x, 3]`` with ``vec3``; None: an empty grid), ``ijk`` (index of
    element [0, 0, 0]), ``matrix`` (OpenVDB's 4x4 row-vector index-to-world map; None: voxel size 1) and ``half``.
    Voxels equal to the background 0 are inactive (pyopenvdb's copyFromArray), so zeros make a grid sparse."""
    spec = {}
    for k, (file, grids) in enumerate(files.items()):
        spec[str(folder / file)] = []
        for j, g in enumerate(grids):
            entry = {key: v for key, v in g.items() if key != "array"}
            if g.get("array") is not None:
                entry["array"] = str(folder / f".array-{k}-{j}.npy")
                np.save(entry["array"], np.asarray(g["array"], dtype=np.float32))
            spec[str(folder / file)].append(entry)
    try:
        done = subprocess.run([SYSTEM_PYTHON, "-c", _WRITER], input=json.dumps(spec), capture_output=True, text=True,
                              timeout=600)
    except FileNotFoundError:
        raise VolrenError(f"{SYSTEM_PYTHON} is missing: writing .vdb files needs Debian's python3-openvdb") from None
    if done.returncode:
        raise VolrenError(f"writing .vdb files with {SYSTEM_PYTHON} (pyopenvdb) failed: "
                          f"{done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.returncode}")
    for file in folder.glob(".array-*.npy"):
        file.unlink()

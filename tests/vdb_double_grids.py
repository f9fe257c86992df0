"""The OpenVDB double grids of tests/test_vdb_double.py (issue 45 item 3), as written to ``tests/data/openvdb/`` by
OpenVDB 10's C++ library (``write_grids.cc`` there: Debian's pyopenvdb wraps no DoubleGrid). The arrays are built
here, so the tests compare what volren reads with what was written.

Regenerate (after building write_grids.cc as its header says):
``python tests/vdb_double_grids.py path/to/write_grids`` (writes tests/data/openvdb/*.vdb).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

FOLDER = Path(__file__).parent / "data" / "openvdb"
SCALE = (0.5, 0.25, 2.0)
"""voxel size [m] of sim.vdb's grids"""
SHAPE = (14, 12, 24)
"""[z, y, x] of sim.vdb's grids: every voxel active, so the active box is the array"""
IJK = (116, 5, 3)
"""file index (x, y, z) of element [0, 0, 0]: the constant interior's 8^3 blocks at index x 120-127 and 128-135
(array x 4-11 and 12-19, y 3-10, z 5-12) lie in two lower internal nodes (128 voxels wide) and are stored as tiles"""
CENTRED = tuple(-np.array(SCALE) * (np.array(IJK) + (np.array(SHAPE[::-1]) - 1) / 2))
"""the translation that centres the grid, as ``--spacing 0.5,0.25,2 --units m`` centres a .npy"""
MARKER = (9, 1, 20)
"""[z, y, x] of the one voxel of density 7 (in a leaf)"""


def _density() -> np.ndarray:
    """0.5 inside; a shell (z < 2, x >= 22) of values such as 0.05 + 10/31 that float32 does not hold exactly."""
    z, y, x = np.indices(SHAPE)
    out = np.full(SHAPE, 0.5)
    shell = (z < 2) | (x >= 22)
    out[shell] = 0.05 + ((x + 3 * y + 7 * z) % 29)[shell] / 31.0
    out[MARKER] = 7.0
    return out


DENSITY = _density()
"""float64 [z, y, x]: sim.vdb's ``density`` (a DoubleGrid)"""
TEMPERATURE = 300.0 + 1500.0 * DENSITY / 7.0
"""float64: sim.vdb's ``temperature`` (a DoubleGrid), kelvin"""
_RNG = np.random.default_rng(45)
COUNT = _RNG.integers(1, 10, (8, 8, 16)).astype(np.float64)
"""choices.vdb's ``count`` (an Int32Grid: not a density volren reads)"""
HEAT = _RNG.uniform(0.1, 1.0, (8, 8, 16))
"""choices.vdb's ``heat`` (DoubleGrid), index (0, 0, 0) on, voxel size 0.1"""
FLAME = _RNG.uniform(0.1, 1.0, (8, 8, 16))
"""choices.vdb's ``flame`` (FloatGrid: float32 in the file)"""
HUGE = np.full((8, 8, 8), 0.5)
HUGE[3, 4, 5] = 1e300
"""huge.vdb's ``density`` (DoubleGrid): one value beyond float32's range"""

FILES: dict[str, list[tuple]] = {
    # name, type, array, ijk, scale, translation, half
    "sim.vdb": [("density", "double", DENSITY, IJK, SCALE, CENTRED, 0),
                ("temperature", "double", TEMPERATURE, IJK, SCALE, CENTRED, 0)],
    "choices.vdb": [("heat", "double", HEAT, (0, 0, 0), (0.1,) * 3, (0.0,) * 3, 0),
                    ("flame", "float", FLAME, (0, 0, 0), (0.1,) * 3, (0.0,) * 3, 0),
                    ("count", "int32", COUNT, (0, 0, 0), (0.1,) * 3, (0.0,) * 3, 0)],
    "half-double.vdb": [("density", "double", HEAT, (0, 0, 0), (0.1,) * 3, (0.0,) * 3, 1)],
    "huge.vdb": [("density", "double", HUGE, (0, 0, 0), (0.1,) * 3, (0.0,) * 3, 0)],
}


def write(writer: str, folder: Path = FOLDER) -> None:
    """Write ``FILES`` into ``folder`` with the compiled ``write_grids.cc``."""
    with tempfile.TemporaryDirectory() as tmp:
        lines = []
        for file, grids in FILES.items():
            lines.append(f"out {folder / file}")
            for k, (name, kind, array, ijk, scale, translation, half) in enumerate(grids):
                raw = Path(tmp) / f"{file}-{k}.raw"
                np.ascontiguousarray(array, dtype="<f8").tofile(raw)
                nz, ny, nx = array.shape
                lines.append(" ".join(str(v) for v in (
                    "grid", name, kind, nx, ny, nz, *ijk, *(repr(float(s)) for s in scale),
                    *(repr(float(t)) for t in translation), half, raw)))
            lines.append("end")
        (Path(tmp) / "spec").write_text("\n".join(lines) + "\n")
        subprocess.run([writer, str(Path(tmp) / "spec")], check=True)


if __name__ == "__main__":
    write(sys.argv[1])

"""Suite ``load``: seconds and peak memory to open volume files, against the reader library's own read (issue 21).

Each case is a ``LoadCase`` in ``CASES``: a name, a function writing its file into a temporary folder, the volren
load and the bare reader's load (other formats add theirs). The ``.vdb`` cases (256^3, dense and 10%-sparse; 128^3
with ``--quick``) are written by OpenVDB itself (Debian's ``python3-openvdb`` under the system ``/usr/bin/python3``)
and timed as ``load_volume`` (a validated float32 ``[z, y, x]`` grid) against tinyvdb's open + read_grids + its
decoded leaf values joined into one array (tinyvdb's own ``materialize_dense`` drops leaves, see
``volren.data.vdb``). Every load runs in a fresh subprocess that first imports both sides' modules; peak memory is
its peak resident set during the open (Linux ``VmHWM``, reset just before) minus the resident set before it, seconds
the median of ``repeats`` runs timed inside the processes. Goal: volren's time and peak memory at most 1.2x the
reader's."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from volren.bench import Suite
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
        for lo, hi, value, active in g.get("fills", ()):
            grid.fill(tuple(lo), tuple(hi), value, active)
        if g.get("matrix") is not None:
            grid.transform = vdb.createLinearTransform(g["matrix"])
        grid.saveFloatAsHalf = bool(g.get("half", False))
        out.append(grid)
    vdb.write(name, out)
"""


def openvdb_available() -> bool:
    """Whether the system Python can import pyopenvdb (Debian's python3-openvdb) to write test and benchmark files."""
    try:
        return subprocess.run([SYSTEM_PYTHON, "-c", "import pyopenvdb"], capture_output=True).returncode == 0
    except FileNotFoundError:
        return False


def write_with_openvdb(files: dict[str, list[dict[str, Any]]], folder: Path) -> None:
    """Write ``.vdb`` files with OpenVDB itself: ``files`` maps a file name to its grids, each a dict with ``name``,
    ``array`` (float32 ``[z, y, x]``, or ``[z, y, x, 3]`` with ``vec3``; None: an empty grid), ``ijk`` (index of
    element [0, 0, 0]), ``matrix`` (OpenVDB's 4x4 row-vector index-to-world map; None: voxel size 1), ``half`` and
    ``fills`` (``grid.fill`` boxes ``(lo, hi, value, active)`` in index (x, y, z), after the array).
    Voxels equal to the background 0 are inactive (pyopenvdb's copyFromArray), so zeros make a grid sparse; constant
    8^3 blocks of the array and filled whole nodes are stored as tiles, not leaves."""
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


def _smooth_field(n: int, span: float = 3.0 * np.pi) -> np.ndarray:
    """float32 ``[z, y, x]`` in [0.05, 1.05]: a product of sines, positive everywhere (every voxel active)."""
    t = np.linspace(0.0, span, n, dtype=np.float32)
    return (0.55 + 0.5 * np.sin(t)[:, None, None] * np.sin(1.3 * t)[None, :, None] * np.sin(0.7 * t)[None, None, :])


def write_dense_vdb(folder: Path, n: int) -> Path:
    write_with_openvdb({"dense.vdb": [{"name": "density", "array": _smooth_field(n)}]}, folder)
    return folder / "dense.vdb"


def write_sparse_vdb(folder: Path, n: int) -> Path:
    """10% of the n^3 voxels active, in blobs spread over the whole box (smoke-like): the active box nearly fills n^3
    (120 x 125 x 123 at n = 128), most of it background between the blobs."""
    field = _smooth_field(n, 6.0 * np.pi)
    field[field < np.quantile(field, 0.9)] = 0.0  # zeros are inactive
    write_with_openvdb({"sparse.vdb": [{"name": "density", "array": field}]}, folder)
    return folder / "sparse.vdb"


def volren_open(path: Path) -> np.ndarray:
    """volren's reader, one pyramid level read whole for a .zarr (the level that fits, as zarr's side reads it; not
    streamed: this suite times reading a level)."""
    from volren.data.loaders import load_volume

    return load_volume(path, **({"stream": False} if path.suffix == ".zarr" else {})).density


def tinyvdb_open(path: Path) -> np.ndarray:
    """tinyvdb's own read: open, decompress every grid, and its density grid's decoded leaf values as one array (the
    least work that yields every voxel; tinyvdb 0.9.0's ``materialize_dense`` keeps only 64 leaves per lower node)."""
    import tinyvdb

    with tinyvdb.open(str(path)) as f:
        f.read_grids()
        tree = f.grid(0).tree
        return np.frombuffer(b"".join(n.data for n in (tree.node(i) for i in range(tree.num_nodes)) if n.level == 3),
                             np.float32)


ZARR_BUDGET = 1 << 30
"""[bytes] volren's default OME-Zarr memory budget (`volren.data.omezarr.DEFAULT_MEMORY_BUDGET`), which the bare
reader applies too"""


def write_omezarr(folder: Path, n: int) -> Path:
    """An OME-Zarr pyramid written by ome-zarr (levels 0 and 1, every axis halved) of float32 ``[z, y, x]`` with side
    ``25 n / 8``: 400^3 = 256 MiB at n = 128 (``--quick``: level 0 fits the 1 GiB budget), 800^3 = 2 GiB at n = 256
    (level 1, 256 MiB, is chosen)."""
    import zarr
    from ome_zarr.writer import write_multiscale

    field = _smooth_field(25 * n // 8)
    axes = [{"name": a, "type": "space", "unit": "micrometer"} for a in "zyx"]
    path = folder / "image.zarr"  # ome-zarr derives each level's scale from the shapes
    write_multiscale([field, field[::2, ::2, ::2]], zarr.open_group(str(path), mode="w"), axes=axes)
    return path


def zarr_open(path: Path) -> np.ndarray:
    """zarr's own read of the level volren picks: the finest whose float32 voxels fit ``ZARR_BUDGET``."""
    import zarr

    group = zarr.open_group(str(path), mode="r")
    levels = [group[d["path"]] for d in group.attrs["ome"]["multiscales"][0]["datasets"]]
    return next(a for a in levels if 4 * a.size <= ZARR_BUDGET)[...]


@dataclass(frozen=True)
class LoadCase:
    """One row: a file written into a temporary folder, opened by volren and by the bare reader library."""

    name: str
    write: Callable[[Path, int], Path]
    """(folder, voxels per axis) -> the file to open"""
    volren: Callable[[Path], np.ndarray]
    reader: Callable[[Path], np.ndarray]
    reader_name: str


CASES = [
    LoadCase("vdb dense", write_dense_vdb, volren_open, tinyvdb_open, "tinyvdb"),
    LoadCase("vdb 10% sparse", write_sparse_vdb, volren_open, tinyvdb_open, "tinyvdb"),
    LoadCase("ome-zarr level", write_omezarr, volren_open, zarr_open, "zarr"),
]
"""The suite's rows; other formats (sequences, OME-Zarr) add a LoadCase here."""


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(field + ":"))


def child() -> None:
    """In a fresh process (``python -c 'from volren.bench.load import child; child()' CASE SIDE PATH``): import both
    sides' modules, reset the peak resident set (``/proc/self/clear_refs``: 5), then time one open and print JSON with
    the seconds and the peak resident set's rise over the resident set before the open [KiB] (Linux ``VmHWM`` and
    ``VmRSS``)."""
    import tinyvdb  # noqa: F401  (both sides import the same modules, so the baseline is the same)
    import zarr  # noqa: F401  (the OME-Zarr row: zarr's own read and volren's reader)

    import volren.data.loaders
    import volren.data.omezarr
    import volren.data.vdb  # noqa: F401

    name, side, path = sys.argv[1:4]
    case = next(c for c in CASES if c.name == name)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = _status_kib("VmRSS")
    start = time.perf_counter()
    data = (case.volren if side == "volren" else case.reader)(Path(path))
    seconds = time.perf_counter() - start
    peak = _status_kib("VmHWM") - before
    print(json.dumps({"seconds": seconds, "peak_kib": peak, "shape": list(data.shape),
                      "sum": float(data.sum(dtype=np.float64))}))


def _measure(case: LoadCase, side: str, path: Path, repeats: int) -> dict[str, Any]:
    runs = []
    for _ in range(repeats):
        done = subprocess.run([sys.executable, "-c", "from volren.bench.load import child; child()", case.name, side,
                               str(path)], capture_output=True, text=True, timeout=600)
        if done.returncode:
            raise VolrenError(f"bench load: {case.name} ({side}) failed: {done.stderr.strip().splitlines()[-1:]}")
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return {"seconds": statistics.median(r["seconds"] for r in runs),
            "peak_mib": statistics.median(r["peak_kib"] for r in runs) / 1024, "shape": runs[0]["shape"],
            "sum": runs[0]["sum"]}


def run_config(cfg: dict[str, Any], cases: list[LoadCase] | None = None) -> dict[str, Any]:
    rows, summary = [], []
    with tempfile.TemporaryDirectory(prefix="volren-bench-load-") as tmp:
        for case in CASES if cases is None else cases:
            folder = Path(tmp) / case.name.replace(" ", "_").replace("%", "pct")
            folder.mkdir()
            path = case.write(folder, cfg["size"])
            ours, reader = (_measure(case, side, path, cfg["repeats"]) for side in ("volren", "reader"))
            if not np.isclose(ours["sum"], reader["sum"], rtol=1e-5):  # inactive voxels are 0: the same total
                raise VolrenError(f"bench load: {case.name}: volren read {ours['shape']} (sum {ours['sum']}), "
                                  f"{case.reader_name} {reader['shape']} (sum {reader['sum']})")
            dense = np.prod(ours["shape"])
            files = [f for f in path.rglob("*") if f.is_file()] if path.is_dir() else [path]  # a .zarr is a folder
            rows.append({"case": case.name, "reader": case.reader_name,
                         "file_mib": sum(f.stat().st_size for f in files) / 2**20,
                         "shape": "x".join(str(v) for v in ours["shape"][::-1]), "voxels": int(dense),
                         "volren_s": ours["seconds"], "reader_s": reader["seconds"],
                         "volren_peak_mib": ours["peak_mib"], "reader_peak_mib": reader["peak_mib"],
                         "dense_mib": dense * 4 / 2**20})
            time_ratio = ours["seconds"] / reader["seconds"]
            memory_ratio = ours["peak_mib"] / reader["peak_mib"] if reader["peak_mib"] > 0 else None  # tiny files
            met = time_ratio <= GOAL and (memory_ratio is None or memory_ratio <= GOAL)
            summary.append({"case": case.name, "time_ratio": time_ratio, "memory_ratio": memory_ratio,
                            "goal": GOAL, "met": "yes" if met else "no"})
    columns = [
        ("case", "case", "s"), ("shape", "dense box (x, y, z)", "s"), ("file_mib", "file [MiB]", ".1f"),
        ("reader", "reader", "s"), ("reader_s", "reader [s]", ".3f"), ("volren_s", "volren [s]", ".3f"),
        ("reader_peak_mib", "reader peak RSS rise [MiB]", ".1f"),
        ("volren_peak_mib", "volren peak RSS rise [MiB]", ".1f"), ("dense_mib", "dense float32 [MiB]", ".1f"),
    ]
    summary_columns = [("case", "case", "s"), ("time_ratio", "volren / reader time", ".3f"),
                       ("memory_ratio", "volren / reader peak memory", ".3f"), ("goal", "goal (at most)", ".2f"),
                       ("met", "met", "s")]
    settings = {**cfg, "memory": "peak resident set (VmHWM, reset before the open) minus the resident set before it, "
                "in a fresh subprocess",
                "seconds": "median over repeats, each timed inside its subprocess"}
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(QUICK if quick else FULL)


SUITE = Suite("load", "seconds and peak memory to open volume files against the reader library's own (issue 21)",
              run)

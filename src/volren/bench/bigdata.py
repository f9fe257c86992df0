"""Suite ``bigdata``, part (a) sparse (issue 41): a sparse ``.vdb`` loaded through the public path
(`volren.data.loaders.load_volume`, as ``volren render --volume FILE``) against the same voxels dense.

Files, written by OpenVDB itself (Debian's pyopenvdb under the system ``/usr/bin/python3``, fed block by block, so no
dense copy of the index box is ever made) and cached on disk (`cache_folder`):

- ``two-balls``: the issue's file: two balls of radius R voxels centred 0.15 n from opposite corners of an n^3 index
  box, density 1 - (r / R)^2 inside (`volren.bench.bricks.two_balls_regions`); the issue's n = 2000, R = 100 holds
  2 x 4/3 pi R^3 = 8.38 M active voxels.
- ``smoke``: a rising plume of overlapping puffs widening with height, plus detached puffs above it, modulated by
  two octaves of plane-wave noise and thresholded (holes and filaments), in an n^3 index box (issue: 2048^3, a few
  percent active); made chunk by chunk (`smoke_blocks`).

Each file (and its dense twin, a ``.npy`` of the file's active box, where that box holds at most
``dense_max_voxels``) is loaded in a fresh subprocess (`child`) that first imports volren and renders a tiny volume
with every method (kernels loaded), so that the resident set before the load is the interpreter, its imports and the
kernels: peak memory is the peak resident set during the load (Linux ``VmHWM``, reset just before) minus the
resident set before it; after the load the process renders the volume (``methods``: dssrm at its default quality,
and its maximum intensity projection) from the camera ``volren render`` frames, one mono view of ``size``: the first
frame's wall time (upload, light map, march) and the fastest of the next ``repeats`` frames (the light map kept, as
``volren render --frames`` and the server keep it for a still volume). The goal (summary table): peak load
memory at most `MEMORY_GOAL` x the active voxels' float32 bytes, load time, first frame and ms per frame at most
`TIME_GOAL` x the dense twin's; the images' largest difference to the dense twin's is reported beside. On CUDA the
resident set is the host's: the rise of Warp's memory pool's high-water mark over the load and frames is reported
beside it (``device_peak_mib``).

Part (b), out-of-core (`run_outofcore`, its own table): a uint8 OME-Zarr pyramid of fine structure (`pyramid_block`,
`write_pyramid`; the issue's 4096^3, 64 GiB as float32), cached like the files above, opened within a memory budget
(it streams: `volren.stream`) in a fresh subprocess (`outofcore_child`) and rendered by DSSRM with ``stream_wait``
False (as ``serve``) from a close-up: time to the first (coarse) frame and to full refinement, bytes read per frame
while orbiting, the peak resident set against the budget plus 1 GiB.

Until the sparse reader lands, ``load_volume`` densifies a ``.vdb`` over its active box (and refuses a box over
`volren.data.vdb.MAX_DENSE_VOXELS`): a refused load is a row saying so, not a failure of the suite.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np

from volren.bench import Suite, sized
from volren.bench.bricks import two_balls_regions
from volren.bench.load import SYSTEM_PYTHON, _status_kib
from volren.errors import VolrenError
from volren.progress import case_done

MAX_DENSE = 1 << 30
"""[voxels] today's dense reader's limit (`volren.data.vdb.MAX_DENSE_VOXELS`): the dense twin's default cap"""
FULL = {"files": ["two-balls", "smoke"], "two_balls": [2000, 100], "smoke": 2048, "seed": 0,
        "size": [1920, 1080], "methods": ["dssrm", "mip"], "repeats": 10, "dense_max_voxels": MAX_DENSE,
        "cache": None, "outofcore": 4096, "outofcore_budget_mib": 2048, "outofcore_size": [1920, 1080],
        "outofcore_chunk": 64, "outofcore_coarsest": 64, "orbit_frames": 16, "orbit_deg": 5.0,
        "refine_timeout_s": 300.0, "reference_max_voxels": 1 << 30, "outofcore_quality": "interactive"}
QUICK = {"files": ["two-balls", "smoke"], "two_balls": [800, 40], "smoke": 512, "seed": 0,
         "size": [256, 144], "methods": ["dssrm", "mip"], "repeats": 5, "dense_max_voxels": MAX_DENSE,
         "cache": None, "outofcore": 512, "outofcore_budget_mib": 384, "outofcore_size": [256, 144],
         "outofcore_chunk": 64, "outofcore_coarsest": 64, "orbit_frames": 8, "orbit_deg": 5.0,
         "refine_timeout_s": 120.0, "reference_max_voxels": 1 << 27, "outofcore_quality": "interactive"}
"""Part (b) out-of-core (``outofcore``: level 0's edge n, None to leave part (b) out; the pyramid's ``chunk`` and
``coarsest`` edge; the ``budget`` [MiB]; the image ``size``; the orbit: ``orbit_frames`` of ``orbit_deg`` each;
frames of the still camera stop refining at ``refine_timeout_s``; quick's budget, 384 MiB (level 0 is 512 MiB as
float32: it streams), holds the close-up's 7932 wanted bricks (149 MiB a half; 64 MiB would hold 1707: level 0
never drawn); a dense reference render of level 0 where it holds
at most ``reference_max_voxels``; DSSRM at ``outofcore_quality``: ``interactive``, as a served view, since at
``default`` its light map has half the finest level's resolution (256^3 nodes for a 512^3 level 0), recomputed at
every frame that brings bricks: minutes a frame on a 2-core CPU): `run_outofcore`."""
MEMORY_GOAL = 1.3
"""peak resident set of a load over the active voxels' float32 bytes (issue 41)"""
TIME_GOAL = 1.2
"""load seconds and ms per frame over the dense twin's (issue 41)"""
RENDER_SETTINGS = {"dssrm": {}, "mip": {"mode": "mip"}}
"""the ``methods`` a configuration names: DSSRM settings on top of its ``default`` quality (``volren render``'s)"""
QUALITY = "default"
FRAME_FIGURES = ("first_ms", "frame_ms", "frame_median_ms", "upload_ms", "light_map_ms")
"""per method: the first frame's wall time [ms] (upload, light map and march) and its upload and light-map passes,
the fastest and median of the next ``repeats`` frames (the light map kept, as ``volren render --frames`` and the
server keep it for a still volume: the passes' sum but upload and readback)"""
MAKER_VERSION = 1
"""part of every cached file's name: raise it when a maker's output changes, so old files are not reused"""
CHUNK = 64
"""[voxels] edge of the chunks `smoke_blocks` makes and writes"""


def cache_folder(cfg_cache: str | None = None) -> Path:
    """Where the suite's files are kept between runs: the configuration's ``cache``, else ``VOLREN_BENCH_CACHE``,
    else ``$XDG_CACHE_HOME/volren/bench`` (default ``~/.cache/volren/bench``)."""
    if cfg_cache:
        return Path(cfg_cache)
    if os.environ.get("VOLREN_BENCH_CACHE"):
        return Path(os.environ["VOLREN_BENCH_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "volren" / "bench"


Block = tuple[tuple[int, int, int], np.ndarray]
"""(index (z, y, x) of the block's first voxel, float32 ``[z, y, x]`` block); the grid is 0 outside the blocks"""


def two_balls_blocks(n: int, radius: int) -> Iterator[Block]:
    """The issue's two balls (`two_balls_regions`); refused where their blocks would overlap or leave the box."""
    if 0.7 * n <= 2 * radius + 3 or 0.15 * n < radius + 1:
        raise VolrenError(f"bigdata: two balls of radius {radius} do not fit apart in a {n}^3 box "
                          "(0.15 n > R + 1 needed)")
    yield from two_balls_regions(n, radius)


def two_balls_active(n: int, radius: int) -> float:
    """The closed form: 2 x 4/3 pi R^3 active voxels."""
    return 2.0 * 4.0 / 3.0 * math.pi * radius**3


def smoke_puffs(n: int, seed: int) -> np.ndarray:
    """(P, 4) puffs (x, y, z centre, radius) [voxels] of the smoke: a plume rising along y (up) from near the bottom
    of the box, wandering in x and z, its radius growing from 0.05 n to 0.15 n (+-15%); and 8 detached puffs
    (radius 0.04 n to 0.08 n) around and above it."""
    rng = np.random.default_rng(seed)
    p1, p2 = rng.uniform(0.0, 2.0 * np.pi, 2)
    puffs, h = [], 0.08
    while h < 0.76:
        r = 0.05 + 0.14 * (h - 0.08)
        puffs.append((0.5 + 0.07 * math.sin(2.0 * math.pi * 1.1 * h + p1), h,
                      0.5 + 0.07 * math.sin(2.0 * math.pi * 0.8 * h + p2), r * rng.uniform(0.85, 1.15)))
        h += 0.4 * r
    for _ in range(8):
        angle, dist = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(0.18, 0.32)
        puffs.append((0.5 + dist * math.cos(angle), rng.uniform(0.6, 0.88), 0.5 + dist * math.sin(angle),
                      rng.uniform(0.04, 0.08)))
    return np.asarray(puffs, dtype=np.float64) * n


def smoke_waves(n: int, seed: int) -> np.ndarray:
    """(W, 5) plane waves (kx, ky, kz [radians per voxel], phase, amplitude): 6 of 3 to 8 periods across the box and
    6 of 12 to 30 at half the amplitude."""
    rng = np.random.default_rng(seed + 1)
    out = []
    for count, lo, hi, amplitude in ((6, 3.0, 8.0, 1.0), (6, 12.0, 30.0, 0.5)):
        for _ in range(count):
            k = rng.normal(size=3)
            k *= 2.0 * np.pi * rng.uniform(lo, hi) / n / np.linalg.norm(k)
            out.append((*k, rng.uniform(0.0, 2.0 * np.pi), amplitude))
    return np.asarray(out)


def smoke_blocks(n: int, seed: int, chunk: int = CHUNK) -> Iterator[Block]:
    """The smoke of an n^3 index box, chunk by chunk (only chunks that meet a puff, only blocks with a voxel > 0):
    density max over the puffs of 1 - (d / r)^2, times 0.55 + 0.45 noise (noise in [-1, 1]: `smoke_waves` at the
    voxel centres), less 0.12, clipped at 0. Every value depends only on the voxel's global index."""
    puffs, waves = smoke_puffs(n, seed), smoke_waves(n, seed)
    weight = waves[:, 4].sum()
    for z0 in range(0, n, chunk):
        for y0 in range(0, n, chunk):
            for x0 in range(0, n, chunk):
                lo = np.array([x0, y0, z0], dtype=np.float64)
                hi = np.minimum(lo + chunk, n)
                nearest = np.clip(puffs[:, :3], lo + 0.5, hi - 0.5)  # the chunk's voxel centres span [lo+.5, hi-.5]
                near = puffs[np.sum((nearest - puffs[:, :3]) ** 2, axis=1) < puffs[:, 3] ** 2]
                if not len(near):
                    continue
                x, y, z = (np.arange(a, b, dtype=np.float64) + 0.5 for a, b in zip(lo, hi, strict=True))
                falloff = np.zeros((len(z), len(y), len(x)))
                for cx, cy, cz, r in near:
                    d2 = ((z - cz)[:, None, None] ** 2 + (y - cy)[None, :, None] ** 2
                          + (x - cx)[None, None, :] ** 2) / r**2
                    np.maximum(falloff, 1.0 - d2, out=falloff)
                if not (falloff > 0.0).any():
                    continue
                noise = np.zeros_like(falloff)
                for kx, ky, kz, phase, amplitude in waves:
                    noise += amplitude * np.sin((kz * z)[:, None, None] + (ky * y)[None, :, None]
                                                + (kx * x)[None, None, :] + phase)
                block = np.maximum(falloff * (0.55 + 0.45 * noise / weight) - 0.12, 0.0).astype(np.float32)
                block[falloff <= 0.0] = 0.0
                if block.any():
                    yield (z0, y0, x0), block


MAKERS: dict[str, Callable[[dict[str, Any]], tuple[str, int, Callable[[], Iterator[Block]]]]] = {
    "two-balls": lambda cfg: (f"two-balls-n{cfg['two_balls'][0]}-r{cfg['two_balls'][1]}", cfg["two_balls"][0],
                              lambda: two_balls_blocks(*cfg["two_balls"])),
    "smoke": lambda cfg: (f"smoke-n{cfg['smoke']}-s{cfg['seed']}", cfg["smoke"],
                          lambda: smoke_blocks(cfg["smoke"], cfg["seed"])),
}
"""file kind -> (configuration -> (cache name, index box edge n, the blocks' generator))"""

_STREAM_WRITER = r"""
import json, sys
import numpy as np
import pyopenvdb as vdb

stdin = sys.stdin.buffer
head = json.loads(stdin.readline())
grid = vdb.FloatGrid()
grid.name = head["name"]
while True:
    line = stdin.readline()
    if not line.strip():
        break
    block = json.loads(line)
    z, y, x = block["shape"]
    a = np.frombuffer(stdin.read(4 * z * y * x), np.float32).reshape(z, y, x)
    grid.copyFromArray(np.ascontiguousarray(a.transpose(2, 1, 0)), ijk=tuple(block["ijk"]))  # OpenVDB: [x, y, z]
grid.saveFloatAsHalf = False
vdb.write(head["path"], [grid])
lo, hi = grid.evalActiveVoxelBoundingBox()
print(json.dumps({"active_voxels": grid.activeVoxelCount(), "lo": list(lo), "hi": list(hi),
                  "leaves": grid.leafCount()}))
"""


def write_blocks(path: Path, blocks: Iterator[Block]) -> dict[str, Any]:
    """Write a float grid ``density`` of ``blocks`` (disjoint) with OpenVDB, streamed to it one block at a time:
    zeros are inactive (pyopenvdb's copyFromArray). Returns OpenVDB's active voxel count and active box (x, y, z,
    inclusive), checked against the blocks' own (else refused: the file would not be the data asked for)."""
    active, lo, hi = 0, np.full(3, np.iinfo(np.int64).max), np.full(3, -1)
    with tempfile.TemporaryFile() as err:
        try:
            proc = subprocess.Popen([SYSTEM_PYTHON, "-c", _STREAM_WRITER], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=err)
        except FileNotFoundError:
            raise VolrenError(f"{SYSTEM_PYTHON} is missing: writing .vdb files needs Debian's "
                              "python3-openvdb") from None
        try:
            proc.stdin.write(json.dumps({"name": "density", "path": str(path)}).encode() + b"\n")
            for (z, y, x), block in blocks:
                nz = np.nonzero(block)
                if not len(nz[0]):
                    continue
                active += len(nz[0])
                first = np.array([x + nz[2].min(), y + nz[1].min(), z + nz[0].min()])
                last = np.array([x + nz[2].max(), y + nz[1].max(), z + nz[0].max()])
                lo, hi = np.minimum(lo, first), np.maximum(hi, last)
                proc.stdin.write(json.dumps({"ijk": [x, y, z], "shape": list(block.shape)}).encode() + b"\n")
                proc.stdin.write(np.ascontiguousarray(block, dtype=np.float32).tobytes())
            proc.stdin.write(b"\n")
            proc.stdin.close()
        except BrokenPipeError:
            pass  # the writer failed: its message is in err
        out = proc.stdout.read().decode()
        proc.wait()
        err.seek(0)
        message = err.read().decode().strip()
    if proc.returncode:
        raise VolrenError(f"writing {path.name} with {SYSTEM_PYTHON} (pyopenvdb) failed: "
                          f"{message.splitlines()[-1] if message else proc.returncode}")
    written = json.loads(out.strip().splitlines()[-1])
    if written["active_voxels"] != active or written["lo"] != lo.tolist() or written["hi"] != hi.tolist():
        raise VolrenError(f"{path.name}: OpenVDB holds {written['active_voxels']} active voxels in {written['lo']}.."
                          f"{written['hi']}, the blocks {active} in {lo.tolist()}..{hi.tolist()}")
    return written


def make_file(kind: str, cfg: dict[str, Any], *, dense: bool | None = None) -> dict[str, Any]:
    """The ``.vdb`` of file ``kind`` (`MAKERS`) for the configuration, from the cache or written there (with a JSON
    sidecar of its figures), and its dense twin (a ``.npy`` of the file's active box, float32 ``[z, y, x]``, written
    through a memory map) when ``dense`` (None: when the box holds at most ``dense_max_voxels``). Returns the
    sidecar: ``path``, ``dense_path`` (or None), ``n``, ``active_voxels``, ``lo`` / ``hi`` (x, y, z inclusive),
    ``file_bytes``, ``write_s``."""
    if kind not in MAKERS:
        raise VolrenError(f"bigdata: unknown file {kind!r}: choose from {', '.join(MAKERS)}")
    name, n, blocks = MAKERS[kind](cfg)
    folder = cache_folder(cfg.get("cache"))
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"{name}-v{MAKER_VERSION}"
    path, sidecar, twin = stem.with_suffix(".vdb"), stem.with_suffix(".json"), Path(f"{stem}-dense.npy")
    if path.exists() and sidecar.exists():
        info = json.loads(sidecar.read_text())
    else:
        start = time.perf_counter()
        tmp = path.with_name(f".{path.name}.tmp")
        written = write_blocks(tmp, blocks())
        os.replace(tmp, path)
        info = {"kind": kind, "n": n, "active_voxels": written["active_voxels"], "lo": written["lo"],
                "hi": written["hi"], "leaves": written["leaves"], "file_bytes": path.stat().st_size,
                "write_s": time.perf_counter() - start}
        sidecar.write_text(json.dumps(info, indent=1) + "\n")
        case_done(f"wrote {path.name}: {info['active_voxels']:,} active voxels, {info['file_bytes'] / 2**20:.1f} MiB")
    lo, hi = np.array(info["lo"]), np.array(info["hi"])
    box = hi - lo + 1
    if dense is None:
        dense = int(np.prod(box)) <= cfg["dense_max_voxels"]
    if dense and not twin.exists():
        tmp = twin.with_name(f".{twin.name}.tmp.npy")
        out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=tuple(int(v) for v in box[::-1]))
        for (z, y, x), block in blocks():
            first = np.array([x, y, z]) - lo  # the block's first voxel in the box (x, y, z); it may stick out
            a, b = np.maximum(first, 0), np.minimum(first + block.shape[::-1], box)
            out[a[2]:b[2], a[1]:b[1], a[0]:b[0]] = block[a[2] - first[2]:b[2] - first[2],
                                                         a[1] - first[1]:b[1] - first[1],
                                                         a[0] - first[0]:b[0] - first[0]]
        out.flush()
        del out
        os.replace(tmp, twin)
    return {**info, "path": str(path), "dense_path": str(twin) if dense else None}


def child() -> None:
    """In a fresh process (``python -c 'from volren.bench.bigdata import child; child()'``, a JSON spec on stdin:
    ``path``, ``options`` of `volren.load`, ``methods``, ``size``, ``repeats``, ``images`` folder, ``tag``): import
    volren and render a tiny volume with every method (so that its modules and kernels are resident before the
    baseline), reset the peak resident set, time `volren.load` of the file, then time the methods' frames; print JSON
    with the load seconds, the peak resident set's rise over the resident set before the load during the load and
    over the whole run [KiB], the density's bytes and shape (x, y, z), the fastest and median frame [ms] per method;
    each method's image is saved as ``images/<tag>-<method>.npy``. A load volren refuses prints its message as
    ``refused``."""
    import volren as vr
    import volren.data.loaders
    import volren.data.vdb  # the .vdb reader's modules: the same baseline for both sides
    from volren._api import framed_views
    from volren.bench import NOT_PASSES
    from volren.presets import quality_config
    from volren.render import METHODS as RENDERERS
    from volren.scene import Scene, Volume

    spec = json.loads(sys.stdin.read())
    width, height = spec["size"]
    renderers = {m: RENDERERS["dssrm"][0](quality_config("dssrm", QUALITY, **RENDER_SETTINGS[m]), device=spec["device"])
                 for m in spec["methods"]}
    tiny = Scene((Volume(np.full((8, 8, 8), 0.5, np.float32)),))
    for r in renderers.values():  # kernels compiled and loaded before the baseline
        r.render(tiny, framed_views(tiny, None, "mono", 16, 16))
    import tinyvdb  # noqa: F401
    import warp as wp
    from numcodecs import blosc  # noqa: F401  (the .vdb reader's tile values)

    pool = spec["device"].startswith("cuda") and wp.is_mempool_enabled(spec["device"])
    pool_before = wp.get_mempool_used_mem_current(spec["device"]) if pool else None
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = _status_kib("VmRSS")
    start = time.perf_counter()
    try:
        volume = vr.load(spec["path"], **spec["options"])
    except VolrenError as exc:
        print(json.dumps({"refused": str(exc)}))
        return
    seconds = time.perf_counter() - start
    out = {"load_s": seconds, "peak_load_kib": _status_kib("VmHWM") - before, "density_bytes": volume.density.nbytes,
           "shape": list(volume.density.shape[::-1]), "density_max": float(volume.density.max()), "frames": {}}
    scene = Scene((volume,), name=Path(spec["path"]).stem)
    views = framed_views(scene, None, "mono", width, height)
    for method, renderer in renderers.items():
        start = time.perf_counter()
        first = renderer.render(scene, views, frame=0)  # upload, light map, march
        first_ms = (time.perf_counter() - start) * 1e3
        frames = [renderer.render(scene, views, frame=i) for i in range(1, spec["repeats"] + 1)]
        steady = [sum(t for k, t in f.stats.times_ms.items() if k not in NOT_PASSES) for f in frames]
        np.save(Path(spec["images"]) / f"{spec['tag']}-{method}.npy", frames[-1].images[0])
        out["frames"][method] = {"first_ms": first_ms, "frame_ms": min(steady), "frame_median_ms": median(steady),
                                 "upload_ms": first.stats.times_ms.get("upload", 0.0),
                                 "light_map_ms": first.stats.times_ms.get("light_map", 0.0)}
    out["peak_total_kib"] = _status_kib("VmHWM") - before
    if pool:  # CUDA: the device memory the volume and the frames took (the resident set is the host's)
        out["device_peak_bytes"] = wp.get_mempool_used_mem_high(spec["device"]) - pool_before
    print(json.dumps(out))


def measure_file(path: str, options: dict[str, Any], cfg: dict[str, Any], images: Path, tag: str,
                 device: str) -> dict[str, Any]:
    """`child` on one file in a fresh subprocess."""
    spec = {"path": path, "options": options, "methods": cfg["methods"], "size": cfg["size"],
            "repeats": cfg["repeats"], "images": str(images), "tag": tag, "device": device}
    done = subprocess.run([sys.executable, "-c", "from volren.bench.bigdata import child; child()"],
                          input=json.dumps(spec), capture_output=True, text=True, timeout=3600)
    if done.returncode:
        raise VolrenError(f"bench bigdata: {tag} failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def run_config(cfg: dict[str, Any], device: str = "cpu") -> dict[str, Any]:
    unknown = [m for m in cfg["methods"] if m not in RENDER_SETTINGS]
    if unknown:
        raise VolrenError(f"bench bigdata: unknown method {unknown[0]!r}: choose from {', '.join(RENDER_SETTINGS)}")
    rows, summary, files = [], [], []
    with tempfile.TemporaryDirectory(prefix="volren-bench-bigdata-") as images:
        for kind in cfg["files"]:
            info = make_file(kind, cfg)
            active_bytes = 4 * info["active_voxels"]
            box = [h - lo + 1 for lo, h in zip(info["lo"], info["hi"], strict=True)]
            files.append({k: v for k, v in info.items() if k not in ("path", "dense_path")})
            common = {"file": kind, "index_box": f"{info['n']}^3", "active_voxels": info["active_voxels"],
                      "active_share": info["active_voxels"] / info["n"] ** 3, "active_mib": active_bytes / 2**20,
                      "active_box": "x".join(map(str, box)), "file_mib": info["file_bytes"] / 2**20}
            sides = {"sparse": measure_file(info["path"], {}, cfg, Path(images), f"{kind}-sparse", device)}
            if info["dense_path"] is not None:  # the same voxels placed as the .vdb places them: 1 m voxels
                sides["dense"] = measure_file(info["dense_path"], {"spacing": [1.0, 1.0, 1.0], "units": "m"}, cfg,
                                              Path(images), f"{kind}-dense", device)
            for side, got in sides.items():
                row = {**common, "side": "sparse .vdb" if side == "sparse" else "dense .npy",
                       "refused": got.get("refused")}
                if "refused" not in got:
                    row |= {"load_s": got["load_s"], "peak_load_mib": got["peak_load_kib"] / 1024,
                            "peak_total_mib": got["peak_total_kib"] / 1024,
                            "device_peak_mib": (got["device_peak_bytes"] / 2**20 if "device_peak_bytes" in got
                                                else None),
                            "density_mib": got["density_bytes"] / 2**20, "density_bytes": got["density_bytes"],
                            "density_max": got["density_max"], "shape": "x".join(map(str, got["shape"])),
                            "memory_ratio": got["peak_load_kib"] * 1024 / active_bytes,
                            "resident_ratio": got["density_bytes"] / active_bytes,
                            **{f"{m}_{k}": f[k] for m, f in got["frames"].items() for k in FRAME_FIGURES}}
                rows.append(row)
            case_done(f"{kind}: {', '.join(sides)}")
            sparse, dense = (next((r for r in rows[-len(sides):] if r["side"].startswith(s)), None)
                             for s in ("sparse", "dense"))
            entry: dict[str, Any] = {"file": kind, "active_voxels": info["active_voxels"],
                                     "memory_ratio": sparse.get("memory_ratio"),
                                     "resident_ratio": sparse.get("resident_ratio"),
                                     "memory_goal": MEMORY_GOAL, "time_goal": TIME_GOAL}
            if dense is not None and not sparse["refused"] and not dense["refused"]:
                entry["memory_vs_dense"] = _ratio(sparse["peak_load_mib"], dense["peak_load_mib"])
                entry["load_ratio"] = _ratio(sparse["load_s"], dense["load_s"])
                for m in cfg["methods"]:
                    entry[f"{m}_ratio"] = _ratio(sparse[f"{m}_frame_ms"], dense[f"{m}_frame_ms"])
                    entry[f"{m}_first_ratio"] = _ratio(sparse[f"{m}_first_ms"], dense[f"{m}_first_ms"])
                    a, b = (np.load(Path(images) / f"{kind}-{s}-{m}.npy") for s in ("sparse", "dense"))
                    entry[f"{m}_max_abs_diff"] = float(np.abs(a - b).max()) if a.shape == b.shape else None
            times = [entry.get("load_ratio"),
                     *(entry.get(f"{m}_{r}") for m in cfg["methods"] for r in ("ratio", "first_ratio"))]
            met = (entry["memory_ratio"] is not None and entry["memory_ratio"] <= MEMORY_GOAL
                   and all(t is not None and t <= TIME_GOAL for t in times))
            entry["met"] = "yes" if met else ("refused" if sparse["refused"] else "no")
            summary.append(entry)
    ms = [c for m in cfg["methods"] for c in ((f"{m}_first_ms", f"{m} first frame [ms]", ".0f"),
                                              (f"{m}_light_map_ms", f"{m} light map [ms]", ".0f"),
                                              (f"{m}_frame_ms", f"{m} [ms/frame]", ".1f"))]
    columns = [("file", "file", "s"), ("index_box", "index box", "s"), ("active_voxels", "active voxels", ","),
               ("active_share", "active share", ".4f"), ("file_mib", "file [MiB]", ".1f"),
               ("side", "loaded", "s"), ("shape", "density (x, y, z)", "s"), ("load_s", "load [s]", ".2f"),
               ("peak_load_mib", "load peak RSS rise [MiB]", ".1f"), ("density_mib", "density [MiB]", ".1f"),
               ("peak_total_mib", "load + render peak RSS rise [MiB]", ".1f"),
               ("device_peak_mib", "CUDA memory peak rise [MiB]", ".1f"), *ms, ("refused", "refused", "s")]
    summary_columns = [("file", "file", "s"), ("active_voxels", "active voxels", ","),
                       ("memory_ratio", "load peak / active bytes", ".2f"),
                       ("resident_ratio", "density bytes / active bytes", ".2f"),
                       ("memory_vs_dense", "load peak / dense's", ".2f"), ("load_ratio", "load time / dense's", ".2f"),
                       *[c for m in cfg["methods"] for c in ((f"{m}_first_ratio", f"{m} first frame / dense's", ".2f"),
                                                             (f"{m}_ratio", f"{m} ms/frame / dense's", ".2f"))],
                       *[(f"{m}_max_abs_diff", f"{m} image max abs diff to dense", ".2g") for m in cfg["methods"]],
                       ("memory_goal", "memory goal (at most)", ".2f"), ("time_goal", "time goal (at most)", ".2f"),
                       ("met", "met", "s")]
    settings = {**cfg, "cache": str(cache_folder(cfg.get("cache"))), "quality": QUALITY,
                "method_settings": {m: RENDER_SETTINGS[m] for m in cfg["methods"]}, "maker_version": MAKER_VERSION,
                "memory": "peak resident set (VmHWM, reset before the load) minus the resident set before it, in a "
                          "fresh subprocess that has imported volren and loaded the renderers' kernels",
                "ms": "first frame: wall time of frame 0 (upload, light map, march); ms/frame: the fastest of the "
                      "next repeats frames (light map kept; passes but upload and readback); one mono view framed "
                      "as volren render frames the file",
                "files_info": files}
    result = {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}
    if cfg.get("outofcore"):
        result["outofcore"], settings["outofcore_info"] = run_outofcore(cfg, device)
        settings["outofcore_goals"] = {"first_s": GOAL_FIRST_S, "refine_s": GOAL_REFINE_S,
                                       "rss_over_budget_bytes": GOAL_RSS_OVER_BUDGET}
        result["more_tables"] = {"outofcore": OUTOFCORE_COLUMNS}
    return result


# ---------------------------------------------------------------------------------------------- part (b) out-of-core

OUTOFCORE_VERSION = 1
"""part of every cached pyramid's name: raise it when `pyramid_chunk` or `write_pyramid` change"""
GOAL_FIRST_S = 1.0
"""[s] open to the first (coarse) frame (issue 41 (b), on a 2-core CPU)"""
GOAL_REFINE_S = 15.0
"""[s] open to the frame that has every brick it wants"""
GOAL_RSS_OVER_BUDGET = 2**30
"""[bytes] peak resident set rise allowed over the memory budget"""


def pyramid_waves(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Plane waves (kx, ky, kz [radians per voxel], phase) of the out-of-core field: 6 coarse ones of 2 to 6 periods
    across the n^3 box, and 8 fine ones of wavelengths 5 to 20 voxels whatever n (structure that only level 0
    holds), two sets of 4 whose common zeros are the filaments."""
    rng = np.random.default_rng(seed + 41)
    coarse, fine = [], []
    for out, count, lo, hi, per in ((coarse, 6, 2.0, 6.0, n), (fine, 8, 5.0, 20.0, None)):
        for _ in range(count):
            k = rng.normal(size=3)
            length = n / rng.uniform(lo, hi) if per else rng.uniform(lo, hi)
            out.append((*(k * 2.0 * np.pi / length / np.linalg.norm(k)), rng.uniform(0.0, 2.0 * np.pi)))
    return np.asarray(coarse), np.asarray(fine)


def _wave_sum(waves: np.ndarray, z: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """sum of sin(k . p + phase) over ``waves`` at the voxel centres z x y x x (float32): sin(a + b) = sin a cos b +
    cos a sin b with a along x and b over the (z, y) plane, each from float64 1-D / 2-D values of the global index,
    so a voxel's value is the same whatever block it is made in."""
    out = np.zeros((len(z), len(y), len(x)), np.float32)
    for kx, ky, kz, phase in waves:
        b = (kz * z)[:, None] + (ky * y)[None, :] + phase
        sb, cb = np.sin(b).astype(np.float32)[:, :, None], np.cos(b).astype(np.float32)[:, :, None]
        a = kx * x
        sa, ca = np.sin(a).astype(np.float32), np.cos(a).astype(np.float32)
        out += sa * cb
        out += ca * sb
    return out


def pyramid_block(n: int, seed: int, start: tuple[int, int, int], shape: tuple[int, int, int]) -> np.ndarray:
    """Level 0 of the out-of-core pyramid, uint8 ``[z, y, x]`` voxels ``start`` + ``shape`` of the n^3 box: inside a
    ball of radius 0.48 n (softened over its outer 10%), 255 x min(1, 0.3 cloud + filaments), where cloud =
    clip(0.5 + 0.2 coarse, 0, 1) and filaments = exp(-(f1^2 + f2^2) / 0.5^2) (`pyramid_waves`: f1, f2 the two fine
    sets, their common zeros thin tubes a few voxels wide). Every value depends only on the voxel's global index."""
    coarse, fine = pyramid_waves(n, seed)
    z, y, x = (np.arange(a, a + s, dtype=np.float64) + 0.5 for a, s in zip(start, shape, strict=True))
    c = n / 2.0
    r2 = (((z - c) ** 2)[:, None, None] + ((y - c) ** 2)[None, :, None]).astype(np.float32) \
        + ((x - c) ** 2).astype(np.float32)[None, None, :]
    envelope = np.clip((np.float32((0.48 * n) ** 2) - r2) / np.float32((0.48 * n) ** 2 - (0.43 * n) ** 2), 0.0, 1.0)
    cloud = np.clip(_wave_sum(coarse, z, y, x) * np.float32(0.2) + np.float32(0.5), 0.0, 1.0)
    f1, f2 = _wave_sum(fine[:4], z, y, x), _wave_sum(fine[4:], z, y, x)
    filaments = np.exp((f1 * f1 + f2 * f2) * np.float32(-4.0))
    d = np.minimum(cloud * np.float32(0.3) + filaments, np.float32(1.0)) * envelope
    return np.rint(d * np.float32(255.0)).astype(np.uint8)


def outside_ball(n: int, lo: list[int], hi: list[int]) -> bool:
    """Whether the level-0 box [lo, hi) of voxels lies wholly outside `pyramid_block`'s ball (radius 0.48 n, centre
    n / 2), where its field is 0: the box's nearest voxel centre is farther than the radius."""
    c = n / 2.0
    near = [min(max(c, a + 0.5), b - 0.5) - c for a, b in zip(lo, hi, strict=True)]
    return sum(d * d for d in near) > (0.48 * n) ** 2 * (1 + 1e-6)


def pyramid_shapes(n: int, coarsest: int) -> list[tuple[int, int, int]]:
    """Level shapes: n^3, then each ceil(half) of the previous, down to the first whose edge is at most
    ``coarsest``."""
    shapes = [(n, n, n)]
    while max(shapes[-1]) > coarsest:
        shapes.append(tuple(-(-s // 2) for s in shapes[-1]))
    return shapes


def mean_2x2x2(fine: np.ndarray) -> np.ndarray:
    """The next coarser level's voxels over a uint8 block of the finer one: the mean of each 2x2x2 group, rounded
    half up ((sum + 4) // 8); an odd edge (the level's last voxel) is repeated, so the mean is over it alone along
    that axis."""
    pad = [(0, s % 2) for s in fine.shape]
    f = np.pad(fine, pad, mode="edge").astype(np.uint16) if any(p for _, p in pad) else fine.astype(np.uint16)
    z, y, x = (s // 2 for s in f.shape)
    total = f.reshape(z, 2, y, 2, x, 2).sum(axis=(1, 3, 5), dtype=np.uint16)
    return ((total + 4) // 8).astype(np.uint8)


def write_pyramid(path: Path, n: int, seed: int, chunk: int, coarsest: int, *, resume: bool = False
                  ) -> dict[str, Any]:
    """An OME-Zarr (NGFF as ``ome_zarr.writer`` writes it) of `pyramid_block`'s field, uint8 levels chunked
    ``chunk``^3 (`pyramid_shapes`; level k + 1 the `mean_2x2x2` of level k; scale 2^k and translation (2^k - 1) / 2
    level-0 voxels, in micrometres), written chunk by chunk: level 0 made block by block, each coarser chunk from
    the finer level's 2 chunk^3 block read back; never a whole level in memory. With ``resume``, an interrupted
    write at ``path`` goes on: level-0 chunks already on disk are kept (every voxel depends only on its index; a
    4096^3 level 0 takes about 100 minutes here). Returns the levels' shapes and the seconds each level took."""
    import warnings

    import zarr

    with warnings.catch_warnings():  # its import makes a deprecated Scaler as a default argument
        warnings.simplefilter("ignore", DeprecationWarning)
        from ome_zarr import writer

    shapes = pyramid_shapes(n, coarsest)
    resume = resume and (path / "0" / "zarr.json").exists()
    group = zarr.open_group(str(path), mode="a" if resume else "w")
    arrays = [group.create_array(str(k), shape=s, chunks=(chunk,) * 3, dtype="uint8", fill_value=0, overwrite=k > 0)
              if not (resume and k == 0) else group["0"] for k, s in enumerate(shapes)]
    seconds = []
    for k, (array, shape) in enumerate(zip(arrays, shapes, strict=True)):
        start = time.perf_counter()
        for index in np.ndindex(*(-(-s // chunk) for s in shape)):
            lo = [i * chunk for i in index]
            size = tuple(min(chunk, s - a) for a, s in zip(lo, shape, strict=True))
            if outside_ball(n, [a << k for a in lo], [(a + s) << k for a, s in zip(lo, size, strict=True)]):
                continue  # all zero at every level: zarr stores no chunk of only the fill value anyway
            if resume and k == 0 and (path / "0" / "c" / "/".join(map(str, index))).exists():
                continue
            if k == 0:
                block = pyramid_block(n, seed, tuple(lo), size)
            else:
                finer = arrays[k - 1][tuple(slice(2 * a, 2 * (a + s)) for a, s in zip(lo, size, strict=True))]
                block = mean_2x2x2(finer)
            array[tuple(slice(a, a + s) for a, s in zip(lo, size, strict=True))] = block
        seconds.append(time.perf_counter() - start)
    datasets = [{"path": str(k), "coordinateTransformations": [
        {"type": "scale", "scale": [float(2**k)] * 3}, {"type": "translation", "translation": [(2**k - 1) / 2] * 3}]}
        for k in range(len(shapes))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        writer.write_multiscales_metadata(group, datasets,
                                          axes=[{"name": a, "type": "space", "unit": "micrometer"} for a in "zyx"],
                                          name="bigdata-outofcore")
    return {"shapes": [list(s) for s in shapes], "level_s": seconds}


def make_pyramid(cfg: dict[str, Any]) -> dict[str, Any]:
    """The configuration's pyramid (``outofcore`` edge n, ``outofcore_chunk``, ``outofcore_coarsest``, ``seed``)
    from the cache or written there (`write_pyramid`, beside a JSON sidecar). Returns the sidecar: ``path``,
    ``n``, ``shapes``, ``file_bytes``, ``write_s``."""
    import shutil

    n, chunk, coarsest = cfg["outofcore"], cfg["outofcore_chunk"], cfg["outofcore_coarsest"]
    if n < 1 or chunk < 1 or coarsest < 1:
        raise VolrenError(f"bigdata: outofcore {n}, chunk {chunk} and coarsest {coarsest} must be positive")
    folder = cache_folder(cfg.get("cache"))
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"outofcore-n{n}-c{chunk}-top{coarsest}-s{cfg['seed']}-v{OUTOFCORE_VERSION}"
    path, sidecar = stem.with_suffix(".zarr"), stem.with_suffix(".json")
    if path.exists() and sidecar.exists():
        info = json.loads(sidecar.read_text())
    else:
        tmp = path.with_name(f".{path.name}.tmp")  # an interrupted write of this configuration goes on
        shutil.rmtree(path, ignore_errors=True)
        start = time.perf_counter()
        written = write_pyramid(tmp, n, cfg["seed"], chunk, coarsest, resume=True)
        os.replace(tmp, path)
        size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
        info = {"n": n, "chunk": chunk, "coarsest": coarsest, **written, "file_bytes": size,
                "write_s": time.perf_counter() - start}
        sidecar.write_text(json.dumps(info, indent=1) + "\n")
        case_done(f"wrote {path.name}: {len(info['shapes'])} levels, {size / 2**20:.1f} MiB")
    return {**info, "path": str(path)}


def close_up(volume: Any, width: int, height: int, angle_deg: float) -> Any:
    """A camera 1.5 half-edges from the volume's centre (0.5 outside the face it looks at when ``angle_deg`` = 0),
    a little above it, looking at the centre, 40 degrees fov: the near part wants level 0, the far part coarser
    levels. ``angle_deg`` turns it about the volume's y axis (the orbit)."""
    from volren.camera import Camera

    half = float(np.linalg.norm(volume.to_world[:3, :3], axis=0).max())
    centre = np.asarray(volume.center_world, dtype=np.float64)
    a = math.radians(angle_deg)
    offset = np.array([math.sin(a), 0.12, math.cos(a)]) * 1.5 * half
    return Camera(position=tuple(centre + offset), look_at=tuple(centre), fov_y=40.0, width=width, height=height,
                  near=1e-3 * half, far=10.0 * half)


def outofcore_child() -> None:
    """In a fresh process (a JSON spec on stdin: ``path``, ``budget`` [bytes], ``size``, ``orbit_frames``,
    ``orbit_deg``, ``refine_timeout_s``, ``reference``, ``warm_path``, ``device``, ``quality``): import volren,
    render a small streamed pyramid of as many levels (``warm_path``: the streamed kernels loaded), reset the peak
    resident set; then open the pyramid within the budget (``volren.load``; it streams), render the close-up
    (`close_up`) with ``stream_wait`` False until a frame has no brick pending (each frame's stream stats), one more
    (the refined frame), then the orbit; print JSON. With ``reference``, afterwards (out of the peak) the finest
    level dense, rendered from the refined frame's camera."""
    import volren as vr
    from volren.presets import quality_config
    from volren.render import DSSRM
    from volren.scene import Scene

    spec = json.loads(sys.stdin.read())
    width, height = spec["size"]
    budget = spec["budget"]

    def renderer() -> DSSRM:
        r = DSSRM(quality_config("dssrm", spec["quality"]), device=spec["device"])
        r.stream_wait = False
        return r

    warm = vr.load(spec["warm_path"], memory_budget=2**-10, stream=True)
    r = renderer()
    for angle in (0.0, 90.0):
        r.render(Scene((warm,)), [close_up(warm, 16, 9, angle)])
    warm.density.close()
    del warm, r
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = _status_kib("VmRSS")
    start = time.perf_counter()
    volume = vr.load(spec["path"], memory_budget=budget / 2**30)
    open_s = time.perf_counter() - start
    scene = Scene((volume,))
    r = renderer()
    cam = close_up(volume, width, height, 0.0)
    frames: list[dict[str, Any]] = []

    def frame(camera: Any) -> Any:
        t = time.perf_counter()
        got = r.render(scene, [camera], frame=len(frames))
        frames.append({**got.stats.info["stream"][0], "ms": (time.perf_counter() - t) * 1e3,
                       "passes_ms": dict(got.stats.times_ms),
                       "at_s": time.perf_counter() - start})
        return got

    frame(cam)
    while frames[-1]["bricks_pending"] and frames[-1]["at_s"] < spec["refine_timeout_s"]:
        frame(cam)
    refine = len(frames)
    refined = frame(cam)  # everything resident drawn (the frame that said "none pending" drew what came before it)
    for i in range(1, spec["orbit_frames"] + 1):
        frame(close_up(volume, width, height, i * spec["orbit_deg"]))
    from volren.stream.lod import frame_needs

    wanted = [0] * volume.density.layout.count  # after the clock: the level rule's wants of the still camera
    for n in frame_needs([cam], volume.to_world, volume.density.layout):
        wanted[n.level] += 1
    out = {"open_s": open_s, "frames": frames, "refine_frames": refine, "levels_wanted": wanted,
           "peak_kib": _status_kib("VmHWM") - before, "rss_kib": _status_kib("VmRSS") - before,
           "streamed": type(volume.density).__name__, "levels": volume.density.layout.count,
           "brick_bytes": int(__import__("volren.stream.streamer", fromlist=["BRICK_BYTES"]).BRICK_BYTES),
           "psnr": None}
    if spec["reference"]:
        from volren.metrics import psnr

        volume.density.close()
        dense = vr.load(spec["path"], level=0)
        want = renderer().render(Scene((dense,)), [cam])
        out["psnr"] = psnr(want.images[0], refined.images[0])
        out["max_abs_diff"] = float(np.abs(want.images[0] - refined.images[0]).max())
    print(json.dumps(out))


def run_outofcore(cfg: dict[str, Any], device: str) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Part (b): the pyramid (`make_pyramid`), measured in a fresh subprocess (`outofcore_child`); one row."""
    info = make_pyramid(cfg)
    levels = len(pyramid_shapes(cfg["outofcore"], cfg["outofcore_coarsest"]))  # the warm-up's as many (kernels)
    warm = make_pyramid({**cfg, "outofcore": 4 << max(levels - 1, 2), "outofcore_chunk": 16,
                         "outofcore_coarsest": 4})
    budget = int(cfg["outofcore_budget_mib"] * 2**20)
    n = info["n"]
    if 4 * n**3 <= budget:
        raise VolrenError(f"bench bigdata: outofcore level 0 ({4 * n**3 / 2**20:.0f} MiB as float32) fits the budget "
                          f"of {budget / 2**20:.0f} MiB: it would load whole, not stream; lower outofcore_budget_mib")
    spec = {"path": info["path"], "budget": budget, "size": cfg["outofcore_size"],
            "orbit_frames": cfg["orbit_frames"], "orbit_deg": cfg["orbit_deg"],
            "refine_timeout_s": cfg["refine_timeout_s"], "reference": n**3 <= cfg["reference_max_voxels"],
            "warm_path": warm["path"], "device": device, "quality": cfg["outofcore_quality"]}
    done = subprocess.run([sys.executable, "-c", "from volren.bench.bigdata import outofcore_child; "
                           "outofcore_child()"], input=json.dumps(spec), capture_output=True, text=True,
                          timeout=3600)
    if done.returncode:
        raise VolrenError(f"bench bigdata: outofcore failed: {done.stderr.strip().splitlines()[-1:]}")
    got = json.loads(done.stdout.strip().splitlines()[-1])
    frames, refine = got["frames"], got["refine_frames"]
    first, refined, orbit = frames[0], frames[refine], frames[refine + 1:]
    size = cfg["outofcore_size"]
    row = {"file": "outofcore", "index_box": f"{n}^3", "levels": len(info["shapes"]),
           "level0_mib": n**3 / 2**20, "level0_float_mib": 4 * n**3 / 2**20, "file_mib": info["file_bytes"] / 2**20,
           "budget_mib": budget / 2**20, "size": f"{size[0]}x{size[1]}", "loaded": got["streamed"],
           "open_s": got["open_s"], "first_frame_s": first["ms"] / 1e3, "first_s": first["at_s"],
           "first_levels_used": first["levels_used"], "first_pending": first["bricks_pending"],
           "refine_frames": refine, "refine_s": frames[refine - 1]["at_s"], "refined_pending":
           refined["bricks_pending"], "refined_bytes_read": refined["bytes_read"],
           "levels_used": refined["levels_used"], "levels_used_text": "/".join(map(str, refined["levels_used"])),
           "levels_wanted": got["levels_wanted"], "levels_wanted_text": "/".join(map(str, got["levels_wanted"])),
           "bricks_resident": refined["bricks_resident"],
           "pool_bytes": refined["pool_bytes"], "device_bricks": refined["device_bricks"],
           "device_capacity": refined["device_capacity"], "brick_bytes": got["brick_bytes"],
           "refined_frame_ms": refined["ms"],
           "orbit_frames": len(orbit), "orbit_deg": cfg["orbit_deg"],
           "orbit_bytes_per_frame": sum(f["bytes_read"] for f in orbit) / max(len(orbit), 1),
           "orbit_bytes_max": max((f["bytes_read"] for f in orbit), default=0),
           "orbit_loaded_per_frame": sum(f["bricks_loaded"] for f in orbit) / max(len(orbit), 1),
           "orbit_evicted_per_frame": sum(f["bricks_evicted"] for f in orbit) / max(len(orbit), 1),
           "orbit_pending_last": orbit[-1]["bricks_pending"] if orbit else None,
           "orbit_ms": median(f["ms"] for f in orbit) if orbit else None,
           "peak_rss_mib": got["peak_kib"] / 1024, "rss_goal_mib": (budget + GOAL_RSS_OVER_BUDGET) / 2**20,
           "psnr": got["psnr"], "max_abs_diff": got.get("max_abs_diff"),
           "frames_detail": [{k: f[k] for k in ("ms", "at_s", "bricks_pending", "bricks_loaded", "bricks_evicted",
                                                "bytes_read", "levels_used", "device_bricks", "passes_ms")}
                             for f in frames]}
    row["met"] = "yes" if (row["first_s"] <= GOAL_FIRST_S and row["refine_s"] <= GOAL_REFINE_S
                           and refined["bricks_pending"] == 0
                           and row["peak_rss_mib"] <= row["rss_goal_mib"]) else "no"
    case_done(f"outofcore {n}^3: first frame {row['first_s']:.2f} s, refined {row['refine_s']:.2f} s "
              f"({refine} frames), peak RSS {row['peak_rss_mib']:.0f} MiB")
    return [row], {k: v for k, v in info.items() if k != "path"}


OUTOFCORE_COLUMNS = [
    ("index_box", "level 0", "s"), ("levels", "levels", "d"), ("file_mib", "file [MiB]", ".1f"),
    ("level0_float_mib", "level 0 float32 [MiB]", ".0f"), ("budget_mib", "budget [MiB]", ".0f"),
    ("size", "image", "s"), ("open_s", "open [s]", ".2f"), ("first_s", "first frame [s]", ".2f"),
    ("refine_s", "refined [s]", ".2f"), ("refine_frames", "frames to refine", "d"),
    ("levels_wanted_text", "bricks per level wanted", "s"),
    ("levels_used_text", "bricks per level used (refined)", "s"), ("device_bricks", "device bricks", "d"),
    ("device_capacity", "device capacity", "d"), ("orbit_bytes_per_frame", "orbit bytes read / frame", ",.0f"),
    ("orbit_loaded_per_frame", "orbit bricks loaded / frame", ".1f"), ("orbit_ms", "orbit [ms/frame]", ".0f"),
    ("peak_rss_mib", "peak RSS rise [MiB]", ".0f"), ("rss_goal_mib", "RSS goal [MiB]", ".0f"),
    ("psnr", "PSNR to dense [dB]", ".1f"), ("met", "goals met", "s")]


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(sized(QUICK, FULL, quick), device)


SUITE = Suite("bigdata", "sparse .vdb files (issue 41: two balls in 2000^3, a smoke in 2048^3) loaded and rendered "
              "against the same voxels dense: peak memory over the active voxels' bytes, load time, ms per frame; "
              "and an OME-Zarr pyramid over the memory budget, streamed: first frame, refinement, orbit reads, "
              "peak memory",
              run, settable=True)

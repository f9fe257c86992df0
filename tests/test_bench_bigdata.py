"""The ``bigdata`` bench suite, part (a) sparse (issue 41): its files hold exactly the geometry asked (the issue's two
balls at their corners, 8.4 M active voxels at 2000^3; the smoke chunk-independent and a few percent active), written
by OpenVDB itself and read back through volren's ``.vdb`` reader; the suite's rows hold the measured fields with their
exact relations."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from volren.bench.bigdata import (
    MEMORY_GOAL,
    TIME_GOAL,
    make_file,
    smoke_blocks,
    two_balls_active,
    two_balls_blocks,
)
from volren.bench.load import SYSTEM_PYTHON, openvdb_available
from volren.errors import VolrenError

OPENVDB = openvdb_available()
if not OPENVDB and os.environ.get("CI") == "true":
    pytest.fail(f"{SYSTEM_PYTHON} cannot import pyopenvdb in CI: .ci/run installs python3-openvdb", pytrace=False)
needs_openvdb = pytest.mark.skipif(not OPENVDB, reason=f"{SYSTEM_PYTHON} cannot import pyopenvdb "
                                   "(apt-get install python3-openvdb)")
"""part (a) writes its files with OpenVDB; part (b) (out-of-core, OME-Zarr) does not need it"""


def config(tmp_path, **entries):
    return {"two_balls": [120, 10], "smoke": 96, "seed": 0, "dense_max_voxels": 1 << 30, "cache": str(tmp_path),
            **entries}


def lattice_ball(radius: int) -> int:
    """Voxels whose centre (i + 0.5) lies strictly within ``radius`` of a whole-number centre c (0.15 n and 0.85 n
    are whole numbers for the sizes tested): the count over offsets i + 0.5 - c = k + 0.5, k integer."""
    k = np.arange(-radius - 1, radius + 1, dtype=np.float64) + 0.5
    return int(np.count_nonzero(k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2 < radius**2))


def shell_bound(radius: int) -> float:
    """A rigorous bound on |lattice count - 4/3 pi R^3| for one ball: only the unit voxels the sphere cuts can be
    counted wrongly, and they lie within sqrt(3) / 2 of the sphere, in a shell of that half-width."""
    h = math.sqrt(3.0) / 2.0
    return 4.0 / 3.0 * math.pi * ((radius + h) ** 3 - (radius - h) ** 3)


def assemble(shape, blocks) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    for (z, y, x), block in blocks:
        out[z:z + block.shape[0], y:y + block.shape[1], x:x + block.shape[2]] = block
    return out


@needs_openvdb
@pytest.mark.timeout(120)
def test_two_balls_file_loads_as_the_balls_at_their_corners(tmp_path):
    from volren.data.loaders import load_volume

    n, radius = 120, 10
    info = make_file("two-balls", config(tmp_path))
    active = 2 * lattice_ball(radius)
    assert info["active_voxels"] == active
    assert abs(active - two_balls_active(n, radius)) <= 2 * shell_bound(radius)
    c0, c1 = round(0.15 * n), round(0.85 * n)  # 18 and 102
    assert info["lo"] == [c0 - radius] * 3 and info["hi"] == [c1 + radius - 1] * 3  # voxel centres within R
    loaded = load_volume(info["path"])
    full = assemble((n, n, n), two_balls_blocks(n, radius))
    lo, hi = info["lo"][0], info["hi"][0] + 1
    assert np.array_equal(loaded.density.to_dense(), full[lo:hi, lo:hi, lo:hi])  # every voxel, as written
    # placed by the file's index (1 m voxels): the centre of dense voxel c - lo is file index c, at world c
    local = -1.0 + (np.array([c0, c1]) - lo + 0.5) * 2.0 / loaded.density.shape[2]
    assert (loaded.to_world @ [local[0], local[0], local[1], 1.0])[:3] == pytest.approx([c0, c0, c1])
    # the voxels beside each ball's centre (offsets +-0.5 on every axis) read 1 - 3 / (4 R^2), one beyond R reads 0
    for c in (c0, c1):
        assert full[c, c, c] == full[c - 1, c - 1, c - 1] == np.float32(1.0 - 0.75 / radius**2)
        assert full[c, c, c + radius - 1] > 0.0 and full[c, c, c + radius] == 0.0
        assert full[c, c, c - radius] > 0.0 and full[c, c, c - radius - 1] == 0.0
    dense = np.load(info["dense_path"])
    assert np.array_equal(dense, loaded.density.to_dense())  # the dense twin: the same voxels


@needs_openvdb
@pytest.mark.timeout(180)
def test_the_issue_file_holds_8_4_million_active_voxels_without_a_dense_copy(tmp_path):
    """n = 2000, R = 100 (a 1600^3 active box: 16 GiB dense), written in blocks; read back leaf by leaf through the
    .vdb reader's topology (its active counts per leaf) and values."""
    from volren.data.vdb import _leaves, _map, _open

    n, radius = 2000, 100
    info = make_file("two-balls", config(tmp_path, two_balls=[n, radius]), dense=False)
    assert info["dense_path"] is None
    assert info["active_voxels"] == 2 * lattice_ball(radius) == 8_377_792
    assert abs(info["active_voxels"] - two_balls_active(n, radius)) <= 2 * shell_bound(radius)
    # tighter: a ball's lattice-point discrepancy grows far slower than its surface (O(R^(21/16)), Heath-Brown),
    # so R^(3/2) per ball (1,000 voxels, 1.2e-4 of it) is a generous bar; measured: 212 voxels over both
    assert abs(info["active_voxels"] - two_balls_active(n, radius)) <= 2 * radius**1.5
    assert info["lo"] == [300 - radius] * 3 and info["hi"] == [1700 + radius - 1] * 3
    vdb, data = _open(info["path"]), _map(info["path"])
    try:
        leaves, origins, tiles, _ = _leaves(info["path"], data, vdb, 0)
        assert sum(leaf.active_voxel_count for leaf in leaves) == info["active_voxels"] and not len(tiles.values)
        where = {tuple(o): i for i, o in enumerate(origins.tolist())}

        def value(x: int, y: int, z: int) -> float:  # a leaf's values: x slowest, z fastest
            leaf = where.get((x & ~7, y & ~7, z & ~7))
            return 0.0 if leaf is None else float(np.frombuffer(leaves[leaf].data, np.float32)[
                ((x & 7) << 6) | ((y & 7) << 3) | (z & 7)])

        for c in (300, 1700):
            assert value(c, c, c) == value(c - 1, c - 1, c - 1) == np.float32(1.0 - 0.75 / radius**2)
            assert value(c + radius - 1, c, c) > 0.0 and value(c + radius, c, c) == 0.0
            assert value(c, c - radius, c) > 0.0 and value(c, c - radius - 1, c) == 0.0
        assert value(1000, 1000, 1000) == 0.0 and value(300, 1700, 300) == 0.0  # between and beside the balls
    finally:
        vdb.close()
        data.close()


@needs_openvdb
@pytest.mark.timeout(120)
def test_smoke_is_the_same_field_whatever_the_chunks_and_a_few_percent_active(tmp_path):
    from volren.data.vdb import read_vdb

    n = 96
    whole = assemble((n, n, n), smoke_blocks(n, 0, chunk=64))
    assert np.array_equal(assemble((n, n, n), smoke_blocks(n, 0, chunk=24)), whole)  # values of the global index
    assert not np.array_equal(assemble((n, n, n), smoke_blocks(n, 1)), whole)  # the seed matters
    info = make_file("smoke", config(tmp_path, smoke=n))
    assert info["active_voxels"] == np.count_nonzero(whole)
    assert 0.01 < info["active_voxels"] / n**3 < 0.06  # "a few percent": 2.6% at 512^3
    got = read_vdb(info["path"])[0].data.to_dense()
    nz = np.nonzero(whole)
    lo, hi = [int(a.min()) for a in nz], [int(a.max()) + 1 for a in nz]
    assert info["lo"] == lo[::-1] and info["hi"] == [h - 1 for h in hi[::-1]]
    assert np.array_equal(got, whole[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]])
    # a plume: more smoke in the upper half than the lower (it widens as it rises; 2.0x at 96^3), none in the
    # lowest 3%
    assert whole[:, n // 2:].sum() > 1.5 * whole[:, :n // 2].sum() and not whole[:, :3].any()


@needs_openvdb
@pytest.mark.timeout(60)
def test_cached_files_are_reused_and_bad_sizes_refused(tmp_path):
    cfg = config(tmp_path, two_balls=[100, 8])
    first = make_file("two-balls", cfg, dense=False)
    mtime = os.stat(first["path"]).st_mtime_ns
    assert make_file("two-balls", cfg, dense=False) == first and os.stat(first["path"]).st_mtime_ns == mtime
    with pytest.raises(VolrenError, match="do not fit apart"):
        make_file("two-balls", config(tmp_path, two_balls=[100, 20]))
    with pytest.raises(VolrenError, match="unknown file"):
        make_file("ball", cfg)


@needs_openvdb
@pytest.mark.timeout(300)
def test_suite_rows_hold_the_measured_fields_with_their_relations(tmp_path):
    from volren.bench.runner import run_suite

    overrides = {"two_balls": [120, 10], "smoke": 96, "size": [32, 18], "repeats": 2, "cache": str(tmp_path / "c"),
                 "outofcore": None}
    json_path, md_path, table = run_suite("bigdata", quick=True, device="cpu", out=tmp_path, overrides=overrides)
    doc = json.loads(json_path.read_text())
    rows, summary = doc["rows"], doc["summary"]
    assert [(r["file"], r["side"]) for r in rows] == [("two-balls", "sparse .vdb"), ("two-balls", "dense .npy"),
                                                      ("smoke", "sparse .vdb"), ("smoke", "dense .npy")]
    files = {f["kind"]: f for f in doc["settings"]["files_info"]}
    assert files["two-balls"]["active_voxels"] == 2 * lattice_ball(10)
    for r in rows:
        active = files[r["file"]]["active_voxels"]
        assert r["active_voxels"] == active and r["active_mib"] * 2**20 == 4 * active
        assert r["refused"] is None and r["device_peak_mib"] is None  # CUDA only
        shape = [int(v) for v in r["shape"].split("x")]
        box = [h - lo + 1 for lo, h in zip(files[r["file"]]["lo"], files[r["file"]]["hi"], strict=True)]
        assert shape == box
        if r["side"] == "dense .npy":
            assert r["density_bytes"] == 4 * math.prod(shape)
        else:  # bricks: the pool of the bricks the data touches (with their aprons, (17/16)^3), not the box
            assert r["density_bytes"] <= (17 / 16) ** 3 * 4 * math.prod(shape) + 2**16
            if r["file"] == "two-balls":  # two balls in a box: most bricks empty, no pool memory
                assert r["density_bytes"] < 0.5 * 4 * math.prod(shape)
        assert r["resident_ratio"] == r["density_bytes"] / (4 * active)
        assert r["memory_ratio"] == pytest.approx(r["peak_load_mib"] * 2**20 / (4 * active))
        assert r["peak_total_mib"] >= r["peak_load_mib"]  # the same peak, over a longer run
        # the rise over the resident set before the load: the load's own allocations (a few copies of the density at
        # most today), not the interpreter with Warp and the kernels (hundreds of MiB)
        assert r["peak_load_mib"] <= 4 * r["density_mib"] + 16
        for m in ("dssrm", "mip"):
            assert r[f"{m}_first_ms"] >= r[f"{m}_light_map_ms"] + r[f"{m}_upload_ms"]  # passes of the first frame
            assert r[f"{m}_frame_median_ms"] >= r[f"{m}_frame_ms"]
    assert rows[0]["density_max"] == rows[1]["density_max"] == np.float32(1.0 - 0.75 / 10**2)  # the balls' peak
    for s, (sparse, dense) in zip(summary, (rows[0:2], rows[2:4]), strict=True):
        assert s["load_ratio"] == sparse["load_s"] / dense["load_s"]
        assert s["memory_vs_dense"] == sparse["peak_load_mib"] / dense["peak_load_mib"]
        assert s["dssrm_ratio"] == sparse["dssrm_frame_ms"] / dense["dssrm_frame_ms"]
        assert s["mip_first_ratio"] == sparse["mip_first_ms"] / dense["mip_first_ms"]
        # the same voxels from the same framing: the same picture (1 m voxels at another place: rounding only)
        assert s["dssrm_max_abs_diff"] < 1e-4 and s["mip_max_abs_diff"] < 1e-4
        times = [s["load_ratio"], s["dssrm_ratio"], s["dssrm_first_ratio"], s["mip_ratio"], s["mip_first_ratio"]]
        assert s["met"] == ("yes" if s["memory_ratio"] <= MEMORY_GOAL and max(times) <= TIME_GOAL else "no")
    assert "| two-balls | 120^3 |" in table and table in md_path.read_text()


@needs_openvdb
@pytest.mark.timeout(240)
def test_a_file_the_reader_refuses_is_a_row_that_says_so(tmp_path):
    """The issue's 2000^3 file: its 1600^3 active box is too large for a dense twin (the dense reader refused it,
    over 2^30 voxels); the sparse reader loads it as bricks: 59.9 MB for the 33.5 MB of active voxels (1.79x: the
    aprons' (17/16)^3 and the bricks the spheres cut)."""
    from volren.bench.bigdata import run_config

    cfg = config(tmp_path, files=["two-balls"], two_balls=[2000, 100], size=[16, 9], methods=["mip"], repeats=1)
    doc = run_config(cfg)
    assert [r["side"] for r in doc["rows"]] == ["sparse .vdb"]  # no dense twin of 4.1 G voxels
    row, (entry, _) = doc["rows"][0], (doc["summary"][0][0], None)
    assert row["refused"] is None
    assert row["memory_ratio"] == row["peak_load_mib"] * 2**20 / (4 * 8_377_792)
    assert row["density_bytes"] <= 1.8 * 4 * 8_377_792
    assert "load_ratio" not in entry


# ---------------------------------------------------------------------------------------------- part (b) out-of-core


def _mean_by_hand(fine: np.ndarray) -> np.ndarray:
    """The 2x2x2 mean rounded half up, by hand: an odd edge's last voxel repeated, eight strided sums."""
    f = fine.astype(np.int64)
    for axis in range(3):
        if f.shape[axis] % 2:
            f = np.concatenate([f, np.take(f, [-1], axis=axis)], axis=axis)
    total = sum(f[i::2, j::2, k::2] for i in (0, 1) for j in (0, 1) for k in (0, 1))
    return ((total + 4) // 8).astype(np.uint8)


@pytest.mark.timeout(60)
def test_pyramid_is_the_same_whatever_the_chunks_and_each_level_the_mean_of_the_finer(tmp_path):
    import zarr

    from volren.bench.bigdata import pyramid_block, pyramid_shapes, write_pyramid

    n = 36  # 36, 18, 9, 5 (9 is odd: its last voxel stands alone along each axis), 3
    assert pyramid_shapes(n, 4) == [(36,) * 3, (18,) * 3, (9,) * 3, (5,) * 3, (3,) * 3]
    written = {c: write_pyramid(tmp_path / f"c{c}.zarr", n, 0, c, 4) for c in (8, 16)}
    assert written[8]["shapes"] == [[s] * 3 for s in (36, 18, 9, 5, 3)]
    a, b = (zarr.open_group(str(tmp_path / f"c{c}.zarr"), mode="r") for c in (8, 16))
    whole = pyramid_block(n, 0, (0, 0, 0), (n, n, n))
    assert a["0"].chunks == (8, 8, 8) and b["0"].chunks == (16, 16, 16)
    assert np.array_equal(a["0"][...], whole) and np.array_equal(b["0"][...], whole)
    assert 0.05 < np.count_nonzero(whole == 0) / whole.size < 0.6 and whole.max() == 255  # a ball, filaments at 255
    for k in range(1, 5):
        assert np.array_equal(a[str(k)][...], b[str(k)][...])
        assert np.array_equal(a[str(k)][...], _mean_by_hand(a[str(k - 1)][...]))
    assert not np.array_equal(pyramid_block(n, 1, (0, 0, 0), (n, n, n)), whole)  # the seed matters
    # fine structure: level 0 holds detail its mean does not (a mean-preserving step that smooths)
    level1 = a["1"][...].astype(np.float64)
    assert np.abs(np.repeat(np.repeat(np.repeat(level1, 2, 0), 2, 1), 2, 2) - whole).mean() > 4.0
    ms = a.attrs["ome"]["multiscales"][0]
    assert [x["name"] for x in ms["axes"]] == ["z", "y", "x"]
    for k, d in enumerate(ms["datasets"]):
        assert d["path"] == str(k)
        assert d["coordinateTransformations"] == [{"type": "scale", "scale": [2.0**k] * 3},
                                                  {"type": "translation", "translation": [(2**k - 1) / 2] * 3}]


@pytest.mark.timeout(120)
def test_an_interrupted_pyramid_write_goes_on_where_it_stopped(tmp_path, monkeypatch):
    """Level-0 chunks on disk are kept (only the missing ones are made) and the coarser levels made again: the same
    file as a write from scratch."""
    import shutil

    import zarr

    from volren.bench import bigdata

    whole, part = tmp_path / "whole.zarr", tmp_path / "part.zarr"
    bigdata.write_pyramid(whole, 36, 0, 8, 4)
    bigdata.write_pyramid(part, 36, 0, 8, 4)
    gone = sorted((part / "0" / "c").glob("2/*/*"))  # the z slab 16-23 of level 0, as if stopped before it
    for chunk in gone:
        chunk.unlink()
    shutil.rmtree(part / "1")
    made = []
    block = bigdata.pyramid_block
    monkeypatch.setattr(bigdata, "pyramid_block", lambda n, seed, start, shape: made.append(start) or block(
        n, seed, start, shape))
    bigdata.write_pyramid(part, 36, 0, 8, 4, resume=True)
    assert len(gone) >= 9 and sorted(made) == sorted((16, 8 * int(c.parent.name), 8 * int(c.name)) for c in gone)
    a, b = (zarr.open_group(str(p), mode="r") for p in (whole, part))
    for k in range(5):
        assert np.array_equal(a[str(k)][...], b[str(k)][...])


@pytest.mark.timeout(120)
def test_pyramid_reads_back_through_volren_and_is_cached(tmp_path):
    from volren.bench.bigdata import make_pyramid
    from volren.data.loaders import load_volume
    from volren.stream.density import StreamedDensity

    cfg = {"outofcore": 32, "outofcore_chunk": 16, "outofcore_coarsest": 8, "seed": 0, "cache": str(tmp_path)}
    info = make_pyramid(cfg)
    stamp = os.stat(os.path.join(info["path"], "zarr.json")).st_mtime_ns
    assert make_pyramid(cfg) == info and os.stat(os.path.join(info["path"], "zarr.json")).st_mtime_ns == stamp
    assert info["shapes"] == [[32] * 3, [16] * 3, [8] * 3]
    streamed = load_volume(info["path"], stream=True, memory_budget=2**22)
    try:
        density = streamed.density
        assert isinstance(density, StreamedDensity) and density.shape == (32, 32, 32)
        # level k's voxel j is the mean of level 0's 2^k j .. 2^k j + 2^k - 1: index = (v - (2^k - 1) / 2) / 2^k
        maps = density.level_maps()
        assert np.array_equal(maps[:, :3], np.array([[1.0] * 3, [0.5] * 3, [0.25] * 3], np.float32))
        assert np.array_equal(maps[:, 3:], np.array([[0.0] * 3, [-0.25] * 3, [-0.375] * 3], np.float32))
    finally:
        streamed.density.close()
    # the same placement as level 0 read densely
    dense = load_volume(info["path"], level=0)
    assert np.allclose(dense.to_world, streamed.to_world)


@pytest.mark.timeout(300)
def test_suite_outofcore_row_holds_its_relations(tmp_path):
    from volren.bench.bigdata import GOAL_FIRST_S, GOAL_REFINE_S
    from volren.bench.runner import run_suite

    budget_mib = 0.5  # level 0 is 64^3 float32 = 1 MiB: it streams, 13 bricks on the host and 13 on the device
    overrides = {"files": [], "outofcore": 64, "outofcore_chunk": 16, "outofcore_coarsest": 16,
                 "outofcore_budget_mib": budget_mib, "outofcore_size": [48, 27], "orbit_frames": 3, "orbit_deg": 30.0,
                 "refine_timeout_s": 60.0, "cache": str(tmp_path / "c")}
    json_path, md_path, table = run_suite("bigdata", quick=True, device="cpu", out=tmp_path, overrides=overrides)
    doc = json.loads(json_path.read_text())
    assert doc["rows"] == [] and doc["summary"] == []  # no part (a) files asked
    (row,) = doc["outofcore"]
    budget = budget_mib * 2**20
    frames = row["frames_detail"]
    refine = row["refine_frames"]
    assert row["loaded"] == "StreamedDensity" and row["levels"] == 3 and row["index_box"] == "64^3"
    assert len(frames) == refine + 1 + 3 and row["orbit_frames"] == 3
    # the still camera refines: every frame before the last of the refinement has bricks pending, that one none
    assert refine >= 1 and frames[refine - 1]["bricks_pending"] == 0
    assert all(f["bricks_pending"] > 0 for f in frames[: refine - 1])
    assert row["refine_s"] == frames[refine - 1]["at_s"] and row["first_s"] == frames[0]["at_s"]
    assert row["first_s"] >= row["open_s"] + row["first_frame_s"] - 1e-3  # the clock starts before the open
    # the refined frame (the next, same camera) reads nothing: all it wants came; same needs as the first frame
    assert row["refined_pending"] == 0 and row["refined_bytes_read"] == 0 and frames[refine]["bricks_loaded"] == 0
    assert sum(row["levels_used"]) == sum(frames[0]["levels_used"]) == sum(frames[refine - 1]["levels_used"])
    assert row["levels_used_text"] == "/".join(map(str, row["levels_used"]))
    # the budget: half for the device pool, half for the host's bricks
    assert row["device_capacity"] == int(budget // 2 // row["brick_bytes"]) == 13
    assert row["device_bricks"] <= row["device_capacity"] and row["pool_bytes"] <= budget / 2
    orbit = frames[refine + 1 :]
    assert row["orbit_bytes_per_frame"] == sum(f["bytes_read"] for f in orbit) / 3
    assert row["orbit_bytes_max"] == max(f["bytes_read"] for f in orbit)
    assert row["rss_goal_mib"] == budget_mib + 1024
    assert row["met"] == ("yes" if row["first_s"] <= GOAL_FIRST_S and row["refine_s"] <= GOAL_REFINE_S
                          and row["peak_rss_mib"] <= row["rss_goal_mib"] else "no")
    assert row["peak_rss_mib"] <= row["rss_goal_mib"]  # a 1 MiB level 0 and a half-MiB budget
    assert row["psnr"] is not None  # 64^3 fits: the dense reference was rendered
    assert "| 64^3 | 3 |" in table and table in md_path.read_text()
    with pytest.raises(VolrenError, match="fits the budget"):  # 1 MiB: level 0 would load whole
        run_suite("bigdata", quick=True, device="cpu", out=tmp_path, overrides={**overrides, "outofcore_budget_mib": 1})

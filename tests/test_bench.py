"""Benchmark suites at toy sizes: the rows, ratios and files they produce (their timings are not checked)."""

from __future__ import annotations

import json
import re

import pytest

from volren.bench.resolution import run_config
from volren.bench.runner import run_suite


def test_resolution_suite_rows_and_ratios():
    cfg = {"scenes": ["cloud"], "resolution": 64, "light_grid": 16, "sizes": [(48, 27), (96, 54)], "repeats": 1,
           "reference": 64}
    result = run_config(cfg, "cpu")
    rows = result["rows"]
    assert {r["method"] for r in rows} == {"DSSRM:360:96", "DSSRM:100:48", "CMSRM:360:96", "CMSRM:100:48"}
    assert len(rows) == 4 * len(cfg["sizes"])
    smallest = [r for r in rows if r["size"] == "48x27"]
    assert all(0 < r["ssim"] <= 1 and r["psnr"] > 20 for r in smallest)
    assert all("psnr" not in r for r in rows if r["size"] == "96x54")
    at = {(r["size"], r["method"]): r for r in rows}
    # DSSRM's work follows the viewport (4x the pixels, 4x the steps, sampled or skipped as empty); at these sizes
    # CMSRM's hybrid choice marches directly (fewer projected pixels than visible texels), so its counters and image
    # equal DSSRM's.
    dssrm = [at[size, "DSSRM:360:96"]["density_samples"] + at[size, "DSSRM:360:96"]["skipped_steps"]
             for size in ("48x27", "96x54")]
    assert dssrm[1] / dssrm[0] == pytest.approx(4.0, rel=0.02)
    assert all(at[k]["density_samples"] == at[k[0], k[1].replace("CMSRM", "DSSRM")]["density_samples"]
               for k in at if k[1].startswith("CMSRM"))
    (ratio,), _ = result["summary"]
    assert ratio["scene"] == "cloud" and ratio["psnr_dssrm_minus_cmsrm"] == 0.0
    assert ratio["dssrm_over_cmsrm_largest"] == pytest.approx(
        at["96x54", "DSSRM:360:96"]["frame_min_ms"] / at["96x54", "CMSRM:360:96"]["frame_min_ms"])


def test_run_suite_writes_json_and_markdown(tmp_path):
    json_path, md_path, table = run_suite("dssrm", quick=True, device="cpu", out=tmp_path)
    doc = json.loads(json_path.read_text())
    assert doc["machine"]["device"] == "cpu" and doc["rows"]
    assert table in md_path.read_text()


def test_binocular_suite_rows_and_goals():
    from volren.bench.binocular import QUALITY_METHODS, run_config

    cfg = {"scenes": ["cloud"], "resolution": 64, "light_grid": 16, "frames": 2, "quality_size": (48, 32),
           "reference": 64, "sizes": [(64, 36)], "repeats": 1}
    result = run_config(cfg, "cpu")
    quality = [r for r in result["rows"] if r["table"] == "quality"]
    assert [r["method"] for r in quality] == list(QUALITY_METHODS)
    assert all(r["psnr"] > 20 and 0 < r["ssim"] <= 1 for r in quality)
    speed = [r for r in result["rows"] if r["table"] == "speed"]
    assert {r["method"] for r in speed} >= {"CACRM base", "CACRM +VSA", "CACRM +InS", "CACRM", "CACRM +TLOD"}
    near = [r for r in result["rows"] if r["table"] == "close-up"]
    assert len(near) == 4 and near[1]["method"].endswith("+InS") and near[1]["interleaved"] > 0
    (goals,), _ = result["summary"]
    assert 0 <= goals["coupling_gather_cut"] < 1  # at toy sizes the hybrid choice may march directly


def test_viewers_suite_rows_and_goals():
    from volren.bench.viewers import run_config

    cfg = {"scenes": ["hall"], "size": (64, 36), "slices": 16, "counts": [1, 2], "voxels": [1.0],
           "ablation": [2.0, 1.0], "overlaps": [0.5], "repeats": 1}
    result = run_config(cfg, "cpu")
    tables = {r["table"] for r in result["rows"]}
    assert tables == {"viewers", "voxel size", "shadow frustum", "overlap 50%", "arc"}
    frustum = {r["method"]: r for r in result["rows"] if r["table"] == "shadow frustum"}
    assert frustum["grid 1 m, no frustum"]["shadow_frustum_ms"] == 0 < frustum["grid 1 m"]["shadow_frustum_ms"]
    (arc,) = [r for r in result["rows"] if r["table"] == "arc"]
    assert arc["viewers"] == 2 and arc["min_psnr"] > 20
    grid = [r for r in result["rows"] if r["table"] == "viewers" and r["method"] == "grid 1 m"]
    assert all(0 <= r["flip"] < 0.5 and r["shared_bytes"] > 0 and r["shadow_voxels"] > 0 for r in grid)
    (goals,), _ = result["summary"]
    shadow_rays = {r["method"]: r["shadow_rays"] for r in result["rows"]
                   if r["table"] == "viewers" and r["viewers"] == 2}
    # exact counters: the shared grid traces fewer shadow rays than one per froxel and light per viewer (0.834 here)
    assert goals["viewers"] == 2 and goals["ray_ratio"] == shadow_rays["grid 1 m"] / shadow_rays["reference"] < 0.9


def test_vpt_suite_rows_and_goals():
    from volren.bench.vpt import CASES, run_config

    cfg = {"cases": CASES, "denoiser_table": True, "score_every": 1, "resolution": 64, "size": (24, 20),
           "spp": [1, 2], "variance_frames": 3, "variance_spp": 1, "repeats": 1,
           "denoise_size": (24, 20), "denoise_spp": 2, "rotation_frames": 3, "reference_spp": 8, "variance_at": 2,
           "variance_sequences": 3, "orbit_frames": 2, "settle_frames": 3}
    result = run_config(cfg, "cpu")
    tables = {r["table"] for r in result["rows"]}
    assert tables == {"spp", "global majorant", "shading", "denoiser"}
    summary, _ = result["summary"]
    assert len(summary) == 4 and all(s["variance_ratio"] > 0 for s in summary[:3])
    assert summary[3]["variance_ours_over_svgf"] > 0


def test_vpt_suite_splits_by_case_and_scores_every_kth_frame(monkeypatch, capsys):
    """A full-size CPU run is split across cores (`--set cases`, `denoiser_table`) and its 1024-spp references cut
    to every k-th orbit frame (`score_every`): each part holds only its tables, and the denoisers are scored on
    frames 0, k, 2k, ... (counted through the metric) while every frame is still rendered. The denoiser table (an
    hour at full size on a CPU) reports a line per step, as the timed cases do."""
    import volren.metrics
    from volren.bench.vpt import run_config
    from volren.progress import cases

    scored = []
    real_psnr = volren.metrics.psnr
    monkeypatch.setattr(volren.metrics, "psnr", lambda a, b: scored.append(a.shape) or real_psnr(a, b))
    cfg = {"cases": [], "denoiser_table": True, "score_every": 2, "resolution": 64, "size": (16, 12), "spp": [1],
           "variance_frames": 2, "variance_spp": 1, "repeats": 1, "denoise_size": (16, 12), "denoise_spp": 1,
           "rotation_frames": 5, "reference_spp": 4, "variance_at": 1, "variance_sequences": 2, "orbit_frames": 1,
           "settle_frames": 1}
    with cases("bench vpt"):
        result = run_config(cfg, "cpu")
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(" (")[1].split(",")[0] for line in lines] == [
        "4 reference frame(s) at 4 spp", "denoiser none", "denoiser ours", "denoiser svgf", "denoiser wrls"]
    assert {r["table"] for r in result["rows"]} == {"denoiser"}
    assert len(scored) == 4 * (3 + 3)  # per denoiser: orbit frames 0, 2, 4 and the 3 frames after the TF switch
    summary, _ = result["summary"]
    assert [s["scene"] for s in summary] == ["phantom (ct-muscle), denoisers"]
    part = run_config(cfg | {"cases": [["smoke", None]], "denoiser_table": False}, "cpu")
    assert {r["scene"] for r in part["rows"]} == {"smoke (density)"} and "denoiser" not in {
        r["table"] for r in part["rows"]}
    assert part["settings"]["cases"] == ["smoke (density)"]


@pytest.mark.parametrize("setting, message", [
    ({"cases": [["phantom", "nope"]]}, "--set cases: [\"phantom\", \"nope\"] is not [scene"),
    ({"cases": [], "denoiser_table": False}, "leaves bench vpt nothing to measure"),
    ({"denoiser_table": 1}, "--set denoiser_table: true or false, got 1"),
    ({"score_every": 0}, "--set score_every: a whole number of frames >= 1, got 0"),
])
def test_vpt_suite_refuses_settings_before_any_work(setting, message):
    from volren.bench.vpt import QUICK, run_config
    from volren.errors import VolrenError

    with pytest.raises(VolrenError, match=re.escape(message)):
        run_config(QUICK | setting, "nonexistent-device")  # refused before the device is touched


def test_gi_suite_rows_and_goals():
    from volren.bench.gi import METHODS, run_config

    cfg = {"scenes": ["smoke"], "resolution": 64, "light_grid": 8, "size": (24, 16), "frames": 4, "warmup": 2,
           "gt_rays": 64, "prt_rays": 32, "dynamic_frames": 4, "gt_every": 2}
    result = run_config(cfg, "cpu")
    rows = result["rows"]
    assert [r["method"] for r in rows] == list(METHODS) * 3
    assert {r["scene"] for r in rows} == {"smoke", "smoke advected 60 fps", "smoke advected 30 fps"}
    assert all(r["psnr"] > 20 and 0 < r["ssim"] <= 1 and r["gi_rays"] > 0 for r in rows)
    prt = [r for r in rows if r["method"] == "prt"]
    assert prt[0]["precompute_ms"] > 0 and prt[0]["psnr"] > max(r["psnr"] for r in rows[:4] if r["method"] != "prt")
    summary, _ = result["summary"]
    assert [s["scene"] for s in summary] == ["smoke", "smoke advected 60 fps", "smoke advected 30 fps"]
    assert summary[1]["settle_frame"] is not None
    smoke = {r["method"]: r for r in rows if r["scene"] == "smoke"}
    assert summary[0]["time_vs_restir"] == pytest.approx(smoke["sresir"]["gi_ms"] / smoke["restir"]["gi_ms"])
    assert summary[0]["db_vs_restir"] == pytest.approx(smoke["sresir"]["psnr"] - smoke["restir"]["psnr"])


# ---------------------------------------------------------------- issue 14: instance scenes, bench oit, integrated


@pytest.mark.parametrize("overlap", [False, True])
def test_instances_layout_rows_in_depth(overlap):
    import itertools

    import numpy as np

    from volren.data import builtin_scene
    from volren.data.procedural import INSTANCE_FILL

    scene = builtin_scene("instances-overlap" if overlap else "instances", 64, count=16, seed=1)
    assert len(scene.volumes) == 16 and {v.density.shape for v in scene.volumes} == {(32, 32, 32)}
    assert [v.name[:5] for v in scene.volumes[:5]] == ["smoke", "cloud", "smoke", "cloud", "cloud"]  # checkerboard
    lo, hi = scene.bounds
    np.testing.assert_allclose([lo[0], lo[2], hi[0], hi[2]], [-1.2, -1.2, 1.2, 1.2])
    boxes = [(v.corners_world.min(axis=0), v.corners_world.max(axis=0)) for v in scene.volumes]
    pitch = 2.4 / (4 - 1 + 2 * INSTANCE_FILL[overlap])
    shared = []
    for (lo_a, hi_a), (lo_b, hi_b) in itertools.combinations(boxes, 2):
        shared.append((np.minimum(hi_a, hi_b) - np.maximum(lo_a, lo_b)).min())  # < 0: separated along some axis
    # neighbours are separated by 0.2 pitch (disjoint) or share exactly 0.2 pitch (overlapping)
    assert max(shared) == pytest.approx(0.2 * pitch if overlap else -0.2 * pitch)
    # the x-z grid: every row of 4 at one depth, rows 1 pitch apart
    centres = np.array([v.center_world for v in scene.volumes])
    np.testing.assert_allclose(np.diff(np.unique(centres[:, 2].round(9))), pitch)


def test_boxes_per_ray_counts_boxes_along_the_axis():
    import numpy as np

    from volren.bench.oit import boxes_per_ray
    from volren.camera import Camera
    from volren.scene import Scene, Volume, scale_translate

    d = np.ones((4, 4, 4), np.float32)
    scene = Scene((Volume(d, scale_translate(0.2, (0, 0, 0.5))), Volume(d, scale_translate(0.2, (0, 0, -0.5))),
                   Volume(d, scale_translate(0.2, (0, 0, 5.0)))))  # the last one behind the eye
    hits = boxes_per_ray(scene, Camera(position=(0, 0, 3), look_at=(0, 0, 0), width=9, height=9, fov_y=60))
    assert hits[4, 4] == 2 and hits[0, 0] == 0 and hits.max() == 2


def test_covered_psnr_is_the_psnr_of_the_covered_pixels():
    import numpy as np

    from volren.bench.oit import covered_psnr

    ref = np.zeros((4, 4, 4), np.float32)
    ref[:2, :, :] = 0.5  # 8 covered pixels (alpha 0.5), the rest empty
    test = ref.copy()
    test[0, 0, :3] += 0.1
    test[3, 3, :3] += 5.0  # an error where the reference is empty does not count
    assert covered_psnr(ref, test) == pytest.approx(10 * np.log10(0.5**2 / (0.1**2 / 8)))


def test_oit_suite_counters_and_goals():
    from volren.bench.oit import METHODS, goals, nearest_instance, run_config
    from volren.data import builtin_scene
    from volren.render.compositing.oit import TILE_LAYOUT, tile_layout

    # light grid 12: at 8 nodes across a 64^3 instance the light map's tau interpolation blurs the puffs' shadow edges
    # (single-volume 20.7 dB at 8, 32.4 at 12; the old voxel-centre T layout 22.3 / 29.4)
    cfg = {"resolution": 64, "light_grid": 12, "counts": [16, 36], "samples": 32, "light_samples": 16, "k": 8,
           "sizes": [(48, 27)], "quality_size": (48, 27), "reference": 48, "repeats": 1,
           "scenes": ["instances-overlap"]}
    result = run_config(cfg, "cpu")
    rows = result["rows"]
    speed = {(r["instances"], r["method"]): r for r in rows if r["table"] == "speed"}
    tiles = tile_layout(48, 27, TILE_LAYOUT)
    for n in cfg["counts"]:
        sort, rt, tiled = (speed[n, m] for m in METHODS)
        assert sort["pixels"] == 2 * 48 * 27
        assert sort["box_tests"] == sort["pixels"] * n and sort["bvh_queries"] == 0  # every instance per pixel
        assert rt["bvh_queries"] == rt["pixels"] and 0 < rt["box_tests"] < sort["box_tests"]
        assert tiled["bvh_queries"] == 2 * tiles.tiles_x * tiles.tiles_y and tiled["tile_box_tests"] > 0
        assert rt["density_samples"] == sort["density_samples"]  # both exact: the same layers
        assert all(r["view_ms"] == pytest.approx(r["oit_ms"] + r["march_ms"]) for r in (sort, rt, tiled))
    quality = {(r["instances"], r["method"]): r for r in rows if r["table"] == "quality"}
    for n in cfg["counts"]:
        assert quality[n, "pixel-sort"]["psnr"] == quality[n, "pixel-rt"]["psnr"] > 20
        assert quality[n, "pixel-sort"]["psnr_single"] > 20 and quality[n, "pixel-sort"]["multi_box"] > 0.5
    scene = builtin_scene("instances", 64, count=16)
    near = nearest_instance(scene).volumes[0]
    assert all(near.center_world[2] >= v.center_world[2] for v in scene.volumes)  # front row
    summary, _ = result["summary"]
    assert summary == goals(rows, cfg)
    by_goal = {g["goal"]: g for g in summary}
    flat = by_goal["tiled box tests per pixel, 36 / 16 instances, 48x27"]
    assert flat["value"] == pytest.approx(speed[36, "tiled"]["box_tests_px"] / speed[16, "tiled"]["box_tests_px"])
    assert flat["result"] == ("pass" if flat["value"] <= 1.1 else "fail")
    contrast = by_goal["pixel-sort box tests per pixel, 36 / 16 instances, 48x27 (for contrast)"]
    assert contrast["value"] == 2.25 and contrast["result"] == "pass"
    ratio = by_goal["pixel-rt / tiled view passes (oit + march), 16 instances, 48x27"]
    assert ratio["value"] == pytest.approx(speed[16, "pixel-rt"]["view_ms"] / speed[16, "tiled"]["view_ms"])
    drop = by_goal["tiled PSNR - single-volume PSNR, instances-overlap, 36 instances [dB]"]
    assert drop["value"] == pytest.approx(quality[36, "tiled"]["psnr"] - quality[36, "tiled"]["psnr_single"])
    assert len(summary) == 2 + 2 * len(cfg["counts"]) + len(METHODS) * len(cfg["counts"])


def test_integrated_suite_rows_and_ratios():
    from volren.bench.integrated import OURS, VANILLA, run_config

    cfg = {"resolution": 64, "light_grid": 8, "counts": [4], "samples": 32, "light_samples": 16,
           "sizes": [(48, 27)], "repeats": 1}
    result = run_config(cfg, "cpu")
    rows = {r["method"]: r for r in result["rows"]}
    assert list(rows) == [VANILLA, OURS]
    for r in rows.values():
        passes = [v for k, v in r.items() if k.endswith("_ms") and k not in ("frame_ms", "frame_min_ms")]
        assert r["frame_ms"] == pytest.approx(sum(passes)) and r["fps"] == pytest.approx(1e3 / r["frame_ms"])
        assert r["gi_transform_ms"] > 0 and r["light_map_ms"] > 0
    assert "march_ms" in rows[VANILLA] and "oit_ms" not in rows[VANILLA]
    assert "cube_march_ms" in rows[OURS] and "oit_ms" in rows[OURS]  # the tiled k-buffer's phase 1
    (ratio,), _ = result["summary"]
    assert ratio["speedup"] == pytest.approx(rows[VANILLA]["frame_min_ms"] / rows[OURS]["frame_min_ms"])


def test_binocular_translucent_mesh_rows():
    from volren.bench.binocular import MESH_METHODS, run_config

    cfg = {"scenes": [], "resolution": 64, "light_grid": 16, "frames": 2, "quality_size": (48, 32),
           "reference": 64, "sizes": [(32, 18), (64, 36)], "repeats": 1, "mesh_scene": "smoke"}
    result = run_config(cfg, "cpu")
    speed = {(r["size"], r["method"]): r for r in result["rows"] if r["table"] == "transl. mesh-vol."}
    assert len(speed) == 2 * 2 * len(MESH_METHODS)
    fig9 = {r["method"]: r for r in result["rows"] if r["table"] == "fig. 9"}
    assert list(fig9) == ["CACRM vs reference", "DSSRM:360:96 vs reference", "CACRM vs DSSRM:360:96"]
    assert all(r["psnr"] > 30 and 0.9 < r["ssim"] <= 1 for r in fig9.values())
    (summary,), _ = result["summary"]
    assert summary["scene"] == "smoke + sheets"
    for m in MESH_METHODS:
        translucent, opaque = speed["64x36", f"{m} alpha 0.4"], speed["64x36", f"{m} opaque"]
        assert summary[f"mesh_cost_{m}"] == pytest.approx(translucent["frame_min_ms"] / opaque["frame_min_ms"])
        # the sheets lie behind the box: opaque or not, they hide none of the volume, so only the k-buffers differ
        assert translucent["gathers"] == opaque["gathers"]
        # the wide sheet covers about half of each view (2,504 of 4,608 pixels); opaque sheets are no layers
        assert translucent["layered"] > 0.4 * 2 * 64 * 36 and opaque["layered"] == 0


def test_serve_suite_counters_and_goal_ratios():
    import numpy as np

    from volren.bench.serve import GOAL_LATENCY_FRAMES, GOAL_SPEEDUP, STEREO_EVERY, rig_camera, run_config
    from volren.camera import Camera

    cfg = {"cases": [("dssrm", "smoke"), ("fog", "dynamic")], "resolution": 64, "size": (48, 32), "counts": [1, 4],
           "seconds": 0.5, "min_ticks": 3, "repeats": 2, "camera_hz": 30.0,
           "overrides": {"samples": 32, "light_samples": 8, "light_grid": 8}}
    result = run_config(cfg, "cpu")
    rows = {(r["scene"], r["mode"], r["clients"]): r for r in result["rows"]}
    assert len(rows) == len(result["rows"]) == 2 * 2 * 2
    for (_, mode, n), r in rows.items():
        assert r["stereo_clients"] == n // STEREO_EVERY
        assert r["ticks"] >= cfg["min_ticks"] and r["tick_ms"] == pytest.approx(1e3 * r["seconds"] / r["ticks"])
        # the scene plays, so every tick renders every client: in one call (shared) or one per client (naive)
        assert r["renders_per_tick"] == (1 if mode == "shared" else n)
        # at most one frame per client per tick (latest camera wins, nothing queued; +1: a tick in flight as the
        # window opened), and every client is served
        assert 0 < r["frames"] <= (r["ticks"] + 1) * n and r["fps_client_min"] > 0
        assert r["fps_total"] == pytest.approx(r["frames"] / r["seconds"])
        assert len(r["fps_total_windows"]) == 2 and r["fps_total"] == max(r["fps_total_windows"])  # the best window
        assert 0 < r["latency_median_ms"] <= r["latency_p95_ms"] and r["latency_worst_p95_ms"] > 0
        assert r["bytes_per_s"] / r["fps_total"] > 200  # a JPEG and its header per frame
    # the orbit keeps its distance and height and looks at the centre; the fog rig stands still and turns
    base = Camera(position=(1.0, 0.4, 3.0), look_at=(0.0, 0.2, 0.0))
    for t in (0.0, 1.3):
        orbit, look = rig_camera(base, False, 1, 4, t), rig_camera(base, True, 1, 4, t)
        assert np.hypot(orbit["position"][0], orbit["position"][2]) == pytest.approx(np.hypot(1.0, 3.0))
        assert orbit["position"][1] == pytest.approx(0.4) and orbit["look_at"] == pytest.approx([0.0, 0.2, 0.0])
        gaze = np.subtract(look["look_at"], look["position"])
        assert look["position"] == pytest.approx([1.0, 0.4, 3.0]) and gaze[1] == pytest.approx(-0.2)
        assert np.linalg.norm(gaze) == pytest.approx(np.linalg.norm([1.0, 0.2, 3.0]))
        assert gaze[0] != pytest.approx(-1.0)  # turned away from the base gaze
    summary, _ = result["summary"]
    assert [(s["scene"], s["clients"]) for s in summary] == [("smoke", 4), ("dynamic", 4)]
    for s in summary:
        shared, naive = rows[s["scene"], "shared", 4], rows[s["scene"], "naive", 4]
        assert s["speedup"] == pytest.approx(shared["fps_total"] / naive["fps_total"])
        assert s["latency_frames"] == pytest.approx(shared["latency_worst_p95_ms"] / shared["tick_ms"])
        met = s["speedup"] >= GOAL_SPEEDUP and s["latency_frames"] <= GOAL_LATENCY_FRAMES
        assert s["goals"] == ("pass" if met else "fail")


def test_load_suite_reads_what_the_reader_reads_and_reports_the_ratios():
    """``bench load`` on a 48^3 OpenVDB file: volren's grid holds the voxels tinyvdb decoded (run_config refuses a
    differing total) and the ratios are those of the row; written by pyopenvdb, so CI (CI=true) must have it."""
    import os

    from volren.bench.load import CASES, openvdb_available, run_config

    if not openvdb_available():
        if os.environ.get("CI") == "true":
            pytest.fail("/usr/bin/python3 cannot import pyopenvdb in CI: .ci/run installs python3-openvdb")
        pytest.skip("/usr/bin/python3 cannot import pyopenvdb (apt-get install python3-openvdb)")
    result = run_config({"size": 48, "repeats": 1}, [c for c in CASES if c.name == "vdb 10% sparse"])
    (row,) = result["rows"]
    assert row["shape"] != "48x48x48" and row["voxels"] < 48**3  # the active box, not the whole domain
    (ratio,), _ = result["summary"]
    assert ratio["time_ratio"] == pytest.approx(row["volren_s"] / row["reader_s"])
    assert ratio["met"] == ("yes" if ratio["time_ratio"] <= 1.2 and (ratio["memory_ratio"] or 0) <= 1.2 else "no")


def test_load_suite_omezarr_reads_the_level_zarr_reads(tmp_path, monkeypatch):
    """``bench load``'s OME-Zarr row (in-process, n = 16: a 50^3 level 0): volren and zarr's own read load the same
    voxels of the same level, also when the budget leaves only level 1 (both sides' budgets lowered)."""
    import numpy as np

    import volren.data.omezarr
    from volren.bench import load

    path = load.write_omezarr(tmp_path, 16)
    np.testing.assert_array_equal(load.volren_open(path), load.zarr_open(path))
    assert load.zarr_open(path).shape == (50, 50, 50)
    for module, name in ((load, "ZARR_BUDGET"), (volren.data.omezarr, "DEFAULT_MEMORY_BUDGET")):
        monkeypatch.setattr(module, name, 4 * 50**3 - 1)
    coarse = load.zarr_open(path)
    assert coarse.shape == (25, 25, 25)
    np.testing.assert_array_equal(load.volren_open(path), coarse)
    from volren.data.loaders import load_volume  # without stream=False the pyramid streams its level 0 instead

    streamed = load_volume(path).density
    assert streamed.streamed and streamed.shape == (50, 50, 50)
    streamed.close()


class CountingRenderer:
    """A renderer stand-in for `measure`: counts its frames."""

    name = "counting"
    config = None

    def __init__(self) -> None:
        self.frames = 0

    def render(self, scene, views, frame=0):
        from types import SimpleNamespace

        self.frames += 1
        return SimpleNamespace(stats=SimpleNamespace(times_ms={"march": 1.0}, counters={}))


def test_repeats_cut_the_timed_frames_of_measure_and_are_recorded(tmp_path):
    """``bench --repeats N``: every `measure` of the run times N frames (after its warm-up) instead of the suite's
    own, the JSON's settings say so and the run's wall time is recorded; a suite not timed by `measure` refuses the
    flag before any work, and so does a count below 1."""
    from volren.bench import Suite, measure
    from volren.camera import Camera
    from volren.errors import VolrenError

    renderer = CountingRenderer()

    def run(quick, device):
        measure(renderer, None, [Camera(width=8, height=8)], 5)
        return {"settings": {"repeats": 5}, "rows": [{"frames": renderer.frames}], "columns": [("frames", "n", "d")]}

    json_path, _, _ = run_suite("toy", quick=True, device="cpu", out=tmp_path, suite=Suite("toy", "", run, True),
                                repeats=2)
    doc = json.loads(json_path.read_text())
    assert doc["rows"] == [{"frames": 3}]  # warm-up + 2, not + 5
    assert doc["settings"]["repeats"] == 2 and doc["settings"]["repeats_cut_from_suite"]
    assert doc["elapsed_s"] >= 0
    run_suite("toy", quick=True, device="cpu", out=tmp_path, suite=Suite("toy", "", run, True))
    assert renderer.frames == 3 + 6
    def untimed(quick, device):
        raise AssertionError("a suite that refuses --repeats ran")

    with pytest.raises(VolrenError, match="--repeats: bench untimed times its work its own way"):
        run_suite("untimed", quick=True, device="cpu", out=tmp_path, suite=Suite("untimed", "", untimed), repeats=1)
    with pytest.raises(VolrenError, match="at least 1"):
        run_suite("toy", quick=True, device="cpu", out=tmp_path, suite=Suite("toy", "", run, True), repeats=0)


def test_set_replaces_suite_settings_and_refuses_unknown_keys(tmp_path):
    """``bench --set KEY=VALUE``: `sized` hands the suite its configuration with the entry replaced (recorded in the
    JSON's settings); a key the suite does not have, or a suite that takes no settings, is refused with the flag
    named, before the suite's work."""
    from volren.bench import Suite, sized
    from volren.cli import bench_overrides
    from volren.errors import VolrenError

    def run(quick, device):
        cfg = sized({"frames": 12, "size": [96, 64]}, {"frames": 60, "size": [480, 270]}, quick)
        return {"settings": cfg, "rows": [cfg], "columns": [("frames", "frames", "d")]}

    toy = Suite("toy", "", run, settable=True)
    json_path, md_path, _ = run_suite("toy", quick=False, device="cpu", out=tmp_path, suite=toy,
                                      overrides=bench_overrides(["frames=6"]))
    doc = json.loads(json_path.read_text())
    assert doc["rows"] == [{"frames": 6, "size": [480, 270]}] and doc["settings"]["overridden"] == ["frames"]
    assert "frames = 6" in md_path.read_text()
    with pytest.raises(VolrenError, match="--set sizes: not a setting of this suite; it has frames, size"):
        run_suite("toy", quick=True, device="cpu", out=tmp_path, suite=toy, overrides={"sizes": 1})
    def fixed(quick, device):
        raise AssertionError("a suite without settings ran")

    with pytest.raises(VolrenError, match="--set: bench fixed has no settings"):
        run_suite("fixed", quick=True, device="cpu", out=tmp_path, suite=Suite("fixed", "", fixed), overrides={"a": 1})
    assert bench_overrides(["sizes=[[8, 8]]", "scene=smoke"]) == {"sizes": [[8, 8]], "scene": "smoke"}


def test_viewer_rigs_are_nested():
    """Each count's rig is the first viewers of the largest, so the scaling ratio compares the same viewers."""
    from volren.bench.viewers import nested_rigs
    from volren.camera import Camera
    from volren.data.fog_scenes import fog_scene_camera, fog_scene_walk_area

    spot = fog_scene_camera("hall")
    base = Camera(position=spot["position"], look_at=spot["look_at"], width=32, height=18)
    rigs = nested_rigs(base, [1, 2, 16], fog_scene_walk_area("hall"))
    assert [len(v) for v in rigs.values()] == [1, 2, 16]
    assert rigs[1] == rigs[16][:1] and rigs[2] == rigs[16][:2]
    assert len({v.position for v in rigs[16]}) == 16


def test_gi_suite_times_without_ground_truth(capfd):
    """gt_rays = 0 times the chosen methods with no brute-force grid: no quality, the time ratio kept; each
    method's sequence is reported as a case done (a full-size run takes an hour)."""
    from volren.bench.gi import run_config
    from volren.progress import cases

    cfg = {"scenes": ["smoke"], "resolution": 64, "light_grid": 8, "size": (24, 16), "frames": 3, "warmup": 1,
           "gt_rays": 0, "prt_rays": 32, "dynamic_frames": 2, "gt_every": 1, "methods": ["restir", "sresir"]}
    with cases("bench gi"):
        result = run_config(cfg, "cpu")
    done = [line for line in capfd.readouterr().err.splitlines() if line.startswith("volren: bench gi: case")]
    assert len(done) == 6 and "(sresir GI, 3 frame(s) of 24x16)" in done[1] and "2 frame(s)" in done[-1]
    rows = result["rows"]
    assert [r["method"] for r in rows] == ["restir", "sresir"] * 3
    assert all(r["psnr"] is None and r["ssim"] is None and r["gi_ms"] > 0 and r["gi_rays"] > 0 for r in rows)
    assert all(r["settle_frame"] is None for r in rows[2:]) and result["resampling"] == []
    summary, _ = result["summary"]
    assert summary[0]["time_vs_restir"] == pytest.approx(rows[1]["gi_ms"] / rows[0]["gi_ms"])
    assert summary[0]["db_vs_restir"] is None and summary[0]["db_vs_major"] is None


@pytest.mark.parametrize("setting", [{"methods": ["sresir", "bogus"]}, {"methods": []}, {"gt_rays": -1}])
def test_gi_suite_refuses_bad_settings(setting):
    from volren.bench.gi import run_config
    from volren.errors import VolrenError

    cfg = {"scenes": ["smoke"], "resolution": 64, "light_grid": 8, "size": (24, 16), "frames": 3, "warmup": 1,
           "gt_rays": 0, "prt_rays": 32, "dynamic_frames": 2, "gt_every": 1} | setting
    with pytest.raises(VolrenError, match=f"--set {next(iter(setting))}"):
        run_config(cfg, "cpu")

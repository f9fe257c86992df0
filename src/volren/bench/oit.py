"""Suite ``oit``: multi-volume order-independent transparency (paper 000 §3.4, Table 3; paper 001 §3.4; issue 14).

The three ways a pixel finds the boxes its ray meets (`volren.render.compositing.oit`): per-pixel k-buffer sorting
(``pixel-sort``: every instance tested), per-pixel ray tracing (``pixel-rt``: a BVH query) and the tiled k-buffer
(``tiled``: one BVH ray per tile of the fixed 240 x 135 layout, then only the tile's instances per pixel), all with
the same renderer and settings (DSSRM:V:L), so that they differ in the layer finding alone. K = 16, the most a
pixel keeps and, since issue 19, the renderers' default: from the default eye, rays through ``instances-overlap``
at N = 36 cross up to 12 boxes (252 of the 14,400 pixels at 160x90 cross more than 8), and with K = 8 the farthest
are dropped (quick run: PSNR 11.6 dB (pixel-sort, pixel-rt) and 19.2 dB (tiled) under the single-volume PSNR; with
K = 16 all three score 41.50 dB).

Speed (Table 3): scene ``instances`` (N = 4, 16, 36 smoke and cloud instances in rows receding in depth, disjoint
boxes, `volren.data.procedural.instances_layout`) from the default camera, stereo at three viewport sizes: time per
pass (median of the timed frames; ``oit`` = the tiled phase 1, ``march`` = the per-pixel march with its layer finding)
and per-pixel counters: box tests (exact ray/box tests in the march), BVH queries, density samples; the tiled phase
1's box tests are per tile and reported as a total.

Quality: both ``instances`` (disjoint; rays cross up to sqrt(N) boxes) and ``instances-overlap`` (neighbours overlap,
so rays cross overlapping spans, marched jointly) against ``--method reference`` at the quality size. PSNR is over
the covered pixels (the reference's alpha > 1/255; the peak is the reference's, as `volren.metrics.psnr`): the
instances cover a few percent of the frame, and a PSNR over the empty background would grow with the empty share.
"Single-volume PSNR" is concrete: the same method and settings, same views, on the instance nearest the eye alone
(the scene with that one volume), against the reference of that one-volume scene, PSNR over its covered pixels.
``multi_box`` is the share of covered pixels whose ray crosses two or more boxes (host-side slab test).

Goals (issue 14), as ratios of this run's rows, printed pass/fail: tiled per-pixel box tests at 36 instances over
those at 16, at the largest size, at most 1.1 ("flat"); the tiled frame time at the largest size below both
baselines' for every N, timing the passes that differ (``oit`` + ``march``: the light map is the same
per-instance work for all three, and at 36 instances on a shared CPU its noise exceeds their differences);
every method's PSNR within 1 dB of its single-volume PSNR on both scenes and every N.
Full (GPU): 128^3 instances (resolution 256), 96^3 light grids, 1080p/2K/4K stereo, quality at 480x270 against the
reference at 1024:1024. Quick (CPU): 32^3 instances, 24^3 light grids, sizes / 4, quality at 160x90 against 256:256.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from volren.bench import Suite, bench_scene, measure, sized
from volren.camera import Camera, make_views
from volren.render import DSSRM, DSSRMConfig, Reference, ReferenceConfig
from volren.scene import Scene

FULL = {"resolution": 256, "light_grid": 96, "counts": [4, 16, 36], "samples": 100, "light_samples": 48, "k": 16,
        "sizes": [(1920, 1080), (2560, 1440), (3840, 2160)], "quality_size": (480, 270), "reference": 1024,
        "repeats": 5, "scenes": ["instances", "instances-overlap"]}
QUICK = {"resolution": 64, "light_grid": 24, "counts": [4, 16, 36], "samples": 100, "light_samples": 48, "k": 16,
         "sizes": [(480, 270), (640, 360), (960, 540)], "quality_size": (160, 90), "reference": 256, "repeats": 3,
         "scenes": ["instances", "instances-overlap"]}
EYE = (0.0, 0.4, 3.2)
"""the CLI's default camera position (looking at the origin): rows of instances recede from it in depth"""
METHODS = ("pixel-sort", "pixel-rt", "tiled")
FLAT_GOAL = 1.1
PSNR_GOAL_DB = -1.0
COVERED_ALPHA = 1.0 / 255.0



def renderer(scheme: str, cfg: dict[str, Any], device: str) -> DSSRM:
    return DSSRM(DSSRMConfig(samples=cfg["samples"], light_samples=cfg["light_samples"], light_grid=cfg["light_grid"],
                             oit=scheme, oit_k=cfg["k"]), device)


def stereo(size: tuple[int, int]) -> list[Camera]:
    return make_views(Camera(position=EYE, width=size[0], height=size[1]), "stereo")


def boxes_per_ray(scene: Scene, cam: Camera) -> np.ndarray:
    """(H, W) the number of volume boxes each pixel's ray meets in front of the eye (slab test on the host)."""
    d = cam.ray_directions().reshape(-1, 3)
    hits = np.zeros(d.shape[0], dtype=np.int32)
    for v in scene.volumes:
        m = v.to_local
        o = m[:3, :3] @ np.asarray(cam.position, dtype=np.float64) + m[:3, 3]
        dl = d @ m[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            ta, tb = (-1.0 - o) * inv, (1.0 - o) * inv
        t0 = np.nanmax(np.minimum(ta, tb), axis=1)
        t1 = np.nanmin(np.maximum(ta, tb), axis=1)
        hits += (t1 > np.maximum(t0, 0.0)).astype(np.int32)
    return hits.reshape(cam.height, cam.width)


def covered_psnr(ref: np.ndarray, test: np.ndarray) -> float:
    """PSNR [dB] over the pixels where the reference has medium (alpha > 1/255), peak = the reference's RGB peak."""
    mask = ref[..., 3] > COVERED_ALPHA
    err = (ref[mask, :3].astype(np.float64) - test[mask, :3]) ** 2
    mse = float(err.mean())
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(float(ref[..., :3].max()) ** 2 / mse))


def nearest_instance(scene: Scene) -> Scene:
    """The scene with only the instance whose box centre is nearest the eye."""
    near = min(scene.volumes, key=lambda v: float(np.linalg.norm(v.center_world - np.asarray(EYE))))
    return dataclasses.replace(scene, volumes=(near,), name=f"{scene.name}-{near.name}")


def mean_psnr(refs: list[np.ndarray], images: list[np.ndarray]) -> float:
    return float(np.mean([covered_psnr(r, i) for r, i in zip(refs, images, strict=True)]))


def quality_rows(cfg: dict[str, Any], device: str) -> list[dict[str, Any]]:
    views = stereo(cfg["quality_size"])
    reference = Reference(ReferenceConfig(samples=cfg["reference"], light_samples=cfg["reference"]), device)
    rows = []
    for name in cfg["scenes"]:
        for n in cfg["counts"]:
            scene = bench_scene(name, cfg["resolution"], count=n)
            single = nearest_instance(scene)
            refs = reference.render(scene, views).images
            single_refs = reference.render(single, views).images
            crossings = boxes_per_ray(scene, views[0])
            covered = refs[0][..., 3] > COVERED_ALPHA
            for scheme in METHODS:
                r = renderer(scheme, cfg, device)
                multi = mean_psnr(refs, r.render(scene, views).images)
                alone = mean_psnr(single_refs, r.render(single, views).images)
                rows.append({"table": "quality", "scene": name, "instances": n, "method": scheme, "psnr": multi,
                             "psnr_single": alone, "psnr_drop": multi - alone,
                             "multi_box": float((crossings[covered] >= 2).mean())})
    return rows


def speed_rows(cfg: dict[str, Any], device: str) -> list[dict[str, Any]]:
    rows = []
    for n in cfg["counts"]:
        scene = bench_scene("instances", cfg["resolution"], count=n)
        for size in cfg["sizes"]:
            views = stereo(size)
            pixels = sum(c.width * c.height for c in views)
            for scheme in METHODS:
                row = measure(renderer(scheme, cfg, device), scene, views, cfg["repeats"])
                row.pop("frame")
                rows.append({"table": "speed", "instances": n, "size": f"{size[0]}x{size[1]}", "method": scheme,
                             "pixels": pixels, "frame_ms": row["frame_ms"], "frame_min_ms": row["frame_min_ms"],
                             "light_map_ms": row.get("light_map_ms", 0.0), "oit_ms": row.get("oit_ms", 0.0),
                             "march_ms": row.get("march_ms", 0.0),
                             "view_ms": row.get("oit_ms", 0.0) + row.get("march_ms", 0.0),
                             "box_tests": row["box_tests"],
                             "tile_box_tests": row["tile_box_tests"], "bvh_queries": row["bvh_queries"],
                             "density_samples": row["density_samples"],
                             "box_tests_px": row["box_tests"] / pixels,
                             "samples_px": row["density_samples"] / pixels})
    return rows


def goal(text: str, value: float, target: str, ok: bool) -> dict[str, Any]:
    return {"goal": text, "value": value, "target": target, "result": "pass" if ok else "fail"}


def goals(rows: list[dict[str, Any]], cfg: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's goals as ratios of ``rows`` (module docstring)."""
    big = "{}x{}".format(*cfg["sizes"][-1])
    speed = {(r["instances"], r["method"]): r for r in rows if r["table"] == "speed" and r["size"] == big}
    out = []
    counts = cfg["counts"]
    if 16 in counts and 36 in counts:
        flat = speed[36, "tiled"]["box_tests_px"] / speed[16, "tiled"]["box_tests_px"]
        out.append(goal(f"tiled box tests per pixel, 36 / 16 instances, {big}", flat, f"<= {FLAT_GOAL}",
                        flat <= FLAT_GOAL))
        sort = speed[36, "pixel-sort"]["box_tests_px"] / speed[16, "pixel-sort"]["box_tests_px"]
        out.append(goal(f"pixel-sort box tests per pixel, 36 / 16 instances, {big} (for contrast)", sort, "= 2.25",
                        sort == 36 / 16))
    for n in counts:
        for base in ("pixel-sort", "pixel-rt"):
            ratio = speed[n, base]["view_ms"] / speed[n, "tiled"]["view_ms"]
            out.append(goal(f"{base} / tiled view passes (oit + march), {n} instances, {big}", ratio, "> 1",
                            ratio > 1.0))
    for r in rows:
        if r["table"] == "quality":
            out.append(goal(f"{r['method']} PSNR - single-volume PSNR, {r['scene']}, {r['instances']} instances "
                            "[dB]", r["psnr_drop"], f">= {PSNR_GOAL_DB}", r["psnr_drop"] >= PSNR_GOAL_DB))
    return out


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    rows = speed_rows(cfg, device) + quality_rows(cfg, device)
    columns = [
        ("table", "table", "s"), ("scene", "scene", "s"), ("instances", "N", "d"), ("size", "stereo view size", "s"),
        ("method", "OIT", "s"), ("frame_ms", "frame [ms]", ".1f"), ("frame_min_ms", "fastest [ms]", ".1f"),
        ("light_map_ms", "light map [ms]", ".1f"), ("oit_ms", "oit phase 1 [ms]", ".2f"),
        ("march_ms", "march [ms]", ".1f"), ("view_ms", "oit + march [ms]", ".1f"),
        ("box_tests_px", "box tests / px", ".3f"),
        ("tile_box_tests", "phase-1 box tests", ","), ("bvh_queries", "BVH queries", ","),
        ("samples_px", "samples / px", ".2f"), ("psnr", "PSNR covered [dB]", ".2f"),
        ("psnr_single", "single-volume PSNR [dB]", ".2f"), ("psnr_drop", "difference [dB]", ".2f"),
        ("multi_box", "covered px crossing >= 2 boxes", ".2f"),
    ]
    summary_columns = [("goal", "goal (issue 14)", "s"), ("value", "measured", ".3f"), ("target", "target", "s"),
                       ("result", "result", "s")]
    settings = {k: v for k, v in cfg.items() if k not in ("sizes", "quality_size")} | {
        "sizes": [f"{w}x{h}" for w, h in cfg["sizes"]], "quality_size": "x".join(map(str, cfg["quality_size"])),
        "renderer": f"DSSRM:{cfg['samples']}:{cfg['light_samples']}, oit_k {cfg['k']}",
        "camera": f"eye {EYE} looking at the origin, stereo ipd 0.063 m",
    }
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (goals(rows, cfg), summary_columns)}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(sized(QUICK, FULL, quick), device)


SUITE = Suite("oit", "multi-volume OIT: per-pixel k-buffer sorting, per-pixel ray tracing and the tiled k-buffer "
              "at 4, 16, 36 instances, time, counters and PSNR against the reference (paper 000 Table 3)", run,
              repeats=True, settable=True)

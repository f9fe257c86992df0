"""Suite ``interactive``: frames per second of one viewer of the default scene (smoke 64^3, the CLI's default eye) per
method and quality preset, with and without empty-space skipping (issue 15 item 4: >= 10 fps at 480x270 on two CPU
cores; on a GPU, 1080p stereo at headset rates).

Frames per second = 1 / the median wall time of a whole ``render`` call on a warm renderer, the scene unchanged (so
the interactive preset's light map, kept while the scene stands still, is computed in the warm-up frame only); the
runs take turns frame by frame, so other jobs on a shared machine slow them alike. On
the CPU each row also gives the process CPU time per frame (all threads), the figure least disturbed by other jobs
on a shared machine, and the median time of each pass. Work: density samples, steps skipped, light samples (exact
counters). Quality: PSNR of the (left) image against the reference renderer at the same size (single scattering;
VPT's multiple scattering differs from it by design, so its PSNR is no quality figure). Fog, whose scenes are not
the default one, is timed on ``hall`` from its own viewpoint, its PSNR taken against its default-quality image.
Quick (CPU): 480x270 mono. Full (GPU): 1920x1080 stereo.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from volren.bench import NOT_PASSES, Suite, bench_scene
from volren.camera import Camera, make_views
from volren.data.fog_scenes import fog_scene, fog_scene_camera
from volren.metrics import psnr
from volren.presets import quality_config
from volren.render import METHODS, Reference, ReferenceConfig

EYE = (0.0, 0.4, 3.2)
"""The CLI's default camera position (``--camera-pos``)."""
QUICK = {"resolution": 64, "size": (480, 270), "views": "mono", "repeats": 10, "reference": 1024}
FULL = {"resolution": 64, "size": (1920, 1080), "views": "stereo", "repeats": 20, "reference": 1024}
RUNS = [("dssrm", "interactive", True), ("dssrm", "interactive", False), ("dssrm", "default", True),
        ("dssrm", "default", False), ("cmsrm", "interactive", True), ("cmsrm", "default", True),
        ("cacrm", "interactive", True), ("cacrm", "default", True), ("vpt", "interactive", None),
        ("vpt", "default", None)]
"""(method, quality, empty-space skipping: on, off, or None where the method has no such switch)"""
GOAL_FPS = 10.0


def timed_frame(renderer, scene, views: list[Camera], frame: int) -> tuple[float, float, Any]:
    """(wall [s], process CPU [s], frame) of one whole ``render`` call."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = renderer.render(scene, views, frame=frame)
    return time.perf_counter() - wall, time.process_time() - cpu, out


def summary(timings: list[tuple[float, float, Any]]) -> dict[str, Any]:
    """fps from the median wall time, the fastest frame, the median CPU time and pass times, the last frame."""
    walls, cpus, frames = zip(*timings, strict=True)
    passes = sorted({k for f in frames for k in f.stats.times_ms if k not in NOT_PASSES})
    wall_ms = 1e3 * statistics.median(walls)
    medians = {k: statistics.median(f.stats.times_ms.get(k, 0.0) for f in frames) for k in passes}
    return {"fps": 1e3 / wall_ms, "render_ms": wall_ms, "render_min_ms": 1e3 * min(walls),
            "cpu_ms": 1e3 * statistics.median(cpus), **{f"{k}_ms": v for k, v in medians.items()},
            "passes": ", ".join(f"{k} {v:.1f}" for k, v in medians.items()), "frame": frames[-1]}


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    """Every run's renderer is warmed up first, then the runs take turns frame by frame (``repeats`` rounds), so
    other jobs on a shared machine slow them alike."""
    scene = bench_scene("smoke", cfg["resolution"])
    width, height = cfg["size"]
    views = make_views(Camera(position=EYE, width=width, height=height), cfg["views"])
    reference = Reference(ReferenceConfig(samples=cfg["reference"], light_samples=cfg["reference"]), device)
    ref = reference.render(scene, views[:1]).images[0]
    spot = fog_scene_camera("hall")
    hall = fog_scene("hall")
    hall_views = make_views(Camera(position=spot["position"], look_at=spot["look_at"], width=width, height=height,
                                   fov_y=60.0), cfg["views"])
    runs = [(m, q, skip, "smoke", scene, views) for m, q, skip in RUNS]
    runs += [("fog", q, None, "hall", hall, hall_views) for q in ("default", "interactive")]
    configs = [quality_config(m, q, **({} if skip is None else {"skip_empty": skip})) for m, q, skip, *_ in runs]
    renderers = [METHODS[run[0]][0](config, device) for run, config in zip(runs, configs, strict=True)]
    for r, (*_, sc, vs) in zip(renderers, runs, strict=True):
        r.render(sc, vs)
    timings: list[list[tuple[float, float, Any]]] = [[] for _ in runs]
    for i in range(cfg["repeats"]):
        for k, (r, (*_, sc, vs)) in enumerate(zip(renderers, runs, strict=True)):
            timings[k].append(timed_frame(r, sc, vs, i + 1))
    rows, fog_default = [], None
    for (method, quality, skip, scene_name, _, _), config, times in zip(runs, configs, timings, strict=True):
        row = summary(times)
        frame = row.pop("frame")
        c = frame.stats.counters
        fields = ("samples", "light_samples", "light_grid", "spp", "max_bounces", "slices", "tile")
        settings = {k: getattr(config, k) for k in fields if hasattr(config, k)}
        if method == "fog" and quality == "default":
            fog_default = frame.images[0]
        against = fog_default if method == "fog" else ref
        rows.append({"method": method, "scene": scene_name, "quality": quality,
                     "skip": {None: "", True: "on", False: "off"}[skip],
                     "settings": ", ".join(f"{k} {v}" for k, v in settings.items()), **row,
                     "density_samples": c["density_samples"], "skipped_steps": c["skipped_steps"],
                     "light_samples": c["light_samples"], "shadow_rays": c["shadow_rays"],
                     "psnr": psnr(against, frame.images[0]), "psnr_against": "fog default" if method == "fog"
                     else "reference", "goal_met": row["fps"] >= GOAL_FPS})
    columns = [
        ("method", "method", "s"), ("scene", "scene", "s"), ("quality", "quality", "s"), ("skip", "skipping", "s"),
        ("settings", "settings", "s"), ("fps", "fps", ".1f"), ("render_ms", "render [ms]", ".1f"),
        ("render_min_ms", "fastest [ms]", ".1f"), ("cpu_ms", "CPU [ms]", ".1f"),
        ("passes", "median pass times [ms]", "s"),
        ("density_samples", "density samples", ","), ("skipped_steps", "skipped steps", ","),
        ("light_samples", "light samples", ","), ("shadow_rays", "shadow rays", ","), ("psnr", "PSNR [dB]", ".2f"),
        ("psnr_against", "PSNR against", "s"),
    ]
    settings = {"scene": "smoke", **cfg, "size": f"{width}x{height}", "camera": list(EYE), "goal_fps": GOAL_FPS}
    return {"settings": settings, "rows": rows, "columns": columns}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(QUICK if quick else FULL, device)


SUITE = Suite("interactive", "frames per second of one viewer of the default scene per method and quality preset, "
              "empty-space skipping on and off (issue 15 item 4)", run)

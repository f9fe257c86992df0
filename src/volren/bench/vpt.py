"""Suite ``vpt``: paper 002 Fig. 9 (frame time and samples per second against spp), the acceleration structure
(macrocell octree against one global majorant: time, tentative collisions, build time, memory) and Fig. 3 (the
surface-medium coexistence model's per-pixel variance against Exposure Render's at equal spp and equal mean).

Scenes: the phantom with the CT muscle/skin transfer function, the phantom with the bone preset (CT-like, mostly
empty: where skipping pays), and the smoke plume with extinction proportional to density. The denoiser rows of the
issue (raw and denoised PSNR along a rotation, output variance, convergence) wait for the denoiser.
Full (GPU): 256^3, 1440x1190 (the paper's viewport), spp 1-32. Quick (CPU): 64^3, 128x106, spp 1-8.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from volren.bench import Suite, measure
from volren.camera import Camera
from volren.data import builtin_scene
from volren.render import VPT, VPTConfig

FULL = {"resolution": 256, "size": (1440, 1190), "spp": [1, 2, 4, 8, 16, 32], "variance_frames": 32,
        "variance_spp": 4, "repeats": 3}
QUICK = {"resolution": 64, "size": (128, 106), "spp": [1, 2, 4, 8], "variance_frames": 16, "variance_spp": 2,
         "repeats": 2}
CASES = [("phantom", "ct-muscle"), ("phantom", "ct-bone"), ("smoke", None)]


def case_name(scene: str, transfer: str | None) -> str:
    return f"{scene} ({transfer or 'density'})"


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    rows, summary = [], []
    cam = Camera(position=(1.6, 1.2, 2.4), width=cfg["size"][0], height=cfg["size"][1], fov_y=40.0)
    for scene_name, transfer in CASES:
        scene = builtin_scene(scene_name, cfg["resolution"])
        name = case_name(scene_name, transfer)
        for spp in cfg["spp"]:
            for global_majorant in (False, True) if spp == cfg["spp"][0] else (False,):
                r = VPT(VPTConfig(spp=spp, transfer=transfer, global_majorant=global_majorant), device)
                row = measure(r, scene, [cam], cfg["repeats"])
                frame = row.pop("frame")
                paths = cam.width * cam.height * spp
                rows.append({"table": "global majorant" if global_majorant else "spp", "scene": name, "spp": spp,
                             "frame_ms": row["frame_ms"], "paths_per_s": paths / (row["frame_min_ms"] * 1e-3),
                             "density_lookups": row["density_samples"], "light_lookups": row["light_samples"],
                             "majorant_bytes": frame.stats.info["majorant_bytes"],
                             "majorant_build_ms": frame.stats.info["majorant_build_ms"]})
        means, variances = {}, {}
        for shading in ("er", "coexist"):
            r = VPT(VPTConfig(spp=cfg["variance_spp"], transfer=transfer, shading=shading, max_bounces=1), device)
            stack = np.stack([r.render(scene, [cam], f).images[0][..., :3] for f in range(cfg["variance_frames"])])
            means[shading], variances[shading] = stack.mean(0), stack.var(0, ddof=1).sum()
            rows.append({"table": "shading", "scene": name, "spp": cfg["variance_spp"], "method": shading,
                         "image_mean": float(stack.mean()), "pixel_variance_sum": float(variances[shading])})
        octree = next(r for r in rows if r["table"] == "spp" and r["scene"] == name and r["spp"] == cfg["spp"][0])
        flat = next(r for r in rows if r["table"] == "global majorant" and r["scene"] == name)
        summary.append({
            "scene": name,
            "variance_ratio": variances["coexist"] / variances["er"],
            "mean_ratio": float(means["coexist"].mean() / max(means["er"].mean(), 1e-12)),
            "octree_speedup": flat["frame_ms"] / octree["frame_ms"],
            "lookup_ratio": octree["density_lookups"] / max(flat["density_lookups"], 1),
        })
    columns = [
        ("table", "table", "s"), ("scene", "scene", "s"), ("spp", "spp", "d"), ("method", "shading", "s"),
        ("frame_ms", "frame [ms]", ".1f"), ("paths_per_s", "paths/s", ",.0f"),
        ("density_lookups", "density lookups", ","), ("light_lookups", "transmittance lookups", ","),
        ("majorant_bytes", "majorant bytes", ","), ("majorant_build_ms", "majorant build [ms]", ".1f"),
        ("image_mean", "image mean", ".5f"), ("pixel_variance_sum", "summed pixel variance", ".4f"),
    ]
    summary_columns = [
        ("scene", "scene", "s"), ("variance_ratio", "variance coexist / ER (goal < 1)", ".3f"),
        ("mean_ratio", "mean coexist / ER (goal 1)", ".4f"),
        ("octree_speedup", "time global majorant / octree", ".2f"),
        ("lookup_ratio", "lookups octree / global", ".3f"),
    ]
    settings = {k: v for k, v in cfg.items() if k != "size"} | {"size": "x".join(map(str, cfg["size"])),
                                                                 "cases": [case_name(*c) for c in CASES]}
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(QUICK if quick else FULL, device)


SUITE = Suite("vpt", "volumetric path tracing: time and paths/s against spp, macrocell octree vs global majorant, "
              "coexistence vs Exposure Render variance (paper 002 Fig. 3, 9)", run)

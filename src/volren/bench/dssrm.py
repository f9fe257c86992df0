"""Suite ``dssrm``: DSSRM time per stereo frame at 1080p, 2K and 4K with a 256^3 volume at 360:96 and 100:48
(paper 000 Table 1 columns; the paper reports 2.35 ms and 1.79 ms per 1080p stereo frame on an RX 6800).

Reports per configuration the median over repeats of each pass's wall time (device-synchronised), the exact work
counters, and density samples per second of the march pass. On the CPU it also measures one thread alone (the
issue's goal: >= 50 M trilinear samples/s per thread; the march's trilinear fetches are its density samples plus its
light-map lookups).
"""

from __future__ import annotations

from typing import Any

from volren.bench import Suite, bench_scene, cpu_thread_limit, measure
from volren.camera import Camera, make_views
from volren.render import DSSRM, DSSRMConfig

FULL = {"resolution": 256, "light_grid": 128, "sizes": [(1920, 1080), (2560, 1440), (3840, 2160)], "repeats": 5}
QUICK = {"resolution": 64, "light_grid": 32, "sizes": [(192, 108), (384, 216)], "repeats": 5}
SETTINGS = [(360, 96), (100, 48)]


def rates(row: dict[str, Any]) -> dict[str, Any]:
    """Samples per second of the march (density, and all trilinear fetches) and of the light-map pass."""
    march, light = row["march_ms"], row.get("light_map_ms", 0.0)
    return {
        "march_msamples_per_s": row["density_samples"] / march / 1e3 if march else None,
        # Light-map lookups are trilinear fetches too (of the light grid instead of the density).
        "march_trilinear_per_s": (row["density_samples"] + row["lightmap_lookups"]) / march / 1e3 if march else None,
        "light_msamples_per_s": row["light_samples"] / light / 1e3 if light else None,
    }


def run(quick: bool, device: str) -> dict[str, Any]:
    cfg = QUICK if quick else FULL
    scene = bench_scene("smoke", cfg["resolution"])
    rows = []
    thread_modes = [None, 1] if device == "cpu" else [None]
    for width, height in cfg["sizes"]:
        views = make_views(Camera(position=(0.0, 0.4, 3.2), width=width, height=height), "stereo")
        for v, lsamp in SETTINGS:
            for threads in thread_modes:
                with cpu_thread_limit(threads):
                    r = DSSRM(DSSRMConfig(samples=v, light_samples=lsamp, light_grid=cfg["light_grid"]), device)
                    row = measure(r, scene, views, cfg["repeats"])
                row.pop("frame")
                rows.append({"size": f"{width}x{height}", "method": f"DSSRM:{v}:{lsamp}",
                             "threads": threads or "all", **row, **rates(row)})
    columns = [
        ("size", "view size", "s"), ("method", "method", "s"), ("threads", "CPU threads", ""),
        ("frame_ms", "stereo frame [ms]", ".2f"), ("light_map_ms", "light map [ms]", ".2f"),
        ("march_ms", "march [ms]", ".2f"), ("density_samples", "density samples", ","),
        ("light_samples", "light samples", ","), ("march_msamples_per_s", "march density Msamples/s", ".1f"),
        ("march_trilinear_per_s", "march trilinear M/s", ".1f"),
        ("light_msamples_per_s", "light map Msamples/s", ".1f"),
    ]
    settings = {"scene": "smoke", **{k: v for k, v in cfg.items() if k != "sizes"},
                "sizes": [f"{w}x{h}" for w, h in cfg["sizes"]], "views": "stereo", "camera": [0.0, 0.4, 3.2]}
    return {"settings": settings, "rows": rows, "columns": columns}


SUITE = Suite("dssrm", "DSSRM stereo frame time at several sizes and V:L (paper 000 Table 1 columns)", run,
              repeats=True)

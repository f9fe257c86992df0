"""Suite ``resolution``: DSSRM against CMSRM as the viewport grows (paper 001 Table 1; paper 000 Table 1's DSSRM
and CMSRM columns).

Per built-in scene, a stereo pair at each size, DSSRM and CMSRM at 360:96 and 100:48 (V or N_max : L): median time
per pass and per frame, density samples, cube-map memory, and, at the smallest size, PSNR/SSIM of the left eye
against the reference. Goals, as ratios from one run: CMSRM's time at the largest size over the smallest <= 1.35;
DSSRM over CMSRM at the largest size >= 4 at 360:96; CMSRM:360:96 within 2 dB of DSSRM:360:96. The ratios use each
configuration's fastest frame, the least disturbed one on a shared machine.

Full sizes (GPU): 256^3 scenes, 128^3 light grid, 1920x1080, 2560x1440 and 3840x2160, reference 1024:1024.
Quick sizes (CPU): 128^3 scenes, 64^3 light grid, the full sizes divided by 4, reference 512:512. The cube map
follows the density grid (S0 = 128 here), so the quick viewports keep the full run's ratio of screen pixels to cube
texels only roughly.
"""

from __future__ import annotations

from typing import Any

from volren.bench import Suite, bench_scene, measure, sized
from volren.camera import Camera, make_views
from volren.metrics import psnr, ssim
from volren.render import CMSRM, DSSRM, CMSRMConfig, DSSRMConfig, Reference, ReferenceConfig

FULL = {"scenes": ["smoke", "cloud", "phantom"], "resolution": 256, "light_grid": 128,
        "sizes": [(1920, 1080), (2560, 1440), (3840, 2160)], "repeats": 5, "reference": 1024}
QUICK = {"scenes": ["smoke", "cloud"], "resolution": 128, "light_grid": 64,
         "sizes": [(480, 270), (640, 360), (960, 540)], "repeats": 4, "reference": 512}
SETTINGS = [(360, 96), (100, 48)]
CAMERA = (0.0, 0.4, 3.2)


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    rows, ratios = [], []
    smallest = cfg["sizes"][0]
    for name in cfg["scenes"]:
        scene = bench_scene(name, cfg["resolution"])
        ref_cam = Camera(position=CAMERA, width=smallest[0], height=smallest[1])
        reference = Reference(ReferenceConfig(samples=cfg["reference"], light_samples=cfg["reference"]), device)
        left_ref = reference.render(scene, [make_views(ref_cam, "stereo")[0]]).images[0]
        times: dict[tuple[str, tuple[int, int]], float] = {}
        quality: dict[str, float] = {}
        for width, height in cfg["sizes"]:
            views = make_views(Camera(position=CAMERA, width=width, height=height), "stereo")
            for v, lsamp in SETTINGS:
                common = {"samples": v, "light_samples": lsamp, "light_grid": cfg["light_grid"]}
                for label, renderer in ((f"DSSRM:{v}:{lsamp}", DSSRM(DSSRMConfig(**common), device)),
                                        (f"CMSRM:{v}:{lsamp}", CMSRM(CMSRMConfig(**common), device))):
                    row = measure(renderer, scene, views, cfg["repeats"])
                    frame = row.pop("frame")
                    times[label, (width, height)] = row["frame_min_ms"]
                    info = frame.stats.info
                    row.update(scene=name, size=f"{width}x{height}", method=label,
                               cube_map_mib=info.get("cube_map_bytes", 0) / 2**20,
                               schemes="/".join(sorted({p["scheme"] for vw in info.get("volumes", []) for p in vw})),
                               march_ms=row.get("march_ms", 0.0) + row.get("cube_march_ms", 0.0))
                    if (width, height) == smallest:
                        row["psnr"] = psnr(left_ref, frame.images[0])
                        row["ssim"] = ssim(left_ref, frame.images[0])
                        quality[label] = row["psnr"]
                    rows.append(row)
        big = cfg["sizes"][-1]
        ratios.append({
            "scene": name,
            "cmsrm_largest_over_smallest": times["CMSRM:360:96", big] / times["CMSRM:360:96", smallest],
            "dssrm_over_cmsrm_largest": times["DSSRM:360:96", big] / times["CMSRM:360:96", big],
            "dssrm_over_cmsrm_largest_100_48": times["DSSRM:100:48", big] / times["CMSRM:100:48", big],
            "psnr_dssrm_minus_cmsrm": quality["DSSRM:360:96"] - quality["CMSRM:360:96"],
        })
    columns = [
        ("scene", "scene", "s"), ("size", "stereo view size", "s"), ("method", "method", "s"),
        ("frame_ms", "frame [ms]", ".1f"), ("frame_min_ms", "fastest frame [ms]", ".1f"),
        ("light_map_ms", "light map [ms]", ".1f"),
        ("march_ms", "march / cube march [ms]", ".1f"), ("resample_ms", "resample [ms]", ".1f"),
        ("density_samples", "density samples", ","), ("cube_map_mib", "cube maps [MiB]", ".2f"),
        ("schemes", "scheme", "s"), ("psnr", "PSNR [dB]", ".2f"), ("ssim", "SSIM", ".5f"),
    ]
    settings = {k: v for k, v in cfg.items() if k != "sizes"} | {
        "sizes": [f"{w}x{h}" for w, h in cfg["sizes"]], "views": "stereo", "camera": list(CAMERA),
        "goals": {"cmsrm_largest_over_smallest": "<= 1.35", "dssrm_over_cmsrm_largest": ">= 4",
                  "psnr_dssrm_minus_cmsrm": "<= 2"},
    }
    ratio_columns = [
        ("scene", "scene", "s"), ("cmsrm_largest_over_smallest", "CMSRM:360:96 largest/smallest (goal <= 1.35)", ".2f"),
        ("dssrm_over_cmsrm_largest", "DSSRM/CMSRM 360:96 at largest (goal >= 4)", ".2f"),
        ("dssrm_over_cmsrm_largest_100_48", "DSSRM/CMSRM 100:48 at largest", ".2f"),
        ("psnr_dssrm_minus_cmsrm", "PSNR DSSRM - CMSRM 360:96 [dB] (goal <= 2)", ".2f"),
    ]
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (ratios, ratio_columns)}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(sized(QUICK, FULL, quick), device)


SUITE = Suite("resolution", "DSSRM vs CMSRM over viewport sizes, with PSNR against the reference (paper 001 "
              "Table 1)", run, repeats=True, settable=True)

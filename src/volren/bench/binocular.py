"""Suite ``binocular``: paper 000 Fig. 7 and Table 1 for a stereo pair on a camera path.

Quality: on a path of stereo frames orbiting each scene, PSNR and SSIM of both eyes against the reference, averaged
over the path, for DSSRM:360:96, DSSRM:100:48, CMSRM:360:96, CMSRM:100:48 and CACRM (paper: 41.17, 34.87, 39.64,
34.21 and 39.72 dB), and CACRM +TLOD (tile LOD on). Speed: per stereo frame at three viewport sizes, the same methods
plus the ablation columns of Table 1: CACRM base (each eye alone, uniform steps), +VSA, +InS, +RCp (= CACRM); voxel
gathers (density samples minus those that reused the other eye's fetch) for each. On the orbit no quad interleaves
(texel rays are a voxel apart from the box entry on), so +InS = +VSA there; a close-up (both eyes inside the box)
measures InS: PSNR of CACRM with and without it against the same renderer at 2048 uniform steps, at equal gathers.
Equal gathers (issue 12): CACRM with VSA at base counts N = 32 and 64 against CACRM with uniform steps at the count
that matches its voxel gathers on every third frame of the path (two secant steps), both on the whole path against the
same reference. N is low on purpose: at 64^3 uniform steps reach the error floor of the light grid and the cube map
by N = 36 (smoke), 56 (cloud) and 96 (phantom) (96x64, six orbit frames: 50.6 -> 51.0, 45.4 -> 45.6, 40.2 dB at
N = 96), and on the floor no step rule can gain; the earlier budget N = 360 compared two floors.

The cube methods run with the hybrid choice off: it would march small views directly and compare DSSRM with itself.

Goals (issue 4): CACRM within 0.5 dB of CMSRM:360:96, at least 10% faster than it, with fewer voxel gathers than
CMSRM:100:48; coupling cuts the pair's gathers by at least 25% against two independent cube marches (+VSA vs +RCp).
Transl. mesh-vol. (Table 1's last rows, Fig. 9): the ``mesh_scene`` with two translucent sheets behind the box
against the same sheets opaque, per stereo frame at the speed sizes for DSSRM:360:96, CMSRM:360:96 and CACRM (paper:
the mesh k-buffers cost about 30% over an opaque mesh). Behind, so that the opaque sheets hide none of the volume and
the ratio is the k-buffers' cost: with the Fig. 9 sheets (one in front, one through the box) the opaque ones hid most
of the smoke (DSSRM:360:96 at 480x270, quick: 72,984 voxel gathers against 1,586,006 translucent) and the ratio,
2.5, measured the hidden volume. Fig. 9: PSNR/SSIM of CACRM and DSSRM:360:96 with the sheets in front of and through
the box at the quality size, frame 0 of the path, against the reference (exact for translucent layers) and against
DSSRM:360:96 (the paper's ground truth).
Full (GPU): 256^3 scenes, 128^3 light grid, 60 frames, quality at 480x270 against 1024:1024, speed at 1080p, 2K, 4K.
Quick (CPU): 64^3 scenes, 32^3 light grid, 12 frames, quality at 160x90 against 256:256, speed at a quarter of those.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from volren.bench import Suite, bench_scene, measure, sized
from volren.camera import Camera, make_views
from volren.metrics import psnr, ssim
from volren.render import (
    CACRM,
    CMSRM,
    DSSRM,
    CACRMConfig,
    CMSRMConfig,
    DSSRMConfig,
    Reference,
    ReferenceConfig,
    Renderer,
)
from volren.scene import Scene, TriangleMesh

FULL = {"scenes": ["smoke", "cloud", "phantom"], "resolution": 256, "light_grid": 128, "frames": 60,
        "quality_size": (480, 270), "reference": 1024, "sizes": [(1920, 1080), (2560, 1440), (3840, 2160)],
        "repeats": 5, "mesh_scene": "smoke"}
QUICK = {"scenes": ["smoke", "cloud", "phantom"], "resolution": 64, "light_grid": 32, "frames": 12,
         "quality_size": (160, 90), "reference": 256, "sizes": [(480, 270), (640, 360), (960, 540)], "repeats": 3,
         "mesh_scene": "smoke"}
RADIUS = 3.2


def path_camera(frame: int, frames: int, size: tuple[int, int]) -> Camera:
    """An orbit around the scene with a gently bobbing height: every side of the volume, near-constant distance."""
    theta = 2 * math.pi * frame / frames
    return Camera(position=(RADIUS * math.sin(theta), 0.4 + 0.3 * math.sin(2 * theta), RADIUS * math.cos(theta)),
                  width=size[0], height=size[1])


def methods(light_grid: int, device: str) -> dict[str, Renderer]:
    """The compared methods, ablation columns included, each with its own renderer (and history)."""
    def dssrm(v: int, lsamp: int) -> DSSRM:
        return DSSRM(DSSRMConfig(samples=v, light_samples=lsamp, light_grid=light_grid), device)

    def cmsrm(v: int, lsamp: int) -> CMSRM:
        return CMSRM(CMSRMConfig(samples=v, light_samples=lsamp, light_grid=light_grid, hybrid=False), device)

    def cacrm(**switches: bool) -> CACRM:
        return CACRM(CACRMConfig(samples=360, light_samples=96, light_grid=light_grid, hybrid=False, **switches),
                     device)

    return {
        "DSSRM:360:96": dssrm(360, 96), "DSSRM:100:48": dssrm(100, 48),
        "CMSRM:360:96": cmsrm(360, 96), "CMSRM:100:48": cmsrm(100, 48),
        "CACRM base": cacrm(coupling=False, vsa=False, interleave=False),
        "CACRM +VSA": cacrm(coupling=False, interleave=False), "CACRM +InS": cacrm(coupling=False),
        "CACRM": cacrm(), "CACRM +TLOD": cacrm(tile_lod=True),
    }


QUALITY_METHODS = ("DSSRM:360:96", "DSSRM:100:48", "CMSRM:360:96", "CMSRM:100:48", "CACRM", "CACRM +TLOD")


def gathers(counters: dict[str, int]) -> int:
    return counters["density_samples"] - counters["shared_samples"]


CLOSE_UP = (0.1, 0.0, 0.5)
"""[m] the close-up eye position: inside the box, where neighbouring texel rays run closest"""


def close_up(scene, cfg: dict[str, Any], device: str) -> list[dict[str, Any]]:
    """InS on and off at the close-up against dense stepping of the same renderer (isolates the depth sampling)."""
    views = make_views(Camera(position=CLOSE_UP, width=cfg["quality_size"][0], height=cfg["quality_size"][1]),
                       "stereo")
    base = {"light_samples": 96, "light_grid": cfg["light_grid"], "hybrid": False}
    dense = CACRM(CACRMConfig(samples=2048, vsa=False, interleave=False, **base), device).render(scene, views)
    rows = []
    for samples in (100, 360):
        for interleave in (False, True):
            frame = CACRM(CACRMConfig(samples=samples, interleave=interleave, **base), device).render(scene, views)
            c = frame.stats.counters
            rows.append({"table": "close-up", "method": f"CACRM:{samples}:96" + (" +InS" if interleave else " -InS"),
                         "psnr": sum(psnr(d, f) for d, f in zip(dense.images, frame.images, strict=True)) / 2,
                         "gathers": gathers(c), "interleaved": c["interleaved_samples"]})
    return rows


VSA_BUDGETS = (32, 64)
"""VSA base counts N of the equal-gathers comparison"""


def equal_gathers(scene, frames: list[list[Camera]], light_grid: int, device: str) -> dict[str, Renderer]:
    """Per VSA base count N: CACRM with VSA, and CACRM with uniform steps at the count whose voxel gathers summed over
    ``frames`` (stereo pairs) match (two secant steps on gathers ~ N)."""
    def cacrm(samples: int, vsa: bool) -> CACRM:
        # Adaptive LOD off: with it N is capped per view and gathers stop scaling with N (the match failed: phantom
        # VSA N = 64 528,669 gathers against uniform N = 244 1,904,857).
        return CACRM(CACRMConfig(samples=samples, light_samples=96, light_grid=light_grid, hybrid=False, vsa=vsa,
                                 adaptive_lod=False), device)

    def cost(r: Renderer) -> int:
        return sum(gathers(r.render(scene, views).stats.counters) for views in frames)

    out: dict[str, Renderer] = {}
    for n in VSA_BUDGETS:
        target = cost(cacrm(n, True))
        m = n
        for _ in range(2):
            m = max(2, round(m * target / cost(cacrm(m, False))))
        out[f"CACRM:{n} VSA"] = cacrm(n, True)
        out[f"CACRM:{m} uniform"] = cacrm(m, False)
    return out


MESH_METHODS = ("DSSRM:360:96", "CMSRM:360:96", "CACRM")
"""the methods timed with the translucent sheets (Table 1's "Transl. mesh-vol." rows, fewer columns to save time)"""


MESH_LAYOUTS = {"fig9": ((0.1, 0.45), (1.2, 0.6)), "behind": ((-1.2, 0.6), (-1.5, 2.0))}
"""(z, half-width) of the two sheets: through the middle of the box and in front of it (Fig. 9's mixing), or both
behind it (the timed rows)"""


def mesh_sheets(alpha: float, layout: str = "fig9") -> tuple[TriangleMesh, ...]:
    """Two square sheets facing +z at ``MESH_LAYOUTS[layout]``, opacity ``alpha``, tinted so that the layers' order
    shows in the colour."""
    def sheet(z: float, half: float, albedo: tuple[float, float, float], name: str) -> TriangleMesh:
        v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
        return TriangleMesh(v, np.array([[0, 1, 2], [0, 2, 3]]), albedo=albedo, name=name, alpha=alpha)

    (z0, h0), (z1, h1) = MESH_LAYOUTS[layout]
    return sheet(z0, h0, (0.2, 0.5, 0.9), "sheet 1"), sheet(z1, h1, (0.9, 0.6, 0.2), "sheet 2")


def translucent_mesh(scene: Scene, cfg: dict[str, Any], renderers: dict[str, Renderer], reference: Reference
                     ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Table 1's "Transl. mesh-vol." rows and Fig. 9's PSNR (module docstring), and the translucent / opaque time
    ratios at the largest size."""
    name = f"{scene.name} + sheets"

    def with_sheets(alpha: float, layout: str) -> Scene:
        return dataclasses.replace(scene, opaque=(*scene.opaque, *mesh_sheets(alpha, layout)))

    scenes = {alpha: with_sheets(alpha, "behind") for alpha in (1.0, 0.4)}
    rows = []
    times: dict[tuple[str, float], float] = {}
    for size in cfg["sizes"]:
        views = make_views(path_camera(0, cfg["frames"], size), "stereo")
        for m in MESH_METHODS:
            for alpha, s in scenes.items():
                row = measure(renderers[m], s, views, cfg["repeats"])
                layers = row.pop("frame").stats.info.get("mesh_layers", {})
                if size == cfg["sizes"][-1]:
                    times[m, alpha] = row["frame_min_ms"]
                rows.append({"table": "transl. mesh-vol.", "scene": name, "size": f"{size[0]}x{size[1]}",
                             "method": f"{m} {'opaque' if alpha == 1 else f'alpha {alpha:g}'}",
                             "frame_ms": row["frame_ms"], "frame_min_ms": row["frame_min_ms"], "gathers": gathers(row),
                             "layered": layers.get("pixels", 0)})
    views = make_views(path_camera(0, cfg["frames"], cfg["quality_size"]), "stereo")
    fig9 = with_sheets(0.4, "fig9")
    ref = reference.render(fig9, views).images
    images = {m: renderers[m].render(fig9, views).images for m in ("DSSRM:360:96", "CACRM")}
    for m, against in (("CACRM", "reference"), ("DSSRM:360:96", "reference"), ("CACRM", "DSSRM:360:96")):
        gt = ref if against == "reference" else images[against]
        rows.append({"table": "fig. 9", "scene": name, "method": f"{m} vs {against}",
                     "psnr": sum(psnr(a, b) for a, b in zip(gt, images[m], strict=True)) / 2,
                     "ssim": sum(ssim(a, b) for a, b in zip(gt, images[m], strict=True)) / 2})
    summary = {"scene": name, **{f"mesh_cost_{m}": times[m, 0.4] / times[m, 1.0] for m in MESH_METHODS}}
    return rows, summary


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    rows, summary = [], []
    for name in cfg["scenes"]:
        scene = bench_scene(name, cfg["resolution"])
        renderers = methods(cfg["light_grid"], device)
        reference = Reference(ReferenceConfig(samples=cfg["reference"], light_samples=cfg["reference"]), device)
        matched = equal_gathers(scene, [make_views(path_camera(f, cfg["frames"], cfg["quality_size"]), "stereo")
                                        for f in range(0, cfg["frames"], 3)], cfg["light_grid"], device)
        quality = {m: {"psnr": [], "ssim": [], "gathers": []} for m in (*QUALITY_METHODS, *matched)}
        for f in range(cfg["frames"]):
            views = make_views(path_camera(f, cfg["frames"], cfg["quality_size"]), "stereo")
            ref = reference.render(scene, views).images
            for m in quality:
                frame = (matched[m] if m in matched else renderers[m]).render(scene, views)
                quality[m]["psnr"] += [psnr(a, b) for a, b in zip(ref, frame.images, strict=True)]
                quality[m]["ssim"] += [ssim(a, b) for a, b in zip(ref, frame.images, strict=True)]
                quality[m]["gathers"].append(gathers(frame.stats.counters))
        for m, q in quality.items():
            rows.append({"table": "quality" if m in QUALITY_METHODS else "equal gathers", "scene": name, "method": m,
                         "psnr": sum(q["psnr"]) / len(q["psnr"]), "ssim": sum(q["ssim"]) / len(q["ssim"]),
                         "gathers": sum(q["gathers"]) // len(q["gathers"])})
        times: dict[tuple[str, tuple[int, int]], float] = {}
        fetches: dict[tuple[str, tuple[int, int]], int] = {}
        for size in cfg["sizes"]:
            views = make_views(path_camera(0, cfg["frames"], size), "stereo")
            for m, r in renderers.items():
                row = measure(r, scene, views, cfg["repeats"])
                row.pop("frame")
                times[m, size] = row["frame_min_ms"]
                fetches[m, size] = gathers(row)
                rows.append({"table": "speed", "scene": name, "size": f"{size[0]}x{size[1]}", "method": m,
                             "frame_ms": row["frame_ms"], "frame_min_ms": row["frame_min_ms"],
                             "gathers": fetches[m, size], "density_samples": row["density_samples"]})
        near = [{"scene": name, **r} for r in close_up(scene, cfg, device)]
        rows += near
        small, big = cfg["sizes"][0], cfg["sizes"][-1]
        q = {r["method"]: r["psnr"] for r in rows if r["table"] in ("quality", "equal gathers") and r["scene"] == name}
        pairs = list(zip(list(matched)[0::2], list(matched)[1::2], strict=True))
        summary.append({
            "scene": name,
            "psnr_cacrm_minus_cmsrm360": q["CACRM"] - q["CMSRM:360:96"],
            "speedup_over_cmsrm360_smallest": times["CMSRM:360:96", small] / times["CACRM", small],
            "speedup_over_cmsrm360_largest": times["CMSRM:360:96", big] / times["CACRM", big],
            "gathers_over_cmsrm100": fetches["CACRM", small] / fetches["CMSRM:100:48", small],
            "coupling_gather_cut": 1 - fetches["CACRM", small] / fetches["CACRM +InS", small],
            "ins_gain_db": near[1]["psnr"] - near[0]["psnr"],
            "tlod_psnr_db": q["CACRM +TLOD"] - q["CACRM"],
            "tlod_speedup_largest": times["CACRM", big] / times["CACRM +TLOD", big],
            **{f"vsa_gain_{n}_db": q[vsa] - q[uni] for n, (vsa, uni) in zip(VSA_BUDGETS, pairs, strict=True)},
        })
    if cfg.get("mesh_scene"):
        reference = Reference(ReferenceConfig(samples=cfg["reference"], light_samples=cfg["reference"]), device)
        mesh_rows, mesh_summary = translucent_mesh(bench_scene(cfg["mesh_scene"], cfg["resolution"]), cfg,
                                                   methods(cfg["light_grid"], device), reference)
        rows += mesh_rows
        summary.append(mesh_summary)
    columns = [
        ("table", "table", "s"), ("scene", "scene", "s"), ("size", "stereo view size", "s"), ("method", "method", "s"),
        ("psnr", "PSNR [dB]", ".2f"), ("ssim", "SSIM", ".5f"), ("frame_ms", "frame [ms]", ".1f"),
        ("frame_min_ms", "fastest frame [ms]", ".1f"), ("gathers", "voxel gathers", ","),
        ("interleaved", "interleaved samples", ","), ("layered", "pixels with mesh layers", ","),
    ]
    summary_columns = [
        ("scene", "scene", "s"), ("psnr_cacrm_minus_cmsrm360", "PSNR CACRM - CMSRM:360:96 [dB] (goal >= -0.5)", ".2f"),
        ("speedup_over_cmsrm360_smallest", "CMSRM:360:96 / CACRM time, smallest (goal >= 1.1)", ".2f"),
        ("speedup_over_cmsrm360_largest", "same, largest", ".2f"),
        ("gathers_over_cmsrm100", "CACRM / CMSRM:100:48 gathers (goal < 1)", ".2f"),
        ("coupling_gather_cut", "gathers cut by coupling (goal >= 0.25)", ".2f"),
        ("ins_gain_db", "InS gain at the close-up, N = 100 [dB]", ".2f"),
        ("tlod_psnr_db", "PSNR +TLOD - CACRM [dB]", ".2f"),
        ("tlod_speedup_largest", "CACRM / +TLOD time, largest", ".2f"),
        *[(f"vsa_gain_{n}_db", f"PSNR VSA - uniform at equal gathers, N = {n} [dB]", ".2f") for n in VSA_BUDGETS],
        *[(f"mesh_cost_{m}", f"{m}: translucent / opaque sheets time, largest (paper ~1.3)", ".2f")
          for m in MESH_METHODS],
    ]
    settings = {k: v for k, v in cfg.items() if k not in ("sizes", "quality_size")} | {
        "sizes": [f"{w}x{h}" for w, h in cfg["sizes"]], "quality_size": "x".join(map(str, cfg["quality_size"])),
        "path": f"orbit radius {RADIUS} m, height 0.4 +- 0.3 m, stereo ipd 0.063 m",
    }
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(sized(QUICK, FULL, quick), device)


SUITE = Suite("binocular", "DSSRM, CMSRM and CACRM (with ablations) on a stereo camera path: quality against the "
              "reference and time per stereo frame (paper 000 Fig. 7, Table 1)", run, repeats=True, settable=True)

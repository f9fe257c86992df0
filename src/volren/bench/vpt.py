"""Suite ``vpt``: paper 002 Fig. 9 (frame time and samples per second against spp), the acceleration structure
(macrocell octree against one global majorant: time, tentative collisions, build time, memory) and Fig. 3 (the
surface-medium coexistence model's per-pixel variance against Exposure Render's at equal spp and equal mean).

Scenes: the phantom with the CT muscle/skin transfer function, the phantom with the bone preset (CT-like, mostly
empty: where skipping pays), and the smoke plume with extinction proportional to density.
Denoisers (phantom, ct-muscle; none, ours, SVGF, WRLS): (b) PSNR and FLIP against a high-spp reference on every
``score_every``-th frame along a rotation with a rotating light (Fig. 12; the paper's LPIPS needs network weights
that cannot be fetched offline, so FLIP stands in as the perceptual metric), the detail kept (`detail_kept`), the
holes filled (pixels none of whose paths hit although the reference's alpha is >= 0.25, filled when the output's
alpha reaches half the reference's) and their mean absolute RGB error against the reference; (c) §6.4.3's variance
test: frame ``variance_at`` rendered with ``variance_sequences`` random sequences on the same history, the summed
per-pixel variance of the outputs; (d) §6.4.4's convergence: after an orbit stops, the frames until the RMSE between
consecutive frames falls below 0.01; (e) ghosting: the mean PSNR of the 3 frames right after the transfer function
switches from ct-muscle to ct-bone.
Full (GPU): 256^3, 1440x1190 (the paper's viewport), spp 1-32. Quick (CPU): 64^3, 128x106, spp 1-8.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from volren.bench import Suite, bench_scene, measure, sized
from volren.camera import Camera
from volren.data import BUILTIN_SCENES
from volren.errors import VolrenError
from volren.progress import case_done
from volren.render import VPT, VPTConfig
from volren.transfer import PRESETS

CASES = [["phantom", "ct-muscle"], ["phantom", "ct-bone"], ["smoke", None]]
FULL = {"cases": CASES, "denoiser_table": True, "score_every": 1, "resolution": 256, "size": (1440, 1190),
        "spp": [1, 2, 4, 8, 16, 32], "variance_frames": 32, "variance_spp": 4, "repeats": 3, "denoise_size": (480, 396),
        "denoise_spp": 8, "rotation_frames": 60, "reference_spp": 1024, "variance_at": 30, "variance_sequences": 50,
        "orbit_frames": 10, "settle_frames": 60}
QUICK = {"cases": CASES, "denoiser_table": True, "score_every": 1, "resolution": 64, "size": (128, 106),
         "spp": [1, 2, 4, 8], "variance_frames": 16, "variance_spp": 2, "repeats": 2, "denoise_size": (96, 80),
         "denoise_spp": 4, "rotation_frames": 12, "reference_spp": 256, "variance_at": 8, "variance_sequences": 8,
         "orbit_frames": 6, "settle_frames": 30}
"""``cases``: [scene, transfer preset or null] per row group of tables (a)-(c); ``denoiser_table``: table (d), the
phantom's denoisers, scored against a reference every ``score_every``-th frame of the orbit from the first. Settable
(`--set`), so that a full-size CPU run can be split across cores and its references cut to a subset of frames."""
DENOISERS = ("none", "ours", "svgf", "wrls")
HOLE_ALPHA = 0.25
"""a pixel without hits counts as a hole where the reference's alpha is at least this"""


def cases_of(cfg: dict[str, Any]) -> list[tuple[str, str | None]]:
    """The configuration's cases, each checked to name a built-in scene and a transfer function (or null)."""
    cases = []
    for case in cfg["cases"]:
        if (not isinstance(case, (list, tuple)) or len(case) != 2 or case[0] not in BUILTIN_SCENES
                or (case[1] is not None and case[1] not in PRESETS)):
            raise VolrenError(f"--set cases: {json.dumps(case)} is not [scene, transfer or null] with a built-in "
                              f"scene ({', '.join(BUILTIN_SCENES)}) and a preset ({', '.join(PRESETS)})")
        cases.append((case[0], case[1]))
    return cases


def case_name(scene: str, transfer: str | None) -> str:
    return f"{scene} ({transfer or 'density'})"


def detail_kept(reference: np.ndarray, image: np.ndarray) -> float:
    """The share of the reference's finest detail the image keeps: the regression slope of the image's 0-1 px band
    (luminance minus its Gaussian blur of sigma 1 px) on the reference's. Noise uncorrelated with the reference
    leaves it unbiased (the raw frames score ~1); blur lowers it."""
    from scipy import ndimage

    def band(x: np.ndarray) -> np.ndarray:
        lum = x[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
        return lum - ndimage.gaussian_filter(lum, 1.0)

    b = band(reference)
    return float((band(image) * b).sum() / max((b * b).sum(), 1e-30))


def denoiser_rows(cfg: dict[str, Any], device: str) -> tuple[list[dict], dict[str, dict]]:
    """Rows (b)-(d) for each denoiser, and per denoiser its mean PSNR, variance and convergence frames."""
    import dataclasses

    from volren.animate import Sequence, frame_scene, frame_views
    from volren.metrics import flip, psnr

    scene = bench_scene("phantom", cfg["resolution"])
    cam = Camera(position=(1.6, 1.2, 2.4), width=cfg["denoise_size"][0], height=cfg["denoise_size"][1], fov_y=40.0)
    seq = Sequence(frames=cfg["rotation_frames"], orbit=90.0, light_orbit=180.0)
    reference = VPT(VPTConfig(spp=cfg["reference_spp"], transfer="ct-muscle"), device)
    every = cfg["score_every"]
    # Every frame is rendered (the denoisers see the paper's motion per frame); every `every`-th, from the first, is
    # scored against its reference: the references are the cost at full size (1024 spp each).
    refs = {i: reference.render(frame_scene(seq, scene, i), frame_views(seq, [cam], i), i).images[0]
            for i in range(0, seq.frames, every)}
    switched_ref = VPT(VPTConfig(spp=cfg["reference_spp"], transfer="ct-bone"), device).render(scene, [cam]).images[0]
    case_done(f"{len(refs) + 1} reference frame(s) at {cfg['reference_spp']} spp, {cam.width}x{cam.height}")
    rows, result, raw_alpha = [], {}, {}
    for name in DENOISERS:
        config = VPTConfig(spp=cfg["denoise_spp"], transfer="ct-muscle", denoise=name)
        r = VPT(config, device)
        images = {}
        for i in range(seq.frames):
            image = r.render(frame_scene(seq, scene, i), frame_views(seq, [cam], i), i).images[0]
            if i in refs:
                images[i] = image
        scores = [psnr(refs[i], images[i]) for i in refs]
        flips = [flip(refs[i], images[i]) for i in refs]
        kept = [detail_kept(refs[i], images[i]) for i in refs]
        if name == "none":  # the same seeds: these frames' alphas are every denoiser's raw input
            raw_alpha = {i: image[..., 3] for i, image in images.items()}
        holes = {i: (raw_alpha[i] == 0) & (refs[i][..., 3] >= HOLE_ALPHA) for i in refs}
        filled = sum(int((images[i][..., 3][holes[i]] >= 0.5 * refs[i][..., 3][holes[i]]).sum()) for i in refs)
        hole_error = float(np.mean(np.concatenate([np.abs(images[i][..., :3] - refs[i][..., :3])[holes[i]].ravel()
                                                    for i in refs])))
        # (c): the same history, different random sequences for one more frame.
        r = VPT(config, device)
        for i in range(cfg["variance_at"]):
            r.render(scene, [cam], i)
        saved = dict(r._denoiser.history) if name != "none" else {}
        outputs = []
        for k in range(cfg["variance_sequences"]):
            r.config = dataclasses.replace(config, seed=1000 + k)
            if saved:
                r._denoiser.history = dict(saved)
            outputs.append(r.render(scene, [cam], cfg["variance_at"]).images[0][..., :3])
        variance = float(np.stack(outputs).var(axis=0, ddof=1).sum())
        # (d): orbit, stop, count frames until consecutive frames differ by RMSE < 0.01.
        r = VPT(config, device)
        orbit = Sequence(frames=cfg["orbit_frames"], orbit=30.0)
        for i in range(orbit.frames):
            last = r.render(scene, frame_views(orbit, [cam], i), i).images[0]
        still = frame_views(orbit, [cam], orbit.frames - 1)
        settle = cfg["settle_frames"]
        for k in range(1, cfg["settle_frames"] + 1):
            image = r.render(scene, still, orbit.frames + k).images[0]
            if float(np.sqrt(np.mean((image - last) ** 2))) < 0.01:
                settle = k
                break
            last = image
        # Ghosting after a transfer-function switch: PSNR of the frames right after it against the new reference.
        r = VPT(config, device)
        for i in range(cfg["variance_at"]):
            r.render(scene, [cam], i)
        r.config = dataclasses.replace(config, transfer="ct-bone")
        after = [psnr(switched_ref, r.render(scene, [cam], cfg["variance_at"] + k).images[0]) for k in range(3)]
        case_done(f"denoiser {name}, {seq.frames} orbit frames at {cfg['denoise_spp']} spp and its history tests")
        result[name] = {"psnr": float(np.mean(scores)), "flip": float(np.mean(flips)), "variance": variance,
                        "settle": settle, "switch": float(np.mean(after))}
        rows.append({"table": "denoiser", "scene": "phantom (ct-muscle)", "spp": cfg["denoise_spp"], "method": name,
                     "psnr": float(np.mean(scores)), "psnr_min": float(np.min(scores)), "flip": float(np.mean(flips)),
                     "detail_kept": float(np.mean(kept)), "holes": sum(int(h.sum()) for h in holes.values()),
                     "holes_filled": filled, "hole_error": hole_error,
                     "output_variance": variance, "settle_frames": settle, "switch_psnr": result[name]["switch"]})
    return rows, result


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    cases = cases_of(cfg)
    if not isinstance(cfg["denoiser_table"], bool):
        raise VolrenError(f"--set denoiser_table: true or false, got {json.dumps(cfg['denoiser_table'])}")
    if not cases and not cfg["denoiser_table"]:
        raise VolrenError("--set cases=[] with denoiser_table=false leaves bench vpt nothing to measure")
    every = cfg["score_every"]
    if not isinstance(every, int) or isinstance(every, bool) or every < 1:
        raise VolrenError(f"--set score_every: a whole number of frames >= 1, got {json.dumps(every)}")
    rows, summary = [], []
    cam = Camera(position=(1.6, 1.2, 2.4), width=cfg["size"][0], height=cfg["size"][1], fov_y=40.0)
    for scene_name, transfer in cases:
        scene = bench_scene(scene_name, cfg["resolution"])
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
            case_done(f"{shading} shading, {cfg['variance_frames']} frames at {cfg['variance_spp']} spp")
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
    if cfg["denoiser_table"]:
        denoise_rows, denoisers = denoiser_rows(cfg, device)
        rows += denoise_rows
        summary.append({"scene": "phantom (ct-muscle), denoisers",
                        "psnr_ours_minus_svgf": denoisers["ours"]["psnr"] - denoisers["svgf"]["psnr"],
                        "psnr_ours_minus_wrls": denoisers["ours"]["psnr"] - denoisers["wrls"]["psnr"],
                        "flip_ours_minus_best_baseline": denoisers["ours"]["flip"] - min(
                            denoisers["svgf"]["flip"], denoisers["wrls"]["flip"]),
                        "psnr_ours_minus_raw": denoisers["ours"]["psnr"] - denoisers["none"]["psnr"],
                        "variance_ours_over_svgf": denoisers["ours"]["variance"] / denoisers["svgf"]["variance"],
                        "settle_ours": denoisers["ours"]["settle"], "settle_svgf": denoisers["svgf"]["settle"],
                        "switch_ours_minus_raw": denoisers["ours"]["switch"] - denoisers["none"]["switch"]})
    columns = [
        ("table", "table", "s"), ("scene", "scene", "s"), ("spp", "spp", "d"), ("method", "shading / denoiser", "s"),
        ("frame_ms", "frame [ms]", ".1f"), ("paths_per_s", "paths/s", ",.0f"),
        ("density_lookups", "density lookups", ","), ("light_lookups", "transmittance lookups", ","),
        ("majorant_bytes", "majorant bytes", ","), ("majorant_build_ms", "majorant build [ms]", ".1f"),
        ("image_mean", "image mean", ".5f"), ("pixel_variance_sum", "summed pixel variance", ".4f"),
        ("psnr", "mean PSNR [dB]", ".2f"), ("psnr_min", "min PSNR [dB]", ".2f"), ("flip", "mean FLIP", ".4f"),
        ("detail_kept", "detail kept (0-1 px band)", ".3f"), ("holes", "holes", "d"),
        ("holes_filled", "holes filled", "d"), ("hole_error", "hole RGB error", ".4f"),
        ("output_variance", "output variance", ".4f"), ("settle_frames", "frames to settle", "d"),
        ("switch_psnr", "PSNR after a TF switch [dB]", ".2f"),
    ]
    summary_columns = [
        ("scene", "scene", "s"), ("variance_ratio", "variance coexist / ER (goal < 1)", ".3f"),
        ("mean_ratio", "mean coexist / ER (goal 1)", ".4f"),
        ("octree_speedup", "time global majorant / octree", ".2f"),
        ("lookup_ratio", "lookups octree / global", ".3f"),
        ("psnr_ours_minus_svgf", "PSNR ours - SVGF [dB] (goal > 0)", ".2f"),
        ("psnr_ours_minus_wrls", "PSNR ours - WRLS [dB] (goal > 0)", ".2f"),
        ("flip_ours_minus_best_baseline", "FLIP ours - best baseline (goal < 0)", ".4f"),
        ("psnr_ours_minus_raw", "PSNR ours - raw [dB]", ".2f"),
        ("variance_ours_over_svgf", "output variance ours / SVGF (goal < 1)", ".3f"),
        ("settle_ours", "frames to settle, ours (goal < SVGF)", "d"), ("settle_svgf", "same, SVGF", "d"),
        ("switch_ours_minus_raw", "PSNR after a TF switch, ours - raw [dB] (no ghosting: > 0)", ".2f"),
    ]
    settings = {k: v for k, v in cfg.items() if k not in ("size", "denoise_size")} | {
                "size": "x".join(map(str, cfg["size"])), "denoise_size": "x".join(map(str, cfg["denoise_size"])),
                                                                 "cases": [case_name(*c) for c in cases]}
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(sized(QUICK, FULL, quick), device)


SUITE = Suite("vpt", "volumetric path tracing: time and paths/s against spp, macrocell octree vs global majorant, "
              "coexistence vs Exposure Render variance (paper 002 Fig. 3, 9)", run, repeats=True, settable=True)

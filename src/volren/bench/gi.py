"""Suite ``gi``: ambient GI quality and time (paper 000 Fig. 10-11, Table 2) for M, PRT, strict ReSTIR and ours.

Per scene (built-ins with the procedural sky, whose directional light makes GI visible) and method, a sequence of
frames is rendered by DSSRM with that GI; each measured frame is compared with the same frame shaded from the
brute-force ground-truth grid (``gt_rays`` uniform rays per voxel integrated against the sky, no SH). Reported:
the GI passes' time per frame (median; PRT's one-off precomputation separately, recomputed every frame when the
density moves), the work counters (GI rays, light samples), and PSNR/SSIM of the image averaged over the frames
after the warm-up, plus the relative RMS error of the ambient grid itself. The animated smoke (per-voxel advection,
`volren.simulate`) runs at fixed 60 and 30 fps time steps (Fig. 11's V60/V30) and reports the frame after which
the ambient error stays within 25% of its final level ("settles"). On the cloud and the smoke, Eq. 12's study
(``resampling`` in the JSON) runs ours with each resampling -- as printed, own directions, RIS -- and reports the
image and ambient-grid PSNR after 1, 8 and 32 frames and the first frame's largest ambient in a constant
environment of radiance 1.

``--set gt_rays=0`` times the methods without the ground truth (no PSNR, SSIM, ambient error, settling frame or
Eq. 12 study): the paper's Table 2 at its sizes on a machine where brute force is out of reach (a 128^3 x 2048-ray
grid takes hours on a CPU); ``--set 'methods=[...]'`` runs some of M, PRT, strict ReSTIR and ours (PRT's
precomputation is 1024 rays a voxel). The summary's ratios need the methods they compare.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Iterable
from typing import Any

import numpy as np

from volren.bench import Suite, bench_scene, sized
from volren.camera import Camera
from volren.data.environments import sky_environment
from volren.errors import VolrenError
from volren.metrics import psnr, ssim
from volren.progress import case_done
from volren.render import DSSRM, DSSRMConfig
from volren.render.gi.ambient import RESAMPLING as RESAMPLING_MODES
from volren.render.gi.ambient import GIConfig
from volren.scene import Environment, Scene
from volren.simulate import advected_frames

METHODS = ("major", "prt", "restir", "sresir")
RESAMPLING = {"scenes": ["cloud", "smoke"], "frames": [1, 8, 32], "seeds": 3}
"""Eq. 12's study (a config's ``resampling``; none: skipped): ours with each ``GIConfig.resampling`` after 1, 8 and
32 frames, mean of 3 seeds"""
FULL = {"scenes": ["smoke", "cloud", "phantom", "multi"],
        "resolution": 256, "light_grid": 128, "size": (1280, 720), "frames": 60, "warmup": 30, "gt_rays": 2048,
        "prt_rays": 1024, "dynamic_frames": 60, "gt_every": 10, "resampling": RESAMPLING,
        "methods": list(METHODS)}
QUICK = {"scenes": ["smoke", "cloud", "phantom", "multi"],
         "resolution": 64, "light_grid": 32, "size": (96, 64), "frames": 40, "warmup": 24, "gt_rays": 1024,
         "prt_rays": 256, "dynamic_frames": 36, "gt_every": 4, "resampling": RESAMPLING,
         "methods": list(METHODS)}
LIGHT_SAMPLES = 96
SETTLE = 1.25


def gi_scene(name: str, resolution: int) -> Scene:
    scene = bench_scene(name, resolution, count=4)
    return dataclasses.replace(scene, environment=sky_environment())


def gi_time(frame) -> float:
    return sum(v for k, v in frame.stats.times_ms.items() if k.startswith("gi_"))


def run_sequence(scenes: Iterable[Scene], gi: GIConfig, cfg: dict[str, Any], device: str, camera: Camera,
                 measured: set[int] | None = None, seed: int = 0) -> list[dict[str, Any]]:
    """Render each scene of a sequence with one renderer (its GI history carries over); per frame the image (on the
    ``measured`` frames, all if None), the ambient grid of volume 0, GI times and counters."""
    r = DSSRM(DSSRMConfig(light_grid=cfg["light_grid"], light_samples=LIGHT_SAMPLES, gi=gi, seed=seed),
              device=device)
    out = []
    for i, scene in enumerate(scenes):
        frame = r.render(scene, [camera], frame=i)
        keep = measured is None or i in measured
        out.append({
            "image": frame.images[0] if keep else None,
            "ambient": r.gi_state.ambient_grid(0) if keep else None,
            "gi_ms": gi_time(frame),
            "precompute_ms": frame.stats.times_ms.get("gi_precompute", 0.0),
            "light_samples": frame.stats.counters["light_samples"],
            "rays": frame.stats.counters["rays"],
        })
    case_done(f"{gi.method} GI, {len(out)} frame(s) of {camera.width}x{camera.height}")
    return out


def relative_rmse(test: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean((test - truth) ** 2)) / max(float(truth.mean()), 1e-12))


def score(run: list[dict[str, Any]], truth: dict[int, dict[str, Any]]) -> dict[str, list[float]]:
    frames = sorted(truth)
    return {
        "psnr": [psnr(truth[i]["image"], run[i]["image"]) for i in frames],
        "ssim": [ssim(truth[i]["image"], run[i]["image"]) for i in frames],
        "ambient_rel_rmse": [relative_rmse(run[i]["ambient"], truth[i]["ambient"]) for i in frames],
    }


def ground_truth(scenes: list[Scene], frames: list[int], cfg: dict[str, Any], device: str,
                 camera: Camera) -> dict[int, dict[str, Any]]:
    """Brute-force grids and images of the given frames (each computed afresh: one precomputation per scene). The
    grids hold the field at the voxel centres (``projection`` off), what the compared estimators estimate, so the
    scores measure the estimators, not the trilinear lookup's bias that the projection removes from brute force."""
    gi = GIConfig(method="brute", rays=cfg["gt_rays"], projection=False)
    return {i: run_sequence([scenes[i]], gi, cfg, device, camera)[0] for i in frames}


def method_row(name: str, method: str, seq: list[dict[str, Any]], scores: dict[str, list[float]] | None,
               cfg: dict[str, Any], **extra: Any) -> dict[str, Any]:
    """One method's row: GI time per frame (median), work counters and, with ``scores`` (None: no ground truth),
    its quality averaged over the scored frames."""
    steady = seq[1:] if method == "prt" and not extra.get("dynamic") else seq
    quality = ({k: float(np.mean(v)) for k, v in scores.items()} if scores is not None
               else dict.fromkeys(("psnr", "ssim", "ambient_rel_rmse")))
    return {
        "scene": name, "method": method, **extra,
        "gi_ms": statistics.median(s["gi_ms"] for s in steady),
        "precompute_ms": max(s["precompute_ms"] for s in seq) if method == "prt" else None,
        "gi_rays": seq[-1]["rays"],
        "light_samples": seq[-1]["light_samples"],
        **quality,
    }


def settle_frame(errors: list[float], frames: list[int]) -> int | None:
    """The first measured frame from which the error stays within SETTLE times its final level."""
    level = SETTLE * float(np.mean(errors[-2:]))
    for k, f in enumerate(frames):
        if all(e <= level for e in errors[k:]):
            return f
    return None


def ambient_psnr(test: np.ndarray, truth: np.ndarray) -> float:
    """PSNR of an ambient grid, peak = the ground truth's maximum."""
    return float(10 * np.log10(float(truth.max()) ** 2 / max(float(np.mean((test - truth) ** 2)), 1e-30)))


def resampling_rows(name: str, scene: Scene, truth: dict[str, Any], cfg: dict[str, Any], device: str,
                    camera: Camera) -> list[dict[str, Any]]:
    """Ours with Eq. 12 as printed, own directions and RIS: image and ambient-grid PSNR against brute force after
    1/8/32 frames (mean over seeds), and the first frame's largest ambient in a constant environment of radiance 1
    (the truth is the mean transmittance, <= 1)."""
    study = cfg["resampling"]
    frames = study["frames"]
    white = dataclasses.replace(scene, environment=Environment(1.0))
    rows = []
    for mode in RESAMPLING_MODES:
        gi = GIConfig(method="sresir", resampling=mode)
        image, grid = [], []
        for seed in range(study["seeds"]):
            seq = run_sequence([scene] * frames[-1], gi, cfg, device, camera, {f - 1 for f in frames}, seed)
            image.append([psnr(truth["image"], seq[f - 1]["image"]) for f in frames])
            grid.append([ambient_psnr(seq[f - 1]["ambient"], truth["ambient"]) for f in frames])
        first = max(float(run_sequence([white], gi, cfg, device, camera, None, seed)[0]["ambient"].max())
                    for seed in range(study["seeds"]))
        row = {"scene": name, "resampling": mode, "max_first_frame": first}
        for k, f in enumerate(frames):
            row[f"image_psnr_{f}"] = float(np.mean([s[k] for s in image]))
            row[f"ambient_psnr_{f}"] = float(np.mean([s[k] for s in grid]))
        rows.append(row)
    return rows


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(sized(QUICK, FULL, quick), device)


def checked_methods(cfg: dict[str, Any]) -> list[str]:
    """The configuration's GI methods (all four unless ``methods`` names some), refused unless known and distinct."""
    methods = list(cfg.get("methods", METHODS))
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown or len(set(methods)) != len(methods):
        raise VolrenError(f"--set methods: {methods!r} is not a list of distinct methods of {', '.join(METHODS)}")
    return methods


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    methods = checked_methods(cfg)
    if cfg["gt_rays"] < 0:
        raise VolrenError(f"--set gt_rays: {cfg['gt_rays']} rays; give 0 (no ground truth) or more")
    truthful = cfg["gt_rays"] > 0
    w, h = cfg["size"]
    camera = Camera(position=(0.0, 0.4, 3.2), width=w, height=h)
    rows = []
    resampling: list[dict[str, Any]] = []
    measured = list(range(cfg["warmup"], cfg["frames"]))
    kept = set(measured) if truthful else set()
    for name in cfg["scenes"]:
        scene = gi_scene(name, cfg["resolution"])
        truth_frame = ground_truth([scene], [0], cfg, device, camera)[0] if truthful else None
        for method in methods:
            gi = GIConfig(method=method, rays=cfg["prt_rays"])
            seq = run_sequence([scene] * cfg["frames"], gi, cfg, device, camera, kept)
            scores = score(seq, dict.fromkeys(measured, truth_frame)) if truthful else None
            rows.append(method_row(name, method, seq, scores, cfg))
        if truthful and name in cfg.get("resampling", {}).get("scenes", ()):
            resampling += resampling_rows(name, scene, truth_frame, cfg, device, camera)
    for fps in (60, 30):
        scenes = list(advected_frames(gi_scene("smoke", cfg["resolution"]), cfg["dynamic_frames"], fps,
                                      device=device))
        frames = list(range(0, cfg["dynamic_frames"], cfg["gt_every"]))
        truth = ground_truth(scenes, frames, cfg, device, camera) if truthful else None
        for method in methods:
            gi = GIConfig(method=method, rays=cfg["prt_rays"])
            seq = run_sequence(scenes, gi, cfg, device, camera, set(frames) if truthful else set())
            scores = score(seq, truth) if truth is not None else None
            # the quality row averages the second half's frames; `score` lists them in frame order
            late_from = sum(f < cfg["dynamic_frames"] // 2 for f in frames)
            late = {k: v[late_from:] for k, v in scores.items()} if scores is not None else None
            row = method_row(f"smoke advected {fps} fps", method, seq, late, cfg, dynamic=True)
            row["settle_frame"] = settle_frame(scores["ambient_rel_rmse"], frames) if scores is not None else None
            rows.append(row)
    summary = []
    for name in sorted({r["scene"] for r in rows}, key=[r["scene"] for r in rows].index):
        by = {r["method"]: r for r in rows if r["scene"] == name}
        ours = by.get("sresir")
        if ours is None:
            continue
        restir, major = by.get("restir"), by.get("major")
        summary.append({
            "scene": name,
            "time_vs_restir": ours["gi_ms"] / restir["gi_ms"] if restir else None,
            "db_vs_restir": ours["psnr"] - restir["psnr"] if restir and truthful else None,
            "db_vs_major": ours["psnr"] - major["psnr"] if major and truthful else None,
            "settle_frame": ours.get("settle_frame"),
        })
    return {
        "settings": {**cfg, "light_samples": LIGHT_SAMPLES, "environment": "sky", "view": "mono 'left' camera",
                     "renderer": "dssrm", "settle": SETTLE},
        "rows": rows,
        "resampling": resampling,
        "columns": [("scene", "scene", ""), ("method", "GI", ""), ("gi_ms", "GI ms/frame", ".2f"),
                    ("precompute_ms", "PRT precompute ms", ".1f"), ("gi_rays", "GI rays", ","),
                    ("light_samples", "light samples", ","), ("psnr", "PSNR dB", ".2f"), ("ssim", "SSIM", ".4f"),
                    ("ambient_rel_rmse", "ambient rel. RMSE", ".3f"), ("settle_frame", "settles at frame", "")],
        "summary": (summary, [("scene", "scene", ""), ("time_vs_restir", "ours / ReSTIR time (goal <= 0.6)", ".2f"),
                              ("db_vs_restir", "ours - ReSTIR dB (goal >= -1.5)", "+.2f"),
                              ("db_vs_major", "ours - M dB (goal >= 8)", "+.2f"),
                              ("settle_frame", "settles at frame (goal <= 30)", "")]),
    }


SUITE = Suite("gi", "ambient GI: M, PRT, strict ReSTIR and ours against brute force (paper 000 Fig. 10-11, "
              "Table 2)", run, settable=True)

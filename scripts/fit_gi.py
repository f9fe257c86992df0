"""Fit Eq. 10's history weights (paper 000 §3.2.1) against brute-force ground truth, as the paper's "simple training".

For each candidate (w_dst, w_clamped, w_poly = 0) and k_gamma, ours (sresir) runs over a static smoke and the smoke
advected at 60 fps; the score is the relative RMS error of the ambient grid against a brute-force grid, averaged
over the frames after a short warm-up (static) and over every measured frame (dynamic: tracking matters). The
cubic term (w_poly, a, b, c) is left at 0: with the coarse mean alone it cannot tell the scenes' ambient levels
apart, so it fits the training scenes' average rather than the voxel. Writes ``docs/bench/gi-fit.json``.

    .venv/bin/python scripts/fit_gi.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from volren.bench import machine_info
from volren.bench.gi import gi_scene, ground_truth, relative_rmse, run_sequence
from volren.camera import Camera
from volren.render.gi import GIConfig
from volren.simulate import advected_frames

WEIGHTS = [(0.125, 0.875), (0.25, 0.75), (0.5, 0.5), (0.75, 0.25), (1.0, 0.0)]
K_GAMMA = [0.125, 0.25, 0.5, 1.0, 2.0]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="16^3 lighting grid, fewer frames")
    p.add_argument("--out", type=Path, default=Path("docs/bench/gi-fit.json"))
    args = p.parse_args(argv)
    cfg = {"resolution": 64, "light_grid": 16 if args.quick else 32, "gt_rays": 512, "frames": 32 if args.quick else 48,
           "warmup": 8}
    camera = Camera(position=(0.0, 0.4, 3.2), width=8, height=8)
    static = [gi_scene("smoke", cfg["resolution"])] * cfg["frames"]
    moving = list(advected_frames(gi_scene("smoke", cfg["resolution"]), cfg["frames"], 60.0))
    static_frames = list(range(cfg["warmup"], cfg["frames"], 4))
    moving_frames = list(range(0, cfg["frames"], 4))
    static_truth = ground_truth(static, [0], cfg, "cpu", camera)[0]
    moving_truth = ground_truth(moving, moving_frames, cfg, "cpu", camera)
    results = []
    for w_dst, w_clamped in WEIGHTS:
        for k_gamma in K_GAMMA if w_clamped > 0 else [0.5]:
            gi = GIConfig(method="sresir", w_dst=w_dst, w_clamped=w_clamped, k_gamma=k_gamma)
            s = run_sequence(static, gi, cfg, "cpu", camera, set(static_frames))
            m = run_sequence(moving, gi, cfg, "cpu", camera, set(moving_frames))
            e_static = float(np.mean([relative_rmse(s[i]["ambient"], static_truth["ambient"]) for i in static_frames]))
            e_moving = float(np.mean([relative_rmse(m[i]["ambient"], moving_truth[i]["ambient"])
                                      for i in moving_frames]))
            results.append({"w_dst": w_dst, "w_clamped": w_clamped, "k_gamma": k_gamma, "static": e_static,
                            "advected_60fps": e_moving, "score": 0.5 * (e_static + e_moving)})
            print(f"w_dst {w_dst:.3f} w_clamped {w_clamped:.3f} k_gamma {k_gamma:.1f}: static {e_static:.4f} "
                  f"advected {e_moving:.4f}", file=sys.stderr)
    best = min(results, key=lambda r: r["score"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine_info("cpu"), "settings": cfg, "results": results,
                                    "best": best}, indent=2) + "\n")
    print(json.dumps(best))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Fit the VSA constants of paper 000 Eq. 4-6 (k_a, k_b, f_lambda_max, w_lambda, w_T, w_A) against the reference.

Objective: image quality at equal cost. For each candidate, CACRM with VSA at base count N renders each scene; its
PSNR against the reference is compared with uniform stepping at the same voxel gathers (uniform CACRM at
N = 12, 16, ..., N + 8, PSNR interpolated in log gathers). The fit keeps the candidate whose worst scene gains most
(ties: the mean). All three factors of Eq. 4 take part (weights > 0): a weight of 0 drops its factor. The paper's
k_a = 3 and f_lambda_max = 2 are in the grid but not imposed.

N is low (64) on purpose: at 360 steps every method sits on the same error floor (light grid, cube-map breadth
interpolation; measured: uniform 100 vs 180 steps differ by < 0.05 dB), and no step rule can show there.
Two frames are noisy: uniform PSNR is not monotone in N (it drops by up to 1.6 dB from one count to the next, as
the texel-anchored lattice moves with N), so single gains below ~0.5 dB are noise. Checked on six frames (0, 2, ...,
10) at N = 24 and 40 over 42 points (k_a 0, 1.5, 3; k_b 0.01, 0.05; f_lambda_max 2, 4; w_T 1, 4; w_A 0.1, 0.25, 1):
the same weights scored best (worst scene -0.02, mean +0.36 dB); k_a = 2 and k_b = 0.2 did not do better.

    python scripts/fit_vsa.py                                   # writes out/vsa_fit.json (a few minutes, 2 cores)
    python scripts/fit_vsa.py --out src/volren/render/marching/vsa_fit.json   # adopt the fit as CACRMConfig's defaults
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from volren.bench.binocular import path_camera
from volren.camera import make_views
from volren.data import builtin_scene
from volren.metrics import psnr
from volren.render import CACRM, CACRMConfig, Reference, ReferenceConfig

SCENES = ("smoke", "cloud", "phantom")
GRID = {"k_a": (1.5, 3.0), "k_b": (0.01, 0.05), "f_lambda_max": (2.0, 3.0, 4.0), "w_lambda": (0.5, 1.0),
        "w_t": (1.0, 4.0), "w_a": (0.1, 0.25, 1.0)}
COMMON = {"light_samples": 64, "light_grid": 32, "hybrid": False, "adaptive_lod": False, "interleave": False}
SAMPLES = 64
FRAMES = (0, 3)
"""orbit frames (of 12) of ``bench binocular``'s path, 96x64 stereo"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/vsa_fit.json"),
                        help="where to write the fit (default out/vsa_fit.json; the package reads "
                             "src/volren/render/marching/vsa_fit.json)")
    args = parser.parse_args()
    views = [v for f in FRAMES for v in make_views(path_camera(f, 12, (96, 64)), "stereo")]
    scenes = {name: builtin_scene(name, 64) for name in SCENES}
    refs = {name: Reference(ReferenceConfig(samples=512, light_samples=64), device="cpu").render(s, views).images
            for name, s in scenes.items()}

    def score(name: str, **config) -> tuple[float, int]:
        frame = CACRM(CACRMConfig(**COMMON, **config), device="cpu").render(scenes[name], views)
        c = frame.stats.counters
        return (float(np.mean([psnr(r, img) for r, img in zip(refs[name], frame.images, strict=True)])),
                c["density_samples"] - c["shared_samples"])

    curves = {name: [score(name, samples=n, vsa=False) for n in range(12, SAMPLES + 9, 4)] for name in SCENES}

    def uniform_at(name: str, gathers: int) -> float:
        g, p = zip(*[(np.log(c[1]), c[0]) for c in curves[name]], strict=True)
        return float(np.interp(np.log(gathers), g, p))

    trials = []
    for values in itertools.product(*GRID.values()):
        weights = dict(zip(GRID, values, strict=True))
        per_scene = {}
        for name in SCENES:
            q, g = score(name, samples=SAMPLES, **weights)
            per_scene[name] = {"psnr": round(q, 3), "gathers": g, "gain_db": round(q - uniform_at(name, g), 3)}
        gains = [s["gain_db"] for s in per_scene.values()]
        trials.append({**weights, "min_gain_db": min(gains), "mean_gain_db": round(float(np.mean(gains)), 3),
                       "scenes": per_scene})
        print(weights, [s["gain_db"] for s in per_scene.values()], flush=True)
    best = max(trials, key=lambda t: (t["min_gain_db"], t["mean_gain_db"]))
    doc = {
        "note": "written by scripts/fit_vsa.py; CACRMConfig takes its VSA defaults from 'weights'",
        "objective": f"largest worst-scene PSNR gain of VSA at N = {SAMPLES} over uniform steps at equal voxel "
                     "gathers (uniform PSNR interpolated in log gathers), against the reference",
        "setup": {"scenes": SCENES, "resolution": 64, "views": f"stereo 96x64, bench binocular orbit frames {FRAMES}",
                  "reference": "512:64", "method": COMMON, "samples": SAMPLES},
        "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version(),
                    "date": datetime.now(UTC).isoformat(timespec="seconds")},
        "uniform": {name: [{"psnr": round(p, 3), "gathers": g} for p, g in c] for name, c in curves.items()},
        "weights": {k: best[k] for k in GRID},
        "result": {k: best[k] for k in ("min_gain_db", "mean_gain_db", "scenes")},
        "trials": trials,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, args.out)
    print(f"best {doc['weights']}: gains {[s['gain_db'] for s in best['scenes'].values()]} dB at equal gathers; "
          f"wrote {args.out}")


if __name__ == "__main__":
    main()

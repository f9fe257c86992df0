"""CMSRM against CACRM per stereo frame, measured interleaved in one process (issue 24, first item).

Both methods render the same scene and stereo pair (the CLI's default eye, 0, 0.4, 3.2) with their defaults; after a
warm-up each is timed ``--repeats`` times, alternating, and the minimum frame time is kept (the machine is shared, so
the minimum is the least-disturbed run). Prints per scene and size: ms per frame and per pass, the counters, the
ratio CMSRM / CACRM frame time (> 1: CACRM faster), each method's cube march as a ratio to CMSRM's, and a checksum of
CACRM's images (to pin them across changes). ``--ablation`` adds CACRM with uniform steps, with k_a = 0 (VSA's
product, no ramp; paper 000 Eq. 4-6), with Eq. 4's ramp alone (w = 0: no product) and with each eye marched alone
(no coupling) to the same interleaved loop; ``--k-a 2,3`` adds CACRM at each of those ramps
(quality: `scripts/k_a_sweep.py`); ``--no-ins`` adds CACRM without interleaved spatial reuse (the quad kernel),
``--camera-pos 0.1,0,0.5`` puts the eyes inside the box."""

from __future__ import annotations

import argparse
import hashlib
import json
import time

import numpy as np

from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.render import CACRM, CMSRM, CACRMConfig, CMSRMConfig


def renderers(ablation: bool, k_as: list[float], no_ins: bool, samples: int) -> dict[str, CMSRM | CACRM]:
    """The methods one case times, CMSRM first (the ratios' base), every one at N = ``samples``."""
    methods: dict[str, CMSRM | CACRM] = {"cmsrm": CMSRM(CMSRMConfig(samples=samples))}
    if ablation:
        methods["cacrm uniform"] = CACRM(CACRMConfig(samples=samples, vsa=False))
        methods["cacrm k_a 0"] = CACRM(CACRMConfig(samples=samples, k_a=0.0))
        methods["cacrm ramp only"] = CACRM(CACRMConfig(samples=samples, w_lambda=0.0, w_t=0.0, w_a=0.0))
        methods["cacrm alone"] = CACRM(CACRMConfig(samples=samples, coupling=False))
    for k_a in k_as:
        methods[f"cacrm k_a {k_a:g}"] = CACRM(CACRMConfig(samples=samples, k_a=k_a))
    if no_ins:
        methods["cacrm no InS"] = CACRM(CACRMConfig(samples=samples, interleave=False))
    methods["cacrm"] = CACRM(CACRMConfig(samples=samples))
    return methods


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", default="smoke,cloud,phantom")
    ap.add_argument("--sizes", default="480x270,960x540")
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ablation", action="store_true",
                    help="also time CACRM with uniform steps, k_a = 0, the ramp alone and without coupling")
    ap.add_argument("--k-a", default="", help="comma-separated k_a values: also time CACRM with each ramp")
    ap.add_argument("--no-ins", action="store_true", help="also time CACRM without interleaved spatial reuse")
    ap.add_argument("--samples", type=int, default=360, help="N for every method")
    ap.add_argument("--camera-pos", default="0,0.4,3.2", help="x,y,z of the stereo pair's centre (0.1,0,0.5: inside)")
    ap.add_argument("--save", help="write CACRM's images per case to this .npz (to compare across changes)")
    ap.add_argument("--compare", help="a .npz from --save: print CACRM's PSNR against it per case")
    args = ap.parse_args()
    saved: dict[str, np.ndarray] = {}
    old = np.load(args.compare) if args.compare else None
    eye = tuple(float(x) for x in args.camera_pos.split(","))
    for name in args.scenes.split(","):
        scene = builtin_scene(name, args.resolution)
        for size in args.sizes.split(","):
            w, h = (int(s) for s in size.split("x"))
            views = make_views(Camera(position=eye, width=w, height=h), "stereo")
            methods = renderers(args.ablation, [float(k) for k in args.k_a.split(",") if k], args.no_ins, args.samples)
            best: dict[str, tuple[float, object]] = {}
            for r in methods.values():
                r.render(scene, views)
            for _ in range(args.repeats):
                for key, r in methods.items():
                    start = time.perf_counter()
                    frame = r.render(scene, views)
                    ms = 1e3 * (time.perf_counter() - start)
                    if key not in best or ms < best[key][0]:
                        best[key] = (ms, frame)
            case = f"{name}-{size}"
            images = np.stack([np.asarray(im) for im in best["cacrm"][1].images])
            saved[case] = images
            row = {"case": case, "ratio": round(best["cmsrm"][0] / best["cacrm"][0], 3),
                   "sha": hashlib.sha1(images.tobytes()).hexdigest()[:12]}
            if old is not None:
                ref = old[case]
                mse = float(np.mean((images - ref) ** 2))
                row["psnr_vs_old"] = "inf" if mse == 0 else round(10 * np.log10(1.0 / mse), 2)
            base_march = best["cmsrm"][1].stats.times_ms["cube_march"]
            for key, (ms, frame) in best.items():
                c = frame.stats.counters
                row[key] = {"ms": round(ms, 1),
                            "passes": {k: round(v, 1) for k, v in frame.stats.times_ms.items()},
                            "cube_march_ratio": round(frame.stats.times_ms["cube_march"] / base_march, 3)
                            if base_march > 0 else None,
                            "counters": {k: int(v) for k, v in c.items()}}
            print(json.dumps(row), flush=True)
    if args.save:
        np.savez_compressed(args.save, **saved)


if __name__ == "__main__":
    main()

"""VPT against the reference on the built-in fire, albedo 0 (emission and absorption only): bias or noise, and where
it comes from (issue 47 item 4: VPT measured 0.4% below the marchers, about 3 sigma over two seeds).

VPT jitters each path inside its pixel (a box filter over the pixel), the reference marches the pixel centres, so
their image sums differ by the pixel filter alone wherever the picture is not linear across a pixel. The script
renders the reference at the pixel centres and box-filtered (``--supersample`` k x k rays per pixel, averaged), and
VPT with ``--seeds`` independent seeds, and prints one JSON line: VPT's image sum over each reference's with the
standard error from the seeds' spread.

    python scripts/vpt_fire_bias.py --seeds 1200 --spp 256 --supersample 8     # ~6 minutes on 2 cores
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

from volren.camera import Camera
from volren.data import builtin_scene
from volren.render import VPT, Reference, ReferenceConfig, VPTConfig


def run(seeds: int, spp: int, supersample: int, size: int, resolution: int) -> dict:
    start = time.perf_counter()
    scene = builtin_scene("fire", resolution)
    scene = dataclasses.replace(scene, volumes=tuple(dataclasses.replace(v, albedo=(0.0, 0.0, 0.0))
                                                     for v in scene.volumes))

    def camera(k: int) -> Camera:
        return Camera(position=(0.0, 0.3, 3.0), look_at=(0.0, 0.1, 0.0), width=size * k, height=size * k, fov_y=40.0)

    centres = Reference(ReferenceConfig(), device="cpu").render(scene, [camera(1)]).images[0][..., :3].sum()
    fine = Reference(ReferenceConfig(), device="cpu").render(scene, [camera(supersample)]).images[0]
    boxed = fine.reshape(size, supersample, size, supersample, 4).mean(axis=(1, 3))[..., :3].sum()
    sums = np.array([VPT(VPTConfig(spp=spp, max_bounces=1, seed=s), device="cpu").render(scene, [camera(1)])
                     .images[0][..., :3].sum() for s in range(seeds)], dtype=np.float64)
    se = sums.std(ddof=1) / np.sqrt(seeds)

    def against(ref: float) -> dict:
        ratio = sums.mean() / ref
        return {"ratio": round(float(ratio), 5), "se": round(float(se / ref), 5),
                "sigmas_from_1": round(float((ratio - 1.0) / (se / ref)), 2)}

    return {"scene": "fire", "albedo": 0.0, "resolution": resolution, "size": size, "seeds": seeds, "spp": spp,
            "supersample": supersample, "box_over_centres": round(float(boxed / centres), 5),
            "vpt_over_centres": against(float(centres)), "vpt_over_box_filtered": against(float(boxed)),
            "seconds": round(time.perf_counter() - start, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1200, help="independent VPT frames (default 1200)")
    ap.add_argument("--spp", type=int, default=256, help="paths per pixel and frame (default 256)")
    ap.add_argument("--supersample", type=int, default=8, help="reference rays per pixel side (default 8)")
    ap.add_argument("--size", type=int, default=40, help="image side [px] (default 40)")
    ap.add_argument("--resolution", type=int, default=64, help="the fire's voxels per axis (default 64)")
    args = ap.parse_args(argv)
    if args.seeds < 2 or args.spp < 1 or args.supersample < 1 or args.size < 8:
        ap.error("--seeds >= 2, --spp >= 1, --supersample >= 1 and --size >= 8")
    print(json.dumps(run(args.seeds, args.spp, args.supersample, args.size, args.resolution)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

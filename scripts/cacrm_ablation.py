"""CACRM's cube march against CMSRM's per stereo frame, by VSA ablation (issue 24, first item): CMSRM, CACRM with
uniform steps, CACRM with k_a = 0 (VSA's product, no ramp) and CACRM, interleaved in one process; the fastest of
``--repeats`` frames each, as ratios to CMSRM's, with the density samples. Prints one JSON line per scene."""

from __future__ import annotations

import argparse
import json

from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.render import CACRM, CMSRM, CACRMConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", default="smoke,cloud,phantom")
    ap.add_argument("--size", default="480x270")
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    w, h = (int(s) for s in args.size.split("x"))
    views = make_views(Camera(position=(0.0, 0.4, 3.2), width=w, height=h), "stereo")
    for name in args.scenes.split(","):
        scene = builtin_scene(name, args.resolution)
        renderers = {"cmsrm": CMSRM(), "cacrm uniform": CACRM(CACRMConfig(vsa=False)),
                     "cacrm k_a 0": CACRM(CACRMConfig(k_a=0.0)), "cacrm": CACRM()}
        for r in renderers.values():
            r.render(scene, views)
        best: dict[str, tuple[float, int]] = {}
        for _ in range(args.repeats):
            for key, r in renderers.items():
                frame = r.render(scene, views)
                ms = frame.stats.times_ms["cube_march"]
                if key not in best or ms < best[key][0]:
                    best[key] = (ms, frame.stats.counters["density_samples"])
        base = best["cmsrm"][0]
        print(json.dumps({"scene": name, "size": args.size, **{k: {"cube_march_ms": round(ms, 1),
                          "ratio": round(ms / base, 3), "density_samples": n} for k, (ms, n) in best.items()}}),
              flush=True)


if __name__ == "__main__":
    main()

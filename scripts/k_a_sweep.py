"""Eq. 4's ramp k_a at the default N against the reference: PSNR and voxel gathers of CACRM per k_a, with CMSRM and
uniform CACRM steps alongside (issue 24: the k_a default, decided at the papers' sizes).

`scripts/fit_vsa.py` fits the VSA constants at N = 64 (quality at equal gathers), where a longer ramp loses; users
march at the default N = 360, where every method sits near the error floor and a longer ramp mostly saves gathers.
This measures that regime: per scene, orbit frames of ``bench binocular`` (stereo, 12-frame orbit), every method
against the reference (``bench binocular``'s: 1024 samples and light samples), as ``bench binocular`` configures
them (light grid, 96 light samples, no hybrid). One JSON line per scene.

    python scripts/k_a_sweep.py --resolution 64 --frames 0 --size 96x54 --reference 128   # a quick look (~5 s)
    python scripts/k_a_sweep.py                      # the papers' 256^3 at 480x270, three frames (~10 min, 2 cores)
    python scripts/k_a_sweep.py --samples 64 --no-lod --k-a 1.5,3 --uniform 56,64   # the fit's N = 64
"""

from __future__ import annotations

import argparse
import json
import time

from volren.bench.binocular import gathers, path_camera
from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.metrics import psnr
from volren.render import CACRM, CMSRM, CACRMConfig, CMSRMConfig, Reference, ReferenceConfig


def methods(k_as: list[float], samples: int, lod: bool, uniform: list[int], light_grid: int, no_ins: bool
            ) -> dict[str, CMSRM]:
    """CMSRM at N = 360, CACRM at N = ``samples`` per k_a (adaptive LOD ``lod``), uniform CACRM per N (adaptive LOD
    off, as `equal_gathers`: with it a low N also picks a coarser density level)."""
    base = {"light_samples": 96, "light_grid": light_grid, "hybrid": False}
    out: dict[str, CMSRM] = {"CMSRM:360:96": CMSRM(CMSRMConfig(samples=360, **base))}
    for k_a in k_as:
        for ins in (True, False) if no_ins else (True,):
            out[f"CACRM:{samples} k_a {k_a:g}" + ("" if ins else " no InS")] = CACRM(
                CACRMConfig(samples=samples, k_a=k_a, adaptive_lod=lod, interleave=ins, **base))
    for n in uniform:
        out[f"CACRM:{n} uniform"] = CACRM(CACRMConfig(samples=n, vsa=False, adaptive_lod=False, **base))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="smoke,cloud,phantom")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--light-grid", type=int, help="default: half the resolution (bench binocular's 128 at 256^3)")
    ap.add_argument("--size", default="480x270", help="stereo view size WxH")
    ap.add_argument("--frames", default="0,4,8", help="frames of the 12-frame orbit")
    ap.add_argument("--k-a", default="1.5,2,2.25,3", help="comma-separated k_a values")
    ap.add_argument("--samples", type=int, default=360, help="CACRM's base step count N for the k_a rows")
    ap.add_argument("--no-lod", action="store_true", help="the k_a rows without the adaptive LOD (as the uniform rows)")
    ap.add_argument("--no-ins", action="store_true", help="each k_a row also without interleaved spatial reuse")
    ap.add_argument("--camera-pos", help="x,y,z: one stereo pair there (0.1,0,0.5: inside) instead of orbit frames")
    ap.add_argument("--uniform", default="64,96,128,160", help="uniform-step counts N (empty: none)")
    ap.add_argument("--reference", type=int, default=1024, help="reference samples and light samples")
    args = ap.parse_args(argv)
    w, h = (int(s) for s in args.size.split("x"))
    frames = [int(f) for f in args.frames.split(",")]
    k_as = [float(k) for k in args.k_a.split(",")]
    uniform = [int(n) for n in args.uniform.split(",") if n]
    eye = tuple(float(x) for x in args.camera_pos.split(",")) if args.camera_pos else None
    shots = [0] if eye else frames  # one stereo pair at --camera-pos, else the orbit frames
    for name in args.scenes.split(","):
        start = time.perf_counter()
        scene = builtin_scene(name, args.resolution)
        renderers = methods(k_as, args.samples, not args.no_lod, uniform, args.light_grid or args.resolution // 2,
                            args.no_ins)
        reference = Reference(ReferenceConfig(samples=args.reference, light_samples=args.reference))
        totals = {key: {"psnr": 0.0, "gathers": 0} for key in renderers}
        for f in shots:
            views = make_views(Camera(position=eye, width=w, height=h) if eye else path_camera(f, 12, (w, h)), "stereo")
            truth = reference.render(scene, views).images
            for key, r in renderers.items():
                frame = r.render(scene, views)
                totals[key]["psnr"] += sum(psnr(a, b) for a, b in zip(truth, frame.images, strict=True)) / 2
                totals[key]["gathers"] += gathers(frame.stats.counters)
        row = {"scene": name, "resolution": args.resolution, "size": args.size,
               **({"camera_pos": list(eye)} if eye else {"frames": frames}),
               "reference": args.reference, "seconds": round(time.perf_counter() - start, 1)}
        row |= {key: {"psnr": round(t["psnr"] / len(shots), 2), "gathers": t["gathers"]} for key, t in totals.items()}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()

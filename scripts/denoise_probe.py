"""Paper 002's denoisers on a still view at the paper's size (issue 24: ours against SVGF, §6.4).

The view, volume and transfer function of ``bench vpt``'s denoiser table (phantom, ct-muscle, 480x396 from
(1.6, 1.2, 2.4)), held still: each denoiser sees ``--history`` frames, then frame H is rendered with ``--sequences``
random sequences on that same history (§6.4.3's test). Against one reference of frame H at ``--reference-spp``:
PSNR, FLIP and the detail kept (`volren.bench.vpt.detail_kept`) averaged over the sequences, and the output
variance (the summed per-pixel variance of the sequences, §6.4.3). One JSON line per denoiser and spp, so that the
gap can be read against the input's spp (the paper's comparison runs at 30 spp; ``bench vpt`` at 8).

    python scripts/denoise_probe.py --spp 8,30 --denoisers none,ours,svgf
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

from volren.bench.vpt import detail_kept
from volren.camera import Camera
from volren.data import builtin_scene
from volren.metrics import flip, psnr
from volren.render import VPT, VPTConfig


def probe(scene, cam: Camera, reference: np.ndarray, denoiser: str, spp: int, history: int, sequences: int) -> dict:
    start = time.perf_counter()
    config = VPTConfig(spp=spp, transfer="ct-muscle", denoise=denoiser)
    r = VPT(config)
    for i in range(history):
        r.render(scene, [cam], i)
    saved = dict(r._denoiser.history) if denoiser != "none" else {}
    outputs = []
    for k in range(sequences):
        r.config = dataclasses.replace(config, seed=1000 + k)
        if saved:
            r._denoiser.history = dict(saved)
        outputs.append(r.render(scene, [cam], history).images[0])
    return {"denoiser": denoiser, "spp": spp,
            "psnr": round(float(np.mean([psnr(reference, o) for o in outputs])), 2),
            "flip": round(float(np.mean([flip(reference, o) for o in outputs])), 4),
            "detail_kept": round(float(np.mean([detail_kept(reference, o) for o in outputs])), 3),
            "output_variance": round(float(np.stack([o[..., :3] for o in outputs]).var(axis=0, ddof=1).sum()), 2),
            "seconds": round(time.perf_counter() - start)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", default="8,30", help="comma-separated input spp")
    ap.add_argument("--denoisers", default="none,ours,svgf,wrls")
    ap.add_argument("--history", type=int, default=10, help="frames of history before the scored frame")
    ap.add_argument("--sequences", type=int, default=4, help="random sequences of the scored frame")
    ap.add_argument("--reference-spp", type=int, default=256)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--size", default="480x396")
    args = ap.parse_args()
    w, h = (int(s) for s in args.size.split("x"))
    scene = builtin_scene("phantom", args.resolution)
    cam = Camera(position=(1.6, 1.2, 2.4), width=w, height=h, fov_y=40.0)
    start = time.perf_counter()
    reference = VPT(VPTConfig(spp=args.reference_spp, transfer="ct-muscle")).render(scene, [cam], args.history)
    print(json.dumps({"reference_spp": args.reference_spp, "frame": args.history, "size": args.size,
                      "resolution": args.resolution, "seconds": round(time.perf_counter() - start)}), flush=True)
    for spp in (int(s) for s in args.spp.split(",")):
        for name in args.denoisers.split(","):
            print(json.dumps(probe(scene, cam, reference.images[0], name, spp, args.history, args.sequences)),
                  flush=True)


if __name__ == "__main__":
    main()

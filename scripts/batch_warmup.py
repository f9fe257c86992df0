"""Measure the warm-up a temporal method needs when the batch engine (`volren.distributed.engine`) starts a worker
mid-sequence: the worst PSNR [dB] of frames S..S+7 rendered on a fresh renderer after W warm-up frames, against the
same frames of one continuous run (the engine's docstring gives the figures and the W chosen: >= 60 dB).

    .venv/bin/python scripts/batch_warmup.py vpt-denoise 0 1 2 4 8 16
"""

from __future__ import annotations

import argparse

from volren.metrics import psnr
from volren.plan import plan_render, render_parser

SMALL = ("--width", "64", "--height", "48", "--views", "mono", "--orbit", "30", "--frames", "48", "--max-minutes", "0")
CASES = {
    "fog": ("--scene", "dynamic", "--method", "fog"),
    "vpt-denoise": ("--method", "vpt", "--denoise", "ours", "--spp", "2"),
    "gi-sresir": ("--gi", "sresir"),
}
START, FRAMES = 24, 8


def plan(case: str):
    args = render_parser().parse_args(["animate", *CASES[case], *SMALL])
    return plan_render(args, args.method)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=CASES)
    ap.add_argument("warmups", type=int, nargs="+", help=f"W values, each <= {START}")
    a = ap.parse_args()
    single = plan(a.case)
    want = [single.render(i).images[0][..., :3] for i in range(START + FRAMES)][START:]
    for w in a.warmups:
        fresh = plan(a.case)
        for i in range(START - w, START):
            fresh.render(i)
        worst = min(psnr(ref, fresh.render(START + k).images[0][..., :3]) for k, ref in enumerate(want))
        print(f"{a.case}: warm-up {w:2d} frames: worst PSNR {worst:.1f} dB", flush=True)


if __name__ == "__main__":
    main()

"""Regenerate the comparison figures behind docs/BENCHMARKS.md's quality claims.

    python scripts/figures.py                        # into out/figures, about a minute on 2 CPU cores
    python scripts/figures.py --out docs/figures     # update the committed figures

banding.png: the phantom close up, left eye. Top row: reference (512:512), DSSRM:100:48, CMSRM:100:48, CACRM (N_max
360 with VSA and coupling). Bottom row: their error heat maps against the reference (per-pixel L1 of normalised RGB
on [0, 25%], paper 000 Fig. 7 "D"), PSNR in the file's sidecar JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

from volren.camera import Camera, make_views
from volren.data import builtin_scene, classic_look
from volren.imageio import composite, to_srgb8
from volren.metrics import error_heatmap, psnr
from volren.progress import progress
from volren.render import CACRM, CMSRM, DSSRM, CACRMConfig, CMSRMConfig, DSSRMConfig, Reference, ReferenceConfig

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "out" / "figures"
"""Not docs/figures: scripts never overwrite tracked files unless asked to (``--out docs/figures``)."""
EXPOSURE = 1.5
"""[stops] for the PNGs (single scattering alone is dim)"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for banding.png/json (default: out/figures)")
    out = ap.parse_args().out
    out.mkdir(parents=True, exist_ok=True)
    scene = classic_look(builtin_scene("phantom", 128))  # the opacity and light banding.json was measured under
    views = make_views(Camera(position=(0.9, 0.6, 2.0), look_at=(0.0, 0.1, 0.0), width=320, height=240, fov_y=50),
                       "stereo")
    common = {"light_grid": 64, "hybrid": False}
    renders = {
        "reference 512:512": Reference(ReferenceConfig(samples=512, light_samples=512), "cpu"),
        "DSSRM:100:48": DSSRM(DSSRMConfig(samples=100, light_samples=48, light_grid=64), "cpu"),
        "CMSRM:100:48": CMSRM(CMSRMConfig(samples=100, light_samples=48, **common), "cpu"),
        "CACRM": CACRM(CACRMConfig(samples=360, light_samples=96, **common), "cpu"),
    }
    with progress("figures: banding", len(renders) * sum(v.height for v in views), always=True) as advance:
        for r in renders.values():  # each view's image pass reports its rows: minutes on a CPU
            r.on_rows = advance
        images = {name: r.render(scene, views).images[0] for name, r in renders.items()}
    ref = images["reference 512:512"]
    top = [to_srgb8(composite(img, scene.background), exposure=EXPOSURE) for img in images.values()]
    bottom = [error_heatmap(ref, img) for img in images.values()]
    grid = np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0)
    Image.fromarray(grid).save(out / "banding.png")
    scores = {name: round(psnr(ref, img), 2) for name, img in images.items() if img is not ref}
    (out / "banding.json").write_text(json.dumps({"columns": list(images), "psnr_db": scores,
                                                  "exposure_stops": EXPOSURE}, indent=2) + "\n")
    print(scores)


if __name__ == "__main__":
    main()

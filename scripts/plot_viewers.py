"""Scaling plots of ``volren bench viewers`` (paper 003 Fig. 11-14) from its JSON, and a picture of the fog scenes.

    python scripts/plot_viewers.py                       # every docs/bench/viewers-*.json, and the scene picture
    python scripts/plot_viewers.py docs/bench/viewers-cpu-quick.json --out docs/figures   # update the committed plot

Writes out/figures/<json stem>.png (``--out DIR`` elsewhere): fog-stage time per frame and shadow rays per frame
against the viewer count, per scene, for the per-viewer reference and the shared grid at each voxel size; and
fog-scenes.png: hall and courtyard from their default viewpoints (shared grid, 0.5 m voxels, 8 temporally blended
frames).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image

from volren.camera import Camera
from volren.data.fog_scenes import fog_scene, fog_scene_camera
from volren.imageio import composite, to_srgb8
from volren.render import FogConfig, FogRenderer

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "out" / "figures"
"""Not docs/figures: scripts never overwrite tracked files unless asked to (``--out docs/figures``)."""


def plot(path: Path, out_dir: Path) -> Path:
    doc = json.loads(path.read_text())
    rows = [r for r in doc["rows"] if r["table"] == "viewers"]
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(2, len(scenes), figsize=(5 * len(scenes), 7), squeeze=False)
    for c, scene in enumerate(scenes):
        for method in dict.fromkeys(r["method"] for r in rows if r["scene"] == scene):
            pts = sorted((r["viewers"], r["fog_ms"], r["shadow_rays"]) for r in rows
                         if r["scene"] == scene and r["method"] == method)
            n, ms, rays = zip(*pts, strict=True)
            axes[0, c].plot(n, ms, marker="o", label=method)
            axes[1, c].plot(n, rays, marker="o", label=method)
        axes[0, c].set_title(f"{scene}: fog stages per frame")
        axes[0, c].set_ylabel("ms")
        axes[1, c].set_ylabel("shadow rays per frame")
        axes[1, c].set_yscale("log")
        for ax in axes[:, c]:
            ax.set_xlabel("viewers")
            ax.grid(alpha=0.3)
            ax.legend()
    machine = doc["machine"]
    fig.suptitle(f"bench viewers ({'quick' if doc['quick'] else 'full'}, {doc['settings']['size']}) on "
                 f"{machine['device_name']}")
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"{path.stem}.png"
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def scenes_picture(out_dir: Path) -> Path:
    tiles = []
    for name in ("hall", "courtyard"):
        spot = fog_scene_camera(name)
        cam = Camera(position=spot["position"], look_at=spot["look_at"], width=480, height=270, fov_y=60.0)
        renderer = FogRenderer(FogConfig(voxel_size=0.5), "cpu")
        scene = fog_scene(name)
        for f in range(8):
            image = renderer.render(scene, [cam], f).images[0]
        tiles.append(to_srgb8(composite(image, (0.0, 0.0, 0.0))))
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / "fog-scenes.png"
    Image.fromarray(np.concatenate(tiles, axis=1)).save(out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="*", type=Path, help="bench viewers JSON files (default: docs/bench/viewers-*.json)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for the PNGs (default: out/figures)")
    args = ap.parse_args()
    for p in args.paths or sorted((ROOT / "docs" / "bench").glob("viewers-*.json")):
        print(f"wrote {plot(p, args.out)}")
    if not args.paths:
        print(f"wrote {scenes_picture(args.out)}")


if __name__ == "__main__":
    main()

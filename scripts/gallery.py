"""Render every built-in scene (`volren scenes`) with its defaults, one view each, and a contact sheet of them.

    python scripts/gallery.py                              # out/gallery/<scene>.png and out/gallery.png
    python scripts/gallery.py --out docs/figures/gallery   # update the committed gallery (docs/figures/gallery.png)

Each scene renders as `volren render --scene NAME --views mono` does (its own light, sky, camera, and method fog for
the fog scenes), so the sheet shows the first picture a user gets; `--width`/`--height`/`--resolution` size it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from volren.cli import main as volren
from volren.data import BUILTIN_SCENES
from volren.data.fog_scenes import FOG_SCENES

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "out" / "gallery"
"""Not docs/figures: scripts never overwrite tracked files unless asked to (``--out docs/figures/gallery``)."""
COLUMNS = 4
LABEL = 14
"""[px] height of the name strip above each tile"""


def all_scenes() -> list[str]:
    """The built-in scenes in `volren scenes` order."""
    return [*BUILTIN_SCENES, *FOG_SCENES]


def render_scene(name: str, path: Path, width: int, height: int, resolution: int, device: str) -> None:
    """`volren render` of one scene's default view into ``path`` (a PNG); raises if the command fails."""
    args = ["render", "--scene", name, "--views", "mono", "--width", str(width), "--height", str(height),
            "--device", device]
    args += ["--method", "fog"] if name in FOG_SCENES else ["--resolution", str(resolution)]
    with tempfile.TemporaryDirectory(prefix="volren-gallery-") as scratch:
        with contextlib.redirect_stdout(io.StringIO()):
            code = volren([*args, "--out", scratch])
        if code != 0:
            raise SystemExit(f"gallery: volren {' '.join(args)} exited with {code}")
        shutil.copyfile(Path(scratch) / "view0.png", path)


def contact_sheet(tiles: dict[str, Path]) -> Image.Image:
    """The tiles on a grid of COLUMNS, each under a strip with its scene's name."""
    images = {name: Image.open(path).convert("RGB") for name, path in tiles.items()}
    w, h = next(iter(images.values())).size
    rows = -(-len(images) // COLUMNS)
    sheet = Image.new("RGB", (COLUMNS * w, rows * (h + LABEL)), (12, 12, 14))
    draw = ImageDraw.Draw(sheet)
    for i, (name, image) in enumerate(images.items()):
        x, y = (i % COLUMNS) * w, (i // COLUMNS) * (h + LABEL)
        sheet.paste(image, (x, y + LABEL))
        draw.text((x + 4, y + 1), name, fill=(230, 230, 230))
    return sheet


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT,
                    help="folder for <scene>.png; the sheet goes beside it as <folder>.png (default: out/gallery)")
    ap.add_argument("--scenes", default=",".join(all_scenes()), help="comma-separated scenes (default: all)")
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--resolution", type=int, default=128, help="voxels per axis of the volume scenes")
    ap.add_argument("--device", default="auto")
    args = ap.parse_args(argv)
    names = args.scenes.split(",")
    unknown = sorted(set(names) - set(all_scenes()))
    if unknown:
        ap.error(f"--scenes: unknown {', '.join(unknown)}; choose from {', '.join(all_scenes())}")
    args.out.mkdir(parents=True, exist_ok=True)
    tiles = {}
    for name in names:
        tiles[name] = args.out / f"{name}.png"
        render_scene(name, tiles[name], args.width, args.height, args.resolution, args.device)
        print(f"{name}: {tiles[name]}", flush=True)
    sheet = args.out.with_suffix(".png")
    contact_sheet(tiles).save(sheet, optimize=True)
    print(f"contact sheet: {sheet} ({np.ceil(sheet.stat().st_size / 1024):.0f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

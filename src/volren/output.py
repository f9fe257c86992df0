"""Write a rendered frame to disk: a PNG per view (sRGB after exposure/tone map), a side-by-side PNG for a stereo
pair, a contact sheet of more views, optional linear ``.npy`` images, and ``stats.json`` for the whole render."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from volren.errors import VolrenError
from volren.imageio import save_linear, save_png, save_side_by_side
from volren.render.frame import Frame


def prepare_out_dir(path: str | Path) -> Path:
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VolrenError(f"cannot create output folder '{out}': {exc.strerror}") from exc
    return out


def write_frame(
    frame: Frame,
    out: Path,
    background: tuple[float, float, float],
    *,
    exposure: float = 0.0,
    tonemap: str = "none",
    linear: bool = False,
    prefix: str = "",
) -> list[Path]:
    """Write one frame's files into ``out``; returns their paths. ``prefix`` tells frames of a sequence apart."""
    paths = []
    for v, image in enumerate(frame.images):
        p = out / f"{prefix}view{v}.png"
        save_png(p, image, background, exposure=exposure, tonemap=tonemap)
        paths.append(p)
        if linear:
            p = out / f"{prefix}view{v}.npy"
            save_linear(p, image)
            paths.append(p)
    if len(frame.images) == 2 and frame.images[0].shape == frame.images[1].shape:
        p = out / f"{prefix}stereo.png"
        save_side_by_side(p, frame.images, background, exposure=exposure, tonemap=tonemap)
        paths.append(p)
    if len(frame.images) > 2:
        p = out / f"{prefix}contact.png"
        save_png(p, contact_sheet(frame.images), background, exposure=exposure, tonemap=tonemap)
        paths.append(p)
    return paths


def contact_sheet(images: list[np.ndarray]) -> np.ndarray:
    """The views on a near-square grid, row by row (cells of the largest view's size, views top-left aligned)."""
    cols = math.ceil(math.sqrt(len(images)))
    rows = math.ceil(len(images) / cols)
    h = max(i.shape[0] for i in images)
    w = max(i.shape[1] for i in images)
    sheet = np.zeros((rows * h, cols * w, 4), dtype=np.float32)
    for n, image in enumerate(images):
        r, c = divmod(n, cols)
        sheet[r * h:r * h + image.shape[0], c * w:c * w + image.shape[1]] = image
    return sheet


def write_stats(out: Path, frames: list[Frame], extra: dict[str, Any]) -> Path:
    """``stats.json``: device, method, settings, per-frame pass times [ms] and work counters."""
    p = out / "stats.json"
    doc = {**extra, "frames": [{"index": f.index, **f.stats.to_dict()} for f in frames]}
    p.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    return p

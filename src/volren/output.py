"""Write a rendered frame to disk: a PNG per view (sRGB after exposure/tone map), a side-by-side PNG for a stereo
pair, optional linear ``.npy`` images, and ``stats.json`` for the whole render."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

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
    return paths


def write_stats(out: Path, frames: list[Frame], extra: dict[str, Any]) -> Path:
    """``stats.json``: device, method, settings, per-frame pass times [ms] and work counters."""
    p = out / "stats.json"
    doc = {**extra, "frames": [{"index": f.index, **f.stats.to_dict()} for f in frames]}
    p.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    return p

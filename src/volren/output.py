"""Write a rendered frame to disk: a PNG per view (sRGB after exposure/tone map), a side-by-side PNG for a stereo
pair, a contact sheet of more views, optional linear ``.npy`` images, and ``stats.json`` for the whole render.

A run is written into a temporary sibling folder and moved into ``--out`` only when it is complete
(:func:`run_output`), so a failure leaves ``--out`` as it was. A new run replaces the files an earlier run wrote
there (every name :data:`RUN_FILE` matches: views, stereo, contact sheet, animation, stats, heat maps that
``volren compare`` wrote beside them) and keeps everything else (other files, sub-folders such as ``out/cloud``):
a mono render never sits beside views 1-3 of an old stereo or multi-view run.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from skimage.transform import downscale_local_mean

from volren.errors import VolrenError
from volren.imageio import save_linear, save_png, save_side_by_side

if TYPE_CHECKING:  # only named in annotations: Frame.save writes through this module, so no import back
    from volren.render.frame import Frame

# The names write_frame, write_stats, write_mp4 and ``volren compare``'s default heat map give a run's files, and
# ``--workers``' manifest (`volren.distributed.engine`): a plain render there ends the batch it recorded.
RUN_FILE = re.compile(r"(frame\d{4}_)?(view\d+(_error)?\.(png|npy)|(stereo|contact)\.png)|stats\.json|animation\.mp4"
                      r"|batch\.json")


def is_run_file(path: Path) -> bool:
    return path.is_file() and RUN_FILE.fullmatch(path.name) is not None


@contextmanager
def run_output(path: str | Path) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``path`` to write a run into; on success move the run into ``path``
    (replacing an earlier run's files, see the module docstring), on an exception delete it and leave ``path``
    untouched. Refuses up front a ``path`` that is a file or whose parent cannot be created."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise VolrenError(f"--out '{out}' is a file, not a folder")
    created = [p for p in (out.parent, *out.parent.parents) if not p.exists()]  # removed again on failure
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.volren-", dir=out.parent))
    except OSError as exc:
        raise VolrenError(f"cannot create output folder '{out}': {exc.strerror}") from exc
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        for p in created:  # innermost first
            try:
                p.rmdir()
            except OSError:
                break
        raise
    _move_into_place(staging, out)


def _move_into_place(staging: Path, out: Path) -> None:
    """A new folder is one rename; into an existing one, the old run's files go to a trash folder first (put back
    if a move fails), then the new files are renamed in, so the folder never holds two runs' files."""
    try:
        os.rename(staging, out)  # atomic when ``out`` does not exist (or is an empty folder, on POSIX)
        return
    except OSError:
        pass
    trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.volren-old-", dir=out.parent))
    old = [p for p in out.iterdir() if is_run_file(p)]
    moved: list[Path] = []
    try:
        for p in old:
            os.replace(p, trash / p.name)
        for p in staging.iterdir():
            os.replace(p, out / p.name)
            moved.append(out / p.name)
    except OSError as exc:
        for p in moved:
            p.unlink(missing_ok=True)
        for p in trash.iterdir():
            os.replace(p, out / p.name)
        shutil.rmtree(staging, ignore_errors=True)
        trash.rmdir()
        raise VolrenError(f"cannot write into output folder '{out}': {exc.strerror}") from exc
    shutil.rmtree(trash, ignore_errors=True)
    staging.rmdir()


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


MAX_SHEET_SIDE = 4096
"""[px] a contact sheet's longer side at most: its cells shrink by a whole factor (block means) to fit, so that 1,024
views of 640x360 give a 4096x2304 sheet instead of a 20480x11520 one (3.8 GB of float32 plus the PNG's temporaries:
what ran a 24 GB machine out of memory)."""


def contact_sheet(images: list[np.ndarray]) -> np.ndarray:
    """The views on a near-square grid, row by row (cells of the largest view's size divided by a whole factor so
    that the sheet's longer side is at most ``MAX_SHEET_SIDE``, views top-left aligned)."""
    cols = math.ceil(math.sqrt(len(images)))
    rows = math.ceil(len(images) / cols)
    h = max(i.shape[0] for i in images)
    w = max(i.shape[1] for i in images)
    f = max(1, math.ceil(max(rows * h, cols * w) / MAX_SHEET_SIDE))
    h, w = -(-h // f), -(-w // f)
    sheet = np.zeros((rows * h, cols * w, 4), dtype=np.float32)
    for n, image in enumerate(images):
        if f > 1:
            image = downscale_local_mean(image, (f, f, 1)).astype(np.float32)
        r, c = divmod(n, cols)
        sheet[r * h:r * h + image.shape[0], c * w:c * w + image.shape[1]] = image
    return sheet


def write_stats(out: Path, frames: list[Frame], extra: dict[str, Any]) -> Path:
    """``stats.json``: device, method, settings, per-frame pass times [ms] and work counters."""
    p = out / "stats.json"
    doc = {**extra, "frames": [{"index": f.index, **f.stats.to_dict()} for f in frames]}
    p.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    return p


def print_summary(method: str, scene: str, views: int, frames: int, wall: float, last, files: list,
                  stats: Path) -> None:
    """The lines a render ends with: what ran, the last frame's pass times and work, the files written."""
    print(f"{method} on {last.device}: {views} view(s) of '{scene}', {frames} frame(s) in {wall:.2f} s")
    print("  last frame, ms per pass: " + ", ".join(f"{k} {v:.1f}" for k, v in last.times_ms.items()))
    print("  work: " + ", ".join(f"{k} {v:,}" for k, v in last.counters.items()))
    shown = files if len(files) <= 8 else [*files[:6], f"... ({len(files) - 6} more)"]
    print("  wrote " + ", ".join(str(f) for f in [*shown, stats]))

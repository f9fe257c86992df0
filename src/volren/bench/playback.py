"""A volume sequence played at 30 fps (issue 21's `volren bench load` row): how many of its 40 frames were not read in
time, with `volren.data.sequence.VolumeSequence` reading ahead in its worker thread.

The player asks for frame i at t0 + i / fps (t0: when frame 0 is shown), as a display clock would, and does not slip:
frame i is *missed* when it is not ready at its time (``frame(i)`` waits longer than MISS_S). Nothing is rendered, so
the figure is the loader's alone: a renderer on the same cores slows the reading thread.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from volren.data.loaders import LoadedVolume, load_volume
from volren.data.sequence import SequenceConfig, VolumeSequence, frame_files

FRAMES = 40
FPS = 30.0
MISS_S = 1e-3
"""[s] a frame that keeps the player waiting longer than this was not ready at its time"""


@dataclass(frozen=True)
class Playback:
    frames: int
    missed: int
    """frames not ready at their time (of frames 1 .. frames - 1: frame 0 starts the clock)"""
    worst_late_s: float
    """[s] the longest a frame kept the player waiting"""
    read_s: float
    """[s] mean time to read one frame in the worker (1 / read_s frames per second can be sustained)"""


def play(files: tuple[Path, ...], fps: float, load: Callable[[Path], LoadedVolume] = load_volume) -> Playback:
    """Play ``files`` as a sequence at ``fps`` (see the module docstring)."""
    reads: list[float] = []

    def timed(path: Path, **box) -> LoadedVolume:
        start = time.perf_counter()
        vol = load(path, **box)
        reads.append(time.perf_counter() - start)
        return vol

    sequence = VolumeSequence(SequenceConfig(files), timed)
    sequence.frame(0)
    t0, missed, worst = time.perf_counter(), 0, 0.0
    for i in range(1, len(files)):
        time.sleep(max(0.0, t0 + i / fps - time.perf_counter()))
        asked = time.perf_counter()
        sequence.frame(i)
        late = time.perf_counter() - asked
        missed += late > MISS_S
        worst = max(worst, late)
    sequence.close()
    return Playback(len(files), missed, worst, float(np.mean(reads)))


def _frame(n: int, i: int, frames: int) -> np.ndarray:
    """Frame i of an n^3 field (float32, positive everywhere: an OpenVDB grid's active box stays the whole box, as a
    sequence needs) drifting along x."""
    t = np.linspace(0.0, 3.0 * np.pi, n, dtype=np.float32)
    return 0.55 + 0.5 * np.sin(t + 2 * np.pi * i / frames)[None, None, :] * np.sin(1.3 * t)[None, :, None] \
        * np.sin(0.7 * t)[:, None, None]


def write_npy_sequence(folder: Path, n: int, frames: int = FRAMES) -> tuple[Path, ...]:
    for i in range(frames):
        np.save(folder / f"smoke_{i:04d}.npy", _frame(n, i, frames))
    return frame_files(folder / "smoke_####.npy")


def write_vdb_sequence(folder: Path, n: int, frames: int = FRAMES) -> tuple[Path, ...]:
    """Written by OpenVDB itself (`volren.bench.load.write_with_openvdb`)."""
    from volren.bench.load import write_with_openvdb

    write_with_openvdb({f"smoke_{i:04d}.vdb": [{"name": "density", "array": _frame(n, i, frames)}]
                        for i in range(frames)}, folder)
    return frame_files(folder / "smoke_####.vdb")


def playback_rows(size: int, fps: float = FPS, frames: int = FRAMES) -> list[dict]:
    """One row per format: a ``frames``-frame ``size``^3 sequence played at ``fps``."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="volren-bench-playback-") as tmp:
        for fmt, write in ((".npy", write_npy_sequence), (".vdb", write_vdb_sequence)):
            folder = Path(tmp) / fmt[1:]
            folder.mkdir()
            result = play(write(folder, size, frames), fps)
            rows.append({"case": f"{frames}-frame {fmt} sequence at {fps:g} fps", "shape": f"{size}x{size}x{size}",
                         "frames_missed": result.missed, "worst_late_s": result.worst_late_s,
                         "read_s": result.read_s, "sustained_fps": 1.0 / result.read_s})
    return rows

"""Volume sequences: one file per frame (``sim_####.vdb``, ``sim_%04d.npy``, ``sim_*.npy``, a folder of numbered
files) or one file of many time points (a 4-D NIfTI: x, y, z, t), read one frame at a time and ahead of need in a
background thread.

`frame_files` finds a ``--volume``'s frames, in frame order (files, or a NIfTI's `TimePoint` frames);
`VolumeSequence` reads frame i as ``load(files[i])`` (`volren.data.loaders.load_volume` with the same options for
every frame; an OpenVDB sequence's frames over the union of their index boxes, ``load(files[i], index_box=...)``, so an
active box that moves or grows is one grid), loading the next frames in a worker thread while the caller renders, and
holds at most ``keep`` frames. Every frame must match the first in grid shape, placement and value mapping; one that
does not is refused, naming its file, when it is reached.

Values share the first frame's mapping: a loader that normalises integers by the file's own range would map each frame
differently and the brightness would flicker, so every frame is re-mapped to the first frame's ``value_range``
(values below its minimum clamp to 0, above its maximum exceed 1). The first frame's range, not one over all frames:
reading every frame's values first would read the whole sequence before the first image (a VDB cannot be read in
part), and a simulation's first frame already holds its range in practice; float files are unchanged anyway.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import re
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from volren.data.loaders import LoadedVolume, TimePoint, ValueMapping, nifti_time_points
from volren.errors import VolrenError

KEEP = 3
"""frames a sequence holds at once: the one being rendered and the next two, being read meanwhile"""
_HASHES = re.compile(r"#+")
_PRINTF = re.compile(r"%(?:0(\d+))?d")
_GLOB = re.compile(r"[*?\[]")
_DIGITS = re.compile(r"\d+")
_EXTENSION = re.compile(r"\.[a-z]\w*(\.gz)?")
_DICOM_MAGIC_AT = 128
"""a DICOM Part 10 file holds b"DICM" after its 128-byte preamble"""


def _suffix(name: str) -> str:
    lower = name.lower()
    return ".nii.gz" if lower.endswith(".nii.gz") else Path(lower).suffix


def _number(name: str) -> int | None:
    """The frame number of a file name: its last run of digits before the extension."""
    runs = _DIGITS.findall(name[: len(name) - len(_suffix(name))])
    return int(runs[-1]) if runs else None


def _is_dicom(path: Path) -> bool:
    if path.suffix.lower() == ".dcm" or path.name.upper() == "DICOMDIR":
        return True
    with open(path, "rb") as f:
        f.seek(_DICOM_MAGIC_AT)
        return f.read(4) == b"DICM"


def _numbered(text: str, entries: list[tuple[int | None, Path]]) -> tuple[Path, ...]:
    """``entries`` (frame number, file) in frame order, refused when a number is missing, repeated or absent, or the
    files mix extensions."""
    if not entries:
        raise VolrenError(f"{text}: no file matches this frame pattern")
    unnumbered = [p.name for n, p in entries if n is None]
    if unnumbered:
        raise VolrenError(f"{text}: {unnumbered[0]} has no frame number in its name")
    suffixes = sorted({_suffix(p.name) for _, p in entries})
    if len(suffixes) > 1:
        raise VolrenError(f"{text}: the frames mix extensions {', '.join(suffixes)}; give a pattern with one")
    entries.sort(key=lambda e: e[0])  # numerically: sim_10 after sim_9
    for (a, pa), (b, pb) in itertools.pairwise(entries):
        if b == a:
            raise VolrenError(f"{text}: {pa.name} and {pb.name} both hold frame {a}")
        if b != a + 1:
            missing = f"frame {a + 1} is" if b == a + 2 else f"frames {a + 1}-{b - 1} are"
            raise VolrenError(f"{text}: {missing} missing (between {pa.name} and {pb.name})")
    return tuple(p for _, p in entries)


def _folder_frames(folder: Path) -> tuple[Path, ...] | None:
    """A folder's numbered files of one extension, or None when it is not a sequence: a DICOM series (any .dcm file,
    DICOMDIR or DICOM Part 10 content), or no numbered file with an extension (one that starts with a letter)."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    if any(_is_dicom(p) for p in files):
        return None
    # an extension starts with a letter: DICOM files named by UID (1.2.840.113619.2.55.1) are not frames ".1"
    frames = [(_number(p.name), p) for p in files if _EXTENSION.fullmatch(_suffix(p.name))]
    frames = [(n, p) for n, p in frames if n is not None]
    return _numbered(str(folder), frames) if frames else None


def frame_files(volume: str | Path) -> tuple[Path, ...] | tuple[TimePoint, ...] | None:
    """The frame files of a ``--volume`` that names a sequence, in frame order; None when it names one volume (an
    existing file, a folder that is not a sequence, or a name with no pattern: the loader reads or refuses it).

    An existing 4-D NIfTI (x, y, z, t, more than one time point) is a sequence of its time points (`TimePoint` frames,
    from its header alone); a NIfTI of another shape (5-D, a vector per voxel) is refused here, naming the file.

    Forms: ``sim_####.vdb`` (a run of ``#`` is the frame number, zero-padded to that many digits), ``sim_%04d.npy``
    (printf ``%d`` or ``%0Nd``), a glob (``sim_*.npy``; frames ordered by the last number in the name), or a folder
    of numbered files of one extension. Frame numbers must run on without a gap (from any first number)."""
    text = str(volume)
    path = Path(text)
    if path.is_file():
        if _suffix(path.name) not in (".nii", ".nii.gz"):
            return None
        count = nifti_time_points(path)
        return tuple(TimePoint(path, t) for t in range(count)) if count > 1 else None
    if path.is_dir():
        return _folder_frames(path)
    name, folder = path.name, path.parent
    fields = _HASHES.findall(name) or [m.group(0) for m in _PRINTF.finditer(name)]
    if len(fields) > 1:
        raise VolrenError(f"{text}: give one frame number field, not {len(fields)} ({', '.join(fields)})")
    if fields:
        field = fields[0]
        width = len(field) if field.startswith("#") else int(_PRINTF.fullmatch(field).group(1) or 1)
        before, _, after = name.partition(field)
        pattern = re.compile(re.escape(before) + r"(\d+)" + re.escape(after))
        matches = [(pattern.fullmatch(p.name), p) for p in _listing(folder)]
        # zero-padded to the field's width, wider only where the number needs it (sim_####: sim_0007, sim_12345)
        return _numbered(text, [(int(m.group(1)), p) for m, p in matches
                                if m and f"{int(m.group(1)):0{width}d}" == m.group(1)])
    if _GLOB.search(name):
        return _numbered(text, [(_number(p.name), p) for p in sorted(folder.glob(name)) if p.is_file()])
    return None


def _listing(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file()) if folder.is_dir() else []


@dataclass(frozen=True)
class SequenceConfig:
    """A sequence's frames and how it is read."""

    files: tuple[Path, ...] | tuple[TimePoint, ...]
    """frame i's file (or time point of one file)"""
    keep: int = KEEP
    """frames held at once (the asked one and the next keep - 1, read ahead), >= 2"""
    loop: bool = False
    """read ahead across the end into the first frames (a player that loops)"""

    def __post_init__(self) -> None:
        if not self.files:
            raise VolrenError("a volume sequence needs at least one frame")
        if self.keep < 2:
            raise VolrenError(f"a volume sequence keeps at least 2 frames (one read ahead), got {self.keep}")


@dataclass(frozen=True)
class _Reference:
    """The first frame's grid, placement and value mapping."""

    shape: tuple[int, ...]
    to_world: np.ndarray
    value_range: tuple[float, float] | None
    hounsfield: bool
    channels: int
    value_mapping: ValueMapping | None


class VolumeSequence:
    """Frame i of a sequence as a `LoadedVolume`, read ahead in one worker thread. The first frame is read at once
    (the reference every other frame is checked against); asking for frame i drops the frames outside i .. i + keep
    - 1 (wrapping with ``loop``) and starts reading the missing ones, so at most ``keep`` frames are held. One caller
    at a time."""

    def __init__(self, config: SequenceConfig, load: Callable[..., LoadedVolume]) -> None:
        self.config = config
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="volren-sequence")
        self._held: dict[int, Future[LoadedVolume]] = {}
        self.index_box = _union_box(config.files)
        """an OpenVDB sequence's frames' index boxes together (`volren.data.vdb.index_box`): every frame is read
        over it, so a simulation whose active box moves or grows keeps one grid and placement (issue 41 item 2);
        None for other files"""
        self._load = load if self.index_box is None else functools.partial(load, index_box=self.index_box)
        first = self._load(config.files[0])
        self._first = _Reference(first.density.shape, first.to_world, first.value_range, first.hounsfield,
                                 len(first.channels), first.value_mapping)
        """what every frame must match (not the first frame's voxels: they are dropped as any frame's)"""
        held: Future[LoadedVolume] = Future()
        held.set_result(first)
        self._held[0] = held

    def __len__(self) -> int:
        return len(self.config.files)

    @property
    def first(self) -> _Reference:
        """The first frame's grid shape, placement, value mapping and channel count: every frame's."""
        return self._first

    @property
    def held(self) -> tuple[int, ...]:
        """The frames held now (read, or being read), in no particular order."""
        return tuple(self._held)

    def frame(self, i: int) -> LoadedVolume:
        """Frame i (waiting for it if it is still being read); the next frames are read meanwhile."""
        n = len(self)
        if not 0 <= i < n:
            raise VolrenError(f"frame {i} is outside the sequence's {n} frames")
        ahead = range(i, i + min(self.config.keep, n))
        window = [j % n for j in ahead] if self.config.loop else [j for j in ahead if j < n]
        for j in [j for j in self._held if j not in window]:
            self._held.pop(j).cancel()
        for j in window:
            if j not in self._held:
                self._held[j] = self._pool.submit(self._read, j)
        return self._held[i].result()

    def check_start(self) -> None:
        """Read and check the first two frames now (before a render writes anything)."""
        self.frame(0)
        if len(self) > 1:
            self._held[1].result()

    def close(self) -> None:
        """Stop reading ahead and drop the frames held."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._held.clear()

    def _read(self, i: int) -> LoadedVolume:
        """In the worker: frame i, checked against the first and mapped to its value range."""
        path, first = self.config.files[i], self._first
        vol = self._load(path)
        what = f"{path}: frame {i} of the sequence"
        if vol.density.shape != first.shape or len(vol.channels) != first.channels:
            raise VolrenError(f"{what} has {_size(vol.density.shape, len(vol.channels))} voxels, the first frame "
                              f"({self.config.files[0].name}) {_size(first.shape, first.channels)}: every frame "
                              "needs the same grid")
        tolerance = 1e-6 * float(np.abs(first.to_world[:3, :3]).max())
        if not np.allclose(vol.to_world, first.to_world, rtol=0.0, atol=tolerance):
            raise VolrenError(f"{what} is placed differently from the first frame ({self.config.files[0].name}): "
                              "every frame needs the same voxel size, origin and orientation (an OpenVDB grid the "
                              "same active box)")
        if (vol.value_range is None) != (first.value_range is None) or vol.hounsfield != first.hounsfield:
            raise VolrenError(f"{what} maps its values differently from the first frame "
                              f"({self.config.files[0].name}): every frame needs the same data type")
        if vol.value_range is None or vol.value_range == first.value_range:
            return vol
        (lo, hi), (lo0, hi0) = vol.value_range, first.value_range
        if hi0 <= lo0:
            raise VolrenError(f"{what}: the first frame ({self.config.files[0].name}) holds the one value {lo0:g}, so "
                              "it gives no value range for the sequence; start the sequence at a frame that varies")
        # the frame's density d stands for lo + d (hi - lo); on the first frame's scale that is (v - lo0) / (hi0 - lo0)
        density = vol.density * np.float32((hi - lo) / (hi0 - lo0)) + np.float32((lo - lo0) / (hi0 - lo0))
        np.maximum(density, 0.0, out=density)
        return dataclasses.replace(vol, density=density, value_range=first.value_range,
                                   value_mapping=first.value_mapping)


def _union_box(files: tuple[Path, ...] | tuple[TimePoint, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    """The union of the frames' OpenVDB index boxes (their topology only), None unless every frame is a .vdb."""
    if not all(isinstance(f, Path) and f.suffix.lower() == ".vdb" for f in files):
        return None
    from volren.data.vdb import index_box  # lazy: tinyvdb only for .vdb users

    boxes = [index_box(f) for f in files]
    return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)


def _size(shape: tuple[int, ...], channels: int) -> str:
    """X x Y x Z, and the channel count of a multi-channel frame"""
    size = "x".join(str(s) for s in shape[::-1])
    return f"{size} in {channels} channels" if channels else size

"""Volume sequences (`volren.data.sequence`): the --volume patterns, gaps, frames that do not match the first, the
read-ahead thread and its memory bound, and playing a sequence in render --frames, animate and serve. Four frames of
a 24^3 blob moving along x keep every render tiny."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import threading
import time
import weakref
from pathlib import Path

import imageio.v2 as imageio
import nibabel as nib
import numpy as np
import pytest
from aiohttp.test_utils import TestClient, TestServer

from test_cli import assert_error, ok
from test_serve import cam_msg, connect, next_frame
from volren.bench.playback import play
from volren.cli import build_parser, served_file
from volren.data.loaders import LoadedVolume, TimePoint, load_volume
from volren.data.sequence import KEEP, SequenceConfig, VolumeSequence, frame_files
from volren.errors import VolrenError
from volren.serve.app import make_app
from volren.serve.loop import RenderLoop
from volren.serve.viewers import Limits

N = 24
FRAMES = 4
SMALL = ("--width", "48", "--height", "32", "--views", "mono", "--samples", "48", "--light-samples", "12",
         "--light-grid", "8", "--device", "cpu")


def blob(i: int, n: int = N) -> np.ndarray:
    """Frame i: a Gaussian blob whose centre moves along x."""
    z, y, x = np.mgrid[0:n, 0:n, 0:n] / (n - 1) * 2 - 1
    return np.exp(-((x + 0.45 - 0.3 * i) ** 2 + y**2 + z**2) / 0.08).astype(np.float32)


@pytest.fixture
def frames(tmp_path: Path) -> Path:
    """A folder holding p_0000.npy .. p_0003.npy."""
    folder = tmp_path / "seq"
    folder.mkdir()
    for i in range(FRAMES):
        np.save(folder / f"p_{i:04d}.npy", blob(i))
    return folder


AFFINE = np.array([[0.0, 0.0, 3.0, -30.0], [2.0, 0.0, 0.0, 10.0], [0.0, 2.5, 0.0, -5.0], [0.0, 0.0, 0.0, 1.0]])
"""a NIfTI affine that permutes and scales the axes (mm): voxel i, j, k -> RAS (3k - 30, 2i + 10, 2.5j - 5)"""


@pytest.fixture
def nifti4d(tmp_path: Path) -> Path:
    """seq.nii.gz, a 4-D NIfTI (x, y, z, t) of the blob's FRAMES time points as int16 (scaled by 1000, so the values
    are mapped as integers are: min..max, 0..1000 by a marker voxel at index 0, 0, 0 in every time point), and
    t_0000.nii.gz .. t_0003.nii.gz, each time point alone as a 3-D NIfTI with the same affine."""
    folder = tmp_path / "nifti"
    folder.mkdir()
    stored = [np.rint(blob(i) * 1000).astype(np.int16).transpose(2, 1, 0) for i in range(FRAMES)]  # [x, y, z]
    for volume in stored:
        volume[0, 0, 0] = 1000
    nib.save(nib.Nifti1Image(np.stack(stored, axis=-1), AFFINE), folder / "seq.nii.gz")
    for i, volume in enumerate(stored):
        nib.save(nib.Nifti1Image(volume, AFFINE), folder / f"t_{i:04d}.nii.gz")
    return folder


def touch(folder: Path, *names: str) -> Path:
    folder.mkdir(exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"")
    return folder


def test_patterns_name_the_same_frames_in_numeric_order(frames: Path, tmp_path: Path):
    expected = tuple(frames / f"p_{i:04d}.npy" for i in range(FRAMES))
    for form in ("p_####.npy", "p_%04d.npy", "p_*.npy"):
        assert frame_files(frames / form) == expected, form
    assert frame_files(frames) == expected  # a folder of numbered files of one extension
    assert frame_files(frames / "p_0002.npy") is None  # a plain file stays one volume
    unpadded = touch(tmp_path / "u", *(f"q_{i}.npy" for i in (8, 9, 10, 11)), "notes.txt")
    order = [p.name for p in frame_files(unpadded / "q_*.npy")]
    assert order == ["q_8.npy", "q_9.npy", "q_10.npy", "q_11.npy"]  # by number, not by name (q_10 < q_8)
    assert [p.name for p in frame_files(unpadded / "q_%d.npy")] == order
    assert [p.name for p in frame_files(unpadded)] == order  # notes.txt has no number: not a frame


def test_gaps_no_match_and_dicom_folders(frames: Path, tmp_path: Path):
    (frames / "p_0002.npy").unlink()
    with pytest.raises(VolrenError, match=r"frame 2 is missing \(between p_0001.npy and p_0003.npy\)"):
        frame_files(frames / "p_####.npy")
    gap = touch(tmp_path / "g", "s_1.vdb", "s_5.vdb")
    with pytest.raises(VolrenError, match="frames 2-4 are missing"):
        frame_files(gap / "s_*.vdb")
    with pytest.raises(VolrenError, match=r"p_##\.npy: no file matches"):
        frame_files(frames / "p_##.npy")
    with pytest.raises(VolrenError, match=r"mix extensions \.npy, \.png"):
        frame_files(touch(tmp_path / "m", "a_1.npy", "a_2.npy", "a_1.png"))
    assert frame_files(touch(tmp_path / "d", "IM_0001.dcm", "IM_0002.dcm")) is None  # a DICOM series stays one
    dicom = tmp_path / "d2"
    dicom.mkdir()
    for i in (1, 2):
        (dicom / f"slice{i}.ima").write_bytes(b"\0" * 128 + b"DICM" + b"\0" * 16)  # DICOM content, any name
    assert frame_files(dicom) is None
    uids = touch(tmp_path / "d3", "1.2.840.113619.2.55.3.1", "1.2.840.113619.2.55.3.2", "1.2.840.113619.2.55.4.1")
    assert frame_files(uids) is None  # DICOM files named by UID (no preamble): no extension, not frames


class Reads:
    """A frame loader that counts its reads, says when each frame is read and can hold one back until released."""

    def __init__(self, hold: int | None = None) -> None:
        self.count: dict[str, int] = {}
        self.done = {i: threading.Event() for i in range(16)}
        self.hold, self.release = hold, threading.Event()
        self.alive: list[weakref.ref] = []

    def __call__(self, path: Path) -> LoadedVolume:
        i = int(path.stem)
        if i == self.hold:
            assert self.release.wait(30), "never released"
        self.count[path.name] = self.count.get(path.name, 0) + 1
        density = np.full((2, 2, 2), float(i), dtype=np.float32)
        self.alive.append(weakref.ref(density))
        self.done[i].set()
        return LoadedVolume(density, np.eye(4), None)

    def held(self) -> int:
        """Frames in memory: arrays have no reference cycles, so a dropped one is freed at once."""
        return sum(r() is not None for r in self.alive)


def paths(count: int) -> tuple[Path, ...]:
    return tuple(Path(f"{i}.npy") for i in range(count))


def test_the_next_frames_are_read_before_they_are_asked_for():
    reads = Reads(hold=3)
    seq = VolumeSequence(SequenceConfig(paths(6)), reads)
    assert seq.frame(0).density[0, 0, 0] == 0.0
    assert reads.done[1].wait(10) and reads.done[2].wait(10), "frames 1 and 2 read ahead, unasked"
    assert seq.frame(1).density[0, 0, 0] == 1.0  # returns while frame 3, read ahead, is held back
    assert not reads.done[3].is_set()
    reads.release.set()
    assert [seq.frame(i).density[0, 0, 0] for i in range(2, 6)] == [2.0, 3.0, 4.0, 5.0]
    assert set(reads.count.values()) == {1}, f"each frame read once: {reads.count}"
    seq.close()


def test_at_most_keep_frames_are_held():
    reads = Reads()
    seq = VolumeSequence(SequenceConfig(paths(8), loop=True), reads)
    for step in range(12):  # round the loop one and a half times
        i = step % 8
        assert seq.frame(i).density[0, 0, 0] == float(i)
        for j in range(KEEP):
            assert reads.done[(i + j) % 8].wait(30)
        assert sorted(seq.held) == sorted((i + j) % 8 for j in range(KEEP))
        assert reads.held() <= KEEP, f"frame {i}: {reads.held()} frames in memory"
    seq.close()


def moved(load, frame: str, **change):
    """``load`` with the frame file named ``frame`` returned changed."""
    def read(path: Path) -> LoadedVolume:
        vol = load(path)
        return dataclasses.replace(vol, **change) if path.name == frame else vol
    return read


def test_a_frame_unlike_the_first_is_refused_naming_its_file(frames: Path):
    files = frame_files(frames / "p_####.npy")
    np.save(frames / "p_0002.npy", blob(2, N - 4))
    seq = VolumeSequence(SequenceConfig(files), load_volume)
    assert np.array_equal(seq.frame(1).density, blob(1))
    with pytest.raises(VolrenError, match=r"p_0002\.npy: frame 2 of the sequence has 20x20x20 voxels, the first "
                                          r"frame \(p_0000\.npy\) 24x24x24"):
        seq.frame(2)
    shifted = np.eye(4)
    shifted[0, 3] = 0.1
    seq = VolumeSequence(SequenceConfig(files), moved(load_volume, "p_0001.npy", to_world=shifted))
    with pytest.raises(VolrenError, match=r"p_0001\.npy: frame 1 .* placed differently"):
        seq.check_start()
    seq = VolumeSequence(SequenceConfig(files), moved(load_volume, "p_0003.npy", value_range=(0.0, 1.0)))
    with pytest.raises(VolrenError, match=r"p_0003\.npy: frame 3 .* maps its values differently"):
        seq.frame(3)


def test_integer_frames_share_the_first_frames_value_range(tmp_path: Path):
    """int16 frames are min-max normalised each by its own range: the sequence maps them all by the first's, so a
    value keeps its density from frame to frame."""
    values = [np.arange(8, dtype=np.int16).reshape(2, 2, 2) * s + o for s, o in ((10, 0), (20, 0), (10, -30))]
    for i, v in enumerate(values):
        np.save(tmp_path / f"ct_{i}.npy", v)
    seq = VolumeSequence(SequenceConfig(frame_files(tmp_path / "ct_*.npy")), load_volume)
    lo, hi = 0.0, 70.0  # frame 0's range
    for i, v in enumerate(values):
        vol = seq.frame(i)
        np.testing.assert_allclose(vol.density, np.maximum((v - lo) / (hi - lo), 0.0), atol=1e-6)
        assert vol.value_range == (lo, hi) and vol.value_mapping.range == (lo, hi)


def test_render_frames_equal_each_file_rendered_alone(capfd, frames: Path, tmp_path: Path):
    out = tmp_path / "seq"
    ok(capfd, "render", "--volume", frames / "p_####.npy", "--frames", FRAMES, *SMALL, "--save-linear", "--out", out)
    images = [np.load(out / f"frame{i:04d}_view0.npy") for i in range(FRAMES)]
    assert not np.array_equal(images[0], images[1]), "the blob moves"
    for i in (0, 3):
        ok(capfd, "render", "--volume", frames / f"p_{i:04d}.npy", *SMALL, "--save-linear", "--out", tmp_path / "one")
        assert np.array_equal(np.load(tmp_path / "one" / "view0.npy"), images[i]), f"frame {i}"
    assert_error(capfd, ["render", "--volume", frames / "p_*.npy", "--frames", 5, *SMALL, "--out", tmp_path / "x"],
                 "--frames 5", "has 4 frames", no_out=tmp_path / "x")


def test_a_bad_frame_stops_the_render_with_nothing_written(capfd, frames: Path, tmp_path: Path):
    np.save(frames / "p_0001.npy", blob(1, N - 2))
    assert_error(capfd, ["render", "--volume", frames / "p_%04d.npy", "--frames", 2, *SMALL, "--out", tmp_path / "a"],
                 "p_0001.npy: frame 1 of the sequence has 22x22x22 voxels", no_out=tmp_path / "a")
    np.save(frames / "p_0001.npy", blob(1))
    np.save(frames / "p_0003.npy", blob(3, N - 2))  # reached after two frames are written
    assert_error(capfd, ["render", "--volume", frames, "--frames", 4, *SMALL, "--out", tmp_path / "b"],
                 "p_0003.npy: frame 3", no_out=tmp_path / "b")


def test_animate_plays_the_sequence_as_its_frames(capfd, frames: Path, tmp_path: Path):
    out = tmp_path / "anim"
    ok(capfd, "animate", "--volume", frames / "p_*.npy", "--orbit", "0", *SMALL, "--out", out)
    assert sorted(p.name for p in out.glob("frame*_view0.png")) == [f"frame{i:04d}_view0.png" for i in range(FRAMES)]
    with imageio.get_reader(out / "animation.mp4") as movie:
        assert movie.count_frames() == FRAMES


def assert_serve_plays_in_a_loop(volume: Path) -> None:
    """`serve --volume VOLUME` (a sequence of FRAMES frames), played: frame 0 -> 1 -> ... -> FRAMES - 1 -> 0 -> 1, so
    the frame after the last is the first's image again, and every step in between shows another frame."""
    args = build_parser().parse_args(["serve", "--volume", str(volume), "--max-width", "128", "--max-height", "96"])
    loop = RenderLoop(method="dssrm", limits=Limits(4, 128, 96), device="cpu", **served_file(args),
                      overrides={"samples": 48, "light_samples": 12, "light_grid": 8})

    async def main() -> None:
        async with TestClient(TestServer(make_app(loop, "p"), shutdown_timeout=1.0)) as client:
            ws, welcome = await connect(client)
            assert welcome["animated"]
            await ws.send_json(cam_msg(1))
            _, first = await next_frame(ws)
            await ws.send_json({"type": "settings", "playing": True})
            played = [(await next_frame(ws))[1] for _ in range(FRAMES + 1)]
            await ws.close()
        shown = [first, *played]
        assert np.array_equal(shown[FRAMES], shown[0]) and np.array_equal(shown[FRAMES + 1], shown[1]), "loops"
        assert not any(np.array_equal(a, b) for a, b in itertools.pairwise(shown)), "every step another frame"

    asyncio.run(main())


def test_serve_plays_the_sequence_in_a_loop(frames: Path):
    """Playing steps frame 0 -> 1 -> 2 -> 3 -> 0 -> 1: the fifth frame is the first's image again, and every step
    in between shows another frame."""
    assert_serve_plays_in_a_loop(frames / "p_####.npy")


def test_playback_counts_the_frames_not_read_in_time():
    """`volren.bench.playback.play`: frames read in 100 ms miss every 33 ms slot at 30 fps, and none of the 200 ms
    slots at 5 fps (read ahead while the player waits). 100 ms, three slots, not 50: a frame then stays late however
    much a busy machine oversleeps a slot (with 50 ms, frame 1 was 17 ms late, and an oversleep hid it)."""
    def slow(path: Path) -> LoadedVolume:
        time.sleep(0.1)
        return LoadedVolume(np.zeros((2, 2, 2), np.float32), np.eye(4), None)

    fast = play(paths(6), 30.0, slow)
    assert (fast.frames, fast.missed) == (6, 5) and fast.read_s >= 0.1
    assert play(paths(6), 5.0, slow).missed == 0


def test_serve_refuses_a_multi_channel_volume(tmp_path: Path):
    np.save(tmp_path / "two.npy", np.stack([blob(0), blob(3)]))
    args = build_parser().parse_args(["serve", "--volume", str(tmp_path / "two.npy")])
    with pytest.raises(VolrenError, match="multi-channel volume renders with render and animate only"):
        served_file(args)


def test_a_4d_nifti_is_a_sequence_of_its_time_points(nifti4d: Path):
    """Issue 45 item 3: seq.nii.gz's frames are its time points, each read alone, equal to that time point saved as a
    3-D NIfTI (values, and the one affine's placement for every frame), the value mapping frame 0's."""
    files = frame_files(nifti4d / "seq.nii.gz")
    assert files == tuple(TimePoint(nifti4d / "seq.nii.gz", t) for t in range(FRAMES))
    seq = VolumeSequence(SequenceConfig(files), load_volume)
    first = load_volume(nifti4d / "t_0000.nii.gz")
    assert first.value_range == (0.0, 1000.0)  # int16: min..max of frame 0
    # the affine's placement: voxel index (i, j, k) = (x, y, z) at RAS (3k - 30, 2i + 10, 2.5j - 5) mm, world (-R, S, A)
    corner = first.to_world @ np.array([-1 + 1 / N, -1 + 1 / N, -1 + 1 / N, 1.0])  # voxel (0, 0, 0)'s centre
    np.testing.assert_allclose(corner[:3], np.array([30.0, -5.0, 10.0]) * 1e-3, atol=1e-12)
    for t in range(FRAMES):
        vol = seq.frame(t)
        assert vol.density.shape == (N, N, N) and vol.value_range == (0.0, 1000.0)
        np.testing.assert_array_equal(vol.to_world, first.to_world)
        np.testing.assert_array_equal(vol.density, load_volume(nifti4d / f"t_{t:04d}.nii.gz").density)
        blob_t = np.rint(blob(t) * 1000) / 1000
        blob_t[0, 0, 0] = 1.0
        np.testing.assert_allclose(vol.density, blob_t, atol=1e-6)  # time point t, not another
    seq.close()
    assert frame_files(nifti4d / "t_0001.nii.gz") is None  # a 3-D NIfTI stays one volume


def test_render_frames_of_a_4d_nifti_equal_each_time_point_rendered_alone(capfd, nifti4d: Path, tmp_path: Path):
    out = tmp_path / "seq"
    ok(capfd, "render", "--volume", nifti4d / "seq.nii.gz", "--frames", FRAMES, *SMALL, "--save-linear", "--out", out)
    images = [np.load(out / f"frame{i:04d}_view0.npy") for i in range(FRAMES)]
    assert not np.array_equal(images[0], images[1]), "the blob moves"
    assert images[0][..., 3].max() > 0.05
    for i in (0, 3):
        ok(capfd, "render", "--volume", nifti4d / f"t_{i:04d}.nii.gz", *SMALL, "--save-linear", "--out",
           tmp_path / "one")
        np.testing.assert_array_equal(np.load(tmp_path / "one" / "view0.npy"), images[i])
    assert_error(capfd, ["render", "--volume", nifti4d / "seq.nii.gz", "--frames", 5, *SMALL, "--out", tmp_path / "x"],
                 "--frames 5", "has 4 frames", no_out=tmp_path / "x")


def test_animate_and_serve_play_a_4d_nifti(capfd, nifti4d: Path, tmp_path: Path):
    """animate renders one frame per time point (its --frames defaults to them); serve plays them in a loop: the
    fifth image is the first again, each step another time point."""
    out = tmp_path / "anim"
    ok(capfd, "animate", "--volume", nifti4d / "seq.nii.gz", "--orbit", "0", *SMALL, "--out", out)
    assert sorted(p.name for p in out.glob("frame*_view0.png")) == [f"frame{i:04d}_view0.png" for i in range(FRAMES)]
    with imageio.get_reader(out / "animation.mp4") as movie:
        assert movie.count_frames() == FRAMES
    assert_serve_plays_in_a_loop(nifti4d / "seq.nii.gz")


@pytest.mark.timeout(60)
def test_serve_frames_the_file_for_its_largest_viewer_image(tmp_path: Path):
    """``serve --volume`` starts every viewer where ``vr.render`` frames the file at --max-width x --max-height: a
    tall image needs the eye further back than a wide one; --resolution (a built-in scene's) is refused."""
    import volren as vr
    from volren._api import framed_camera

    path = tmp_path / "b.npy"
    np.save(path, blob(0)[:, :, : N // 2])  # a box twice as wide as it is deep
    eyes = []
    for width, height in ((256, 64), (64, 256)):
        args = build_parser().parse_args(["serve", "--volume", str(path), "--max-width", str(width),
                                          "--max-height", str(height)])
        camera = served_file(args)["camera"]
        want = framed_camera(vr.Scene((vr.load(path),)), width=width, height=height)
        np.testing.assert_allclose(camera.position, want.position, rtol=1e-9)
        np.testing.assert_allclose(camera.look_at, want.look_at, rtol=1e-9, atol=1e-12)
        eyes.append(np.linalg.norm(np.subtract(camera.position, camera.look_at)))
    assert eyes[1] > 1.5 * eyes[0]
    args = build_parser().parse_args(["serve", "--volume", str(path), "--resolution", "128"])
    with pytest.raises(VolrenError, match="serve --volume shows the file: --scene and --resolution apply to built-in"):
        served_file(args)

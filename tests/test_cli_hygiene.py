"""A CLI that says what it does (issue 22 items 4, 8, 9): progress lines, one-line errors for what used to be
tracebacks or misleading messages, density warnings, and a Ctrl-C that stops a render at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import warp as wp

from test_cli import PROGRESS_LINE, assert_error, run
from volren import device
from volren import progress as progress_module
from volren.device import MAX_BANDS, _band_pool, init_warp, launch_rows

TINY = ["--width", "16", "--height", "8", "--views", "mono"]


def test_a_run_of_frames_prints_a_line_at_every_tenth(capfd, tmp_path: Path) -> None:
    r = run(capfd, "render", *TINY, "--frames", "10", "--out", tmp_path / "out")
    assert r.code == 0, r.err
    lines = r.err.splitlines()
    assert all(PROGRESS_LINE.fullmatch(line) for line in lines), r.err
    assert [int(line.split(": ")[2].split("%")[0]) for line in lines] == list(range(10, 101, 10))
    assert "rows)" in lines[-1] and "(80/80 rows)" in lines[-1]  # 10 frames of 8 rows


def test_plain_progress_steps_and_quiet_start(capfd) -> None:
    with progress_module.progress("job", 100, "cases", always=True) as advance:
        for _ in range(100):
            advance(1)
    lines = capfd.readouterr().err.splitlines()
    assert [line.split(": ")[2].split(" ")[0] for line in lines] == [f"{p}%" for p in range(10, 101, 10)]
    assert lines[4].startswith("volren: job: 50% (50/100 cases), 0 s, about 0 s left")
    with progress_module.progress("short", 10) as advance:  # one quick render: no lines
        advance(10)
    assert capfd.readouterr().err == ""


def test_a_long_single_render_says_it_runs_once_the_quiet_time_is_over(capfd, monkeypatch) -> None:
    monkeypatch.setattr(progress_module, "QUIET_SECONDS", 0.0)
    with progress_module.progress("long", 100) as advance:
        for n in (3, 3, 10, 1):
            advance(n)
    percents = [line.split(": ")[2].split(" ")[0] for line in capfd.readouterr().err.splitlines()]
    assert percents == ["3%", "16%"]  # at once, then the next 10% step (and not again within it)


def test_empty_compare_input_is_one_line(capfd, tmp_path: Path) -> None:
    empty = tmp_path / "empty.npy"
    empty.write_bytes(b"")
    assert_error(capfd, ["compare", empty, empty], "empty.npy", "not a .npy file")


def test_random_bytes_npz_is_not_blamed_on_pickles(capfd, tmp_path: Path) -> None:
    path = tmp_path / "noise.npz"
    path.write_bytes(np.random.default_rng(0).bytes(2000))
    line = assert_error(capfd, ["render", *TINY, "--volume", path, "--out", tmp_path / "out"], "noise.npz",
                        "not a .npz file")
    assert "pickle" not in line


@pytest.mark.parametrize(("density", "warning"), [
    (0.0, "has an all-zero density: it renders nothing"),
    (1e30, "is opaque (optical depth 2.5e+30 in its densest voxel): check --density-scale"),
])
def test_a_density_that_renders_nothing_or_a_box_is_warned_of(capfd, tmp_path: Path, density: float,
                                                              warning: str) -> None:
    path = tmp_path / "grid.npy"
    np.save(path, np.full((8, 8, 8), density, dtype=np.float32))
    r = run(capfd, "render", *TINY, "--volume", path, "--out", tmp_path / "out")
    assert r.code == 0, r.err
    assert r.err.splitlines() == [f"volren: warning: volume 'grid.npy' {warning}"]


def test_builtin_scenes_get_no_density_warning(capsys) -> None:
    from volren.data import BUILTIN_SCENES, builtin_scene
    from volren.plan.scene import warn_density

    for name in BUILTIN_SCENES:
        warn_density(builtin_scene(name, 64).volumes, transfer=False)
    assert capsys.readouterr().err == ""


def test_stdout_on_a_full_disk_is_one_line() -> None:
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    code = "import sys; from volren.cli import main; sys.exit(main(['scenes']))"
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-c", code], stdout=full, stderr=subprocess.PIPE, text=True,
                              timeout=120)
    assert done.returncode == 2
    assert done.stderr == "volren: error: cannot write stdout: No space left on device\n"


def test_ctrl_c_stops_a_long_render_at_once_and_leaves_nothing(tmp_path: Path) -> None:
    """One CPU thread: the whole frame would be one uninterruptible launch, so this checks the row steps."""
    out = tmp_path / "out"
    # 640x360: about 7 s on one thread of the faster of our VMs (320x180 finished in 1.8 s there, before the first
    # progress line)
    argv = [sys.executable, "-m", "volren.cli", "render", "--method", "reference", "--scene", "cloud", "--width",
            "640", "--height", "360", "--views", "mono", "--max-minutes", "0", "--out", str(out)]
    # SIGINT back to its default in the child: a test run started as a background job (`make test &`) has it
    # ignored, which the child would inherit, and Python then installs no KeyboardInterrupt handler
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            env={**os.environ, "VOLREN_CPU_THREADS": "1"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    first = proc.stderr.readline()  # rendering for >= 2 s (volren.progress.QUIET_SECONDS) with far to go
    assert PROGRESS_LINE.fullmatch(first.strip()), first + proc.stderr.read()
    sent = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    rest = ""
    for line in proc.stderr:  # up to the render's last word
        rest += line
        if line.strip() == "volren: interrupted":
            break
    said = time.perf_counter()
    rest += proc.stderr.read()  # through the same file object: communicate() would bypass what it has buffered
    proc.wait(timeout=60)
    exited = time.perf_counter()
    assert proc.returncode == 130, rest
    assert rest.splitlines()[-1] == "volren: interrupted" and "Traceback" not in rest
    assert said - sent < 1.5, f"took {said - sent:.1f} s to stop"  # a row launch at most
    # then out at once: the interpreter's exit waits on Warp (0.4-0.7 s on the faster VM, 2-4 s on the slower)
    assert exited - said < 0.2, f"took {exited - said:.2f} s to exit after saying so"
    assert list(tmp_path.iterdir()) == [], "a partial run was left behind"


@wp.kernel
def slow_rows_kernel(out: wp.array2d(dtype=wp.float32), work: int, counter_rows: wp.array2d(dtype=wp.int64),
                     row0: int):
    i, j = wp.tid()
    acc = float(0.0)
    for k in range(work):
        acc += wp.sin(float(k + j))
    out[row0 + i, j] = 1.0 + 0.0 * acc


def slow_rows(monkeypatch) -> tuple:
    """(rows, cols, out, counters) of `slow_rows_kernel` on two band threads, a launch of one row each (whatever
    this machine's speed), compiled and timed by a first launch."""
    monkeypatch.setenv("VOLREN_CPU_THREADS", "2")
    monkeypatch.setattr(device, "STOP_SECONDS", 1e-4)  # a launch of one row each, whatever this machine's speed
    init_warp()
    rows, cols = 256, 64
    out = wp.zeros((rows, cols), dtype=wp.float32, device="cpu")
    counters = wp.zeros((MAX_BANDS, 1), dtype=wp.int64, device="cpu")
    launch_rows(slow_rows_kernel, 1, cols, [out, 20000], "cpu", counters)  # compiled and timed first
    return rows, cols, out, counters


def test_an_interrupted_launch_stops_its_other_bands(monkeypatch) -> None:
    """Ctrl-C in Python (a notebook): the bands still running stop after their current launch, not at the frame's
    end (the pool would otherwise go on rendering it while the next call waits)."""
    rows, cols, out, counters = slow_rows(monkeypatch)

    calls = []

    def interrupt(_rows: int) -> None:  # Ctrl-C once, in the first band to finish a launch
        calls.append(_rows)
        if len(calls) == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        launch_rows(slow_rows_kernel, rows, cols, [out, 20000], "cpu", counters, progress=interrupt)
    for idle in [_band_pool(2).submit(time.sleep, 0.5) for _ in range(2)]:  # both band threads done
        idle.result()
    done = int(np.count_nonzero(out.numpy()[:, 0]))
    assert done < rows // 8 // 2, f"{done} rows rendered after the interrupt"  # less than half a band


def test_a_failed_band_returns_only_once_no_launch_runs(monkeypatch) -> None:
    """A band that raises (a serve render abandoned, Ctrl-C) makes `launch_rows` raise only after the other bands'
    launches in flight have ended: the caller may then free what they read (a bricked volume's page table is reached
    only through its volume struct: freed under a running launch, the process crashed)."""
    rows, cols, out, counters = slow_rows(monkeypatch)
    running, launch = [0], wp.launch

    def counted(*args, **kwargs):
        running[0] += 1
        try:
            launch(*args, **kwargs)
            time.sleep(0.02)  # the launch's tail, where the race was
        finally:
            running[0] -= 1

    def abandon(_rows: int) -> None:
        raise RuntimeError("abandoned")

    monkeypatch.setattr(wp, "launch", counted)
    with pytest.raises(RuntimeError, match="abandoned"):
        launch_rows(slow_rows_kernel, rows, cols, [out, 20000], "cpu", counters, progress=abandon)
    assert running[0] == 0, f"{running[0]} launch(es) still running when launch_rows raised"


def test_a_bench_suite_reports_each_measured_case(capfd) -> None:
    from types import SimpleNamespace

    from volren.bench import measure
    from volren.progress import case_done, cases

    stats = SimpleNamespace(times_ms={"march": 2.0}, counters={"rays": 1})
    renderer = SimpleNamespace(name="dssrm", config=None,
                               render=lambda scene, views, frame=0: SimpleNamespace(stats=stats))
    view = SimpleNamespace(width=96, height=64)
    with cases("bench dssrm"):
        measure(renderer, None, [view, view], repeats=2)
        case_done("cmsrm, 1 view(s) of 96x64")
    case_done("outside any suite")  # says nothing
    assert capfd.readouterr().err.splitlines() == ["volren: bench dssrm: case 1 done (dssrm, 2 view(s) of 96x64), 0 s",
                                                   "volren: bench dssrm: case 2 done (cmsrm, 1 view(s) of 96x64), 0 s"]


@pytest.mark.parametrize(("name", "content", "cause"), [
    ("noise.usdc", np.random.default_rng(1).bytes(2000), "Sdf crate bootstrap section corrupt"),
    ("cut.usda", b'#usda 1.0\ndef Mesh "m" { int[] faceVertexCounts = [3\n', "parse error matching"),
    ("noise.stl", np.random.default_rng(2).bytes(2000), "noise.stl"),
])
def test_a_corrupt_mesh_is_one_line_naming_its_cause(capfd, tmp_path: Path, name: str, content: bytes,
                                                     cause: str) -> None:
    if name.startswith(("noise.usd", "cut.usd")):
        pytest.importorskip("pxr")
    path = tmp_path / name
    path.write_bytes(content)
    line = assert_error(capfd, ["render", *TINY, "--mesh", path, "--out", tmp_path / "out"], name, cause)
    assert "Error in" not in line and "pxrInternal" not in line and "charset" not in line


def test_the_cli_copies_of_fog_scene_names_and_the_pixel_cap_equal_their_sources() -> None:
    from volren import camera
    from volren.data.fog_scenes import FOG_SCENES
    from volren.plan import options

    assert tuple(FOG_SCENES) == options.FOG_SCENE_NAMES
    assert options.MAX_VIEW_PIXELS == camera.MAX_PIXELS


def test_ctrl_c_while_the_cli_imports_is_one_line(monkeypatch, capsys) -> None:
    """Issue 22.8: the console script catches a Ctrl-C that lands while `volren.cli` is still importing."""
    import types

    from volren import _entry

    class Interrupted(types.ModuleType):
        def __getattr__(self, name: str):  # only `main`: pytest's report looks up other attributes
            if name == "main":
                raise KeyboardInterrupt
            raise AttributeError(name)

    monkeypatch.setitem(sys.modules, "volren.cli", Interrupted("volren.cli"))
    with pytest.raises(SystemExit) as exit_:
        _entry.main()
    assert exit_.value.code == 130
    assert capsys.readouterr().err == "volren: interrupted\n"

"""Nothing hangs on Ray (issue 45 item 4), each run as a user runs it, in a fresh process: `--ray-address` where
nothing listens printed Ray's "Failed to connect" lines for minutes (with 127.0.0.1 turned into the machine's
address) and left `batch.json` in `--out`; SIGTERM to a `--workers` run exited 134 with Ray's native stack dump.
(A sweep's job limit: tests/test_batch_job.py; the connection's deadline: tests/test_ray_runtime.py.)"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

import volren

SMALL = ["--scene", "smoke", "--width", "32", "--height", "24", "--samples", "16", "--light-samples", "6",
         "--light-grid", "8", "--device", "cpu"]
STARTUP_S = 150.0
"""a local Ray start takes ~25 s on 2 idle cores; more beside the rest of the suite"""


def user_env() -> dict[str, str]:
    """This environment as a user's shell has it (no Ray settings), importing the volren under test from any
    working folder (a relative PYTHONPATH=src would not)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["PYTHONPATH"] = os.pathsep.join([str(Path(volren.__file__).resolve().parents[1]),
                                         *filter(None, [env.get("PYTHONPATH")])])
    return env


def free_port() -> int:
    """A port of this machine where nothing listens (bound, then released)."""
    with socket.socket() as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def alive(process: psutil.Process) -> bool:
    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def listing(folder: Path) -> dict[str, bytes] | None:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())} if folder.exists() else None


@pytest.mark.timeout(120)
@pytest.mark.parametrize("case", ["render-new-out", "render-out-with-files", "batch"])
def test_an_unreachable_ray_address_is_refused_in_seconds_and_out_is_left_as_it_was(case, tmp_path):
    address = f"127.0.0.1:{free_port()}"
    out = tmp_path / "out"
    if case == "batch":
        job = tmp_path / "job.toml"
        job.write_text(f'out = "{out}"\nscene = "smoke"\nwidth = 32\nheight = 24\nsamples = 16\nframes = 2\n'
                       '[sweep]\nlight-irradiance = [1, 2]\n')
        argv = ["batch", str(job), "--ray-address", address]
    else:
        argv = ["render", *SMALL, "--frames", "2", "--workers", "1", "--ray-address", address, "--out", str(out)]
    if case == "render-out-with-files":  # an earlier run's frame and manifest: a start would have removed them
        out.mkdir()
        (out / "frame0000_view0.png").write_bytes(b"an earlier frame")
        (out / "batch.json").write_text('{"version": 1, "settings": {}, "units": {}}\n')
        (out / "notes.txt").write_text("mine\n")
    before = listing(out)
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "volren.cli", *argv], cwd=tmp_path, env=user_env(),
                          capture_output=True, text=True, timeout=60)
    elapsed = time.monotonic() - started
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith(
        f"volren: error: --ray-address {address}: nothing answers at {address}"), lines
    assert lines[0].endswith("start a cluster with `ray start --head` or drop --ray-address"), lines
    assert elapsed < 15.0, elapsed
    assert listing(out) == before  # absent stays absent; the files there are untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["job.toml"] * (case == "batch") +
                                                                 ["out"] * (before is not None))


@pytest.mark.timeout(240)
@pytest.mark.xdist_group("ray")  # one Ray start at a time, beside the session cluster's tests
def test_sigterm_stops_a_workers_run_as_ctrl_c_does(tmp_path):
    """SIGTERM once the first unit is written: one line, exit 143 (128 + SIGTERM, as Ctrl-C's is 130), no native
    stack dump, and --out holds exactly the complete units batch.json lists; the local cluster's GCS, raylet and
    worker stop with it."""
    out = tmp_path / "r"
    proc = subprocess.Popen([sys.executable, "-m", "volren.cli", "render", *SMALL, "--frames", "40", "--workers", "1",
                             "--out", str(out)], cwd=tmp_path, env=user_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    root, tree, deadline = psutil.Process(proc.pid), {}, time.monotonic() + STARTUP_S
    try:
        while proc.poll() is None and time.monotonic() < deadline and not any(out.glob("frame0000_*")):
            for child in root.children(recursive=True):
                try:
                    tree.setdefault(child.pid, (child, child.name()))
                except psutil.NoSuchProcess:
                    continue
            time.sleep(0.1)
        assert proc.poll() is None and any(out.glob("frame0000_*")), proc.poll()
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        _, err = proc.communicate(timeout=60)
        stopped_in = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    assert err.strip().splitlines()[-1] == "volren: terminated", err[-3000:]
    for native in ("Fatal Python error", "Aborted", "core dumped", "SIGTERM received", "Traceback"):
        assert native not in err, err[-3000:]
    assert stopped_in < 10.0, stopped_in
    manifest = json.loads((out / "batch.json").read_text())
    units = manifest["units"]
    assert units and len(units) < 40, sorted(units)
    listed = {name: digest for unit in units.values() for name, digest in unit["files"].items()}
    assert sorted(p.name for p in out.iterdir()) == sorted([*listed, "batch.json"])  # no partial unit, no temp file
    assert all(hashlib.sha256((out / n).read_bytes()).hexdigest() == h for n, h in listed.items())
    per_frame = {len(u["files"]) // (u["frames"][1] - u["frames"][0]) for u in units.values()}
    assert len(per_frame) == 1, units  # every listed unit has all its views' files
    core = [(p, name) for p, name in tree.values() if name in ("gcs_server", "raylet") or name.startswith("ray::Unit")]
    assert {"gcs_server", "raylet"} <= {name for _, name in core}, sorted(n for _, n in tree.values())
    gone_by = time.monotonic() + 20.0
    while time.monotonic() < gone_by and any(alive(p) for p, _ in core):
        time.sleep(0.5)
    assert not [name for p, name in core if alive(p)]

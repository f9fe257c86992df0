"""Every front door that starts a local Ray cluster keeps it on loopback (issue 44 item 1, issue 47 item 6): `volren
render --workers`, `volren batch --workers` and `volren serve --shards`, each run as a user runs it, in a fresh
process, its process tree's listening sockets collected while it works. Ray reads its single-machine setting when it
is imported, and the shard and worker paths imported Ray (to check that it is installed) before the setting was made:
with `--shards 2` the GCS, the raylets, the shard workers and a socket of volren itself listened on every interface."""

from __future__ import annotations

import ipaddress
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

STARTUP_S = 150.0
"""a local Ray start takes ~25 s on 2 idle cores; more beside the rest of the suite"""


def loopback(ip: str) -> bool:
    address = ipaddress.ip_address(ip)
    return (getattr(address, "ipv4_mapped", None) or address).is_loopback  # ::ffff:127.0.0.1 too


def listening(root: psutil.Process) -> set[tuple[str, str, int]]:
    """(process name, address, port) of every listening inet socket of ``root`` and its descendants now."""
    found = set()
    for proc in [root, *root.children(recursive=True)]:
        try:
            name = proc.name()
            found |= {(name, c.laddr.ip, c.laddr.port) for c in proc.net_connections(kind="inet")
                      if c.status == psutil.CONN_LISTEN}
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return found


def watch(argv: list[str], done, tmp_path: Path) -> tuple[set, subprocess.Popen]:
    """Run ``volren argv`` and collect its tree's listening sockets until ``done(sockets)`` or it exits."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}  # as a user's shell has it
    proc = subprocess.Popen([sys.executable, "-m", "volren.cli", *argv], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    root, seen, deadline = psutil.Process(proc.pid), set(), time.monotonic() + STARTUP_S
    try:
        while proc.poll() is None and time.monotonic() < deadline and not done(seen):
            seen |= listening(root)
            time.sleep(0.2)
    except psutil.NoSuchProcess:
        pass
    return seen, proc


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timeout(240)
@pytest.mark.xdist_group("ray")  # one Ray start at a time, beside the session cluster's tests
@pytest.mark.parametrize("command", ["render --workers", "batch --workers", "serve --shards"])
def test_a_local_cluster_started_by_any_command_listens_on_loopback_only(command, tmp_path):
    small = ["--scene", "smoke", "--width", "32", "--height", "24", "--samples", "16", "--light-samples", "6",
             "--light-grid", "8", "--device", "cpu"]
    port = free_port()
    if command == "render --workers":
        argv = ["render", *small, "--frames", "4", "--workers", "2", "--out", str(tmp_path / "r")]
    elif command == "batch --workers":
        job = tmp_path / "job.toml"
        job.write_text(f'out = "{tmp_path / "b"}"\nscene = "smoke"\nwidth = 32\nheight = 24\nsamples = 16\n'
                       'light-samples = 6\nlight-grid = 8\nframes = 4\n[sweep]\nlight-irradiance = [1, 2]\n')
        argv = ["batch", str(job), "--workers", "2"]
    else:
        argv = ["serve", "--shards", "2", "--port", str(port), "--resolution", "64", "--device", "cpu"]

    def ray_up(seen) -> bool:  # the GCS, the raylet and the shard workers (or volren's page) are listening
        names = {name for name, *_ in seen}
        return "gcs_server" in names and "raylet" in names and (command != "serve --shards" or any(
            p == port for *_, p in seen))

    seen, proc = watch(argv, ray_up, tmp_path)
    try:
        if command == "serve --shards":
            assert ray_up(seen), (seen, proc.poll())
            proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, proc.stderr.read()[-2000:]
    assert {"gcs_server", "raylet"} <= {name for name, *_ in seen}, seen  # Ray's own listeners were checked
    exposed = sorted(s for s in seen if not loopback(s[1]))
    assert not exposed, exposed

"""`volren.distributed.runtime.connect`'s failure path, without Ray: a start that fails is cleaned up and tried
again (local), an address is tried once, and the error is one line naming the flag and Ray's reason."""

from __future__ import annotations

import ipaddress
import signal
import socket
import time
import types

import pytest

from volren.distributed import runtime
from volren.errors import VolrenError


class FailingRay:
    """A stand-in for the ray module whose init always fails."""

    def __init__(self) -> None:
        self.inits = 0
        self.shutdowns = 0

    def is_initialized(self) -> bool:
        return False

    def init(self, **kwargs) -> None:
        self.inits += 1
        raise RuntimeError("node did not come up\ntraceback lines Ray adds")

    def shutdown(self) -> None:
        self.shutdowns += 1


@pytest.mark.parametrize("address", [None, "10.0.0.9:6379"], ids=["local", "address"])
def test_failed_start_is_retried_cleaned_up_and_one_line(monkeypatch, address):
    fake = FailingRay()
    stopped = []
    monkeypatch.setattr(runtime, "import_ray", lambda flag, local=False: fake)
    monkeypatch.setattr(runtime, "stop_failed_start", stopped.append)
    monkeypatch.setattr(runtime, "check_address", lambda address: None)  # the address's check: tests below
    with pytest.raises(VolrenError) as err:
        runtime.connect("--workers" if address is None else "--ray-address", address, num_cpus=1)
    where = "a local Ray cluster" if address is None else f"the Ray cluster at {address}"
    flag = "--workers" if address is None else "--ray-address"
    assert str(err.value) == f"{flag}: cannot start or reach {where}: node did not come up"
    tries = runtime.LOCAL_STARTS if address is None else 1
    assert fake.inits == tries
    assert (len(stopped), fake.shutdowns) == ((tries, tries) if address is None else (0, 0))


@pytest.mark.xdist_group("ray")
def test_a_local_cluster_listens_on_loopback_only(ray_cluster):
    """Every listening socket of the local cluster (GCS, raylet, object manager, agents, workers: this process's
    descendants) and of this process is on loopback: a laptop on a café's network does not offer its Ray
    cluster to the room. Without Ray's single-machine setting they bind every interface (issue 47 item 6)."""
    import psutil

    me = psutil.Process()
    ray_cluster.get(ray_cluster.remote(lambda: 1).remote())  # a worker up, as a render's would be
    listening = []
    for proc in [me, *me.children(recursive=True)]:
        try:
            conns = proc.net_connections(kind="inet")
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        listening += [(proc.name(), c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN]
    assert len(listening) >= 3, listening  # the GCS, the raylet and more are there to be checked
    def loopback(ip: str) -> bool:
        address = ipaddress.ip_address(ip)
        return (getattr(address, "ipv4_mapped", None) or address).is_loopback  # ::ffff:127.0.0.1 too

    exposed = [s for s in listening if not loopback(s[1])]
    assert not exposed, exposed


def free_port() -> int:
    """A port of 127.0.0.1 where nothing listens (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timeout(60)
def test_an_address_where_nothing_listens_is_refused_in_seconds_before_ray_init(monkeypatch):
    """Issue 45 item 4: Ray would log "Failed to connect" for 20 x 30 s; the check refuses in `CHECK_S`, in one line
    naming --ray-address and what to do, and ray.init is never called."""
    fake = FailingRay()
    monkeypatch.setattr(runtime, "import_ray", lambda flag, local=False: fake)
    address = f"127.0.0.1:{free_port()}"
    started = time.monotonic()
    with pytest.raises(VolrenError) as err:
        runtime.connect("--workers", address, num_cpus=1)
    elapsed = time.monotonic() - started
    text = str(err.value)
    assert text.startswith(f"--ray-address {address}: nothing answers at {address}") and "\n" not in text, text
    assert f"within {runtime.CHECK_S:g} s" in text and "`ray start --head` or drop --ray-address" in text
    assert runtime.CHECK_S - 0.5 <= elapsed < runtime.CHECK_S + 2.0, elapsed  # retried, then refused
    assert fake.inits == 0


@pytest.mark.timeout(60)
def test_auto_without_a_cluster_to_find_is_one_line(monkeypatch):
    """'auto' resolves as Ray resolves it (its own function); nothing found (no RAY_ADDRESS, no cluster started
    here) is one line, at once."""

    def nothing(address, temp_dir=None):
        raise ConnectionError("Could not find any running Ray instance.")

    fake = FailingRay()
    fake._private = types.SimpleNamespace(services=types.SimpleNamespace(canonicalize_bootstrap_address=nothing))
    monkeypatch.setattr(runtime, "import_ray", lambda flag, local=False: fake)
    with pytest.raises(VolrenError) as err:
        runtime.connect("--workers", "auto")
    assert str(err.value) == ("--ray-address auto: no Ray cluster found (RAY_ADDRESS is unset and none was started on "
                              "this machine): start a cluster with `ray start --head` or drop --ray-address")
    assert fake.inits == 0


class SilentRay(FailingRay):
    """A ray.init that never gets an answer: like Ray's own connection loop, it retries every failure
    (``except Exception``) for a long while, in Python between tries."""

    GIVES_UP_S = 20.0

    def init(self, **kwargs) -> None:
        self.inits += 1
        ends = time.monotonic() + self.GIVES_UP_S
        while time.monotonic() < ends:
            try:
                time.sleep(0.05)
                raise RuntimeError("Timed out while waiting for GCS to become available.")
            except Exception:
                continue
        raise RuntimeError("gave up after 20 s")


@pytest.mark.timeout(60)
def test_ray_init_on_an_address_that_never_answers_is_cut_at_the_deadline(monkeypatch):
    """Something listens at the address but never answers (a half-open port, the dashboard's): ray.init is bounded
    by `INIT_TIMEOUT_S`, whose timeout Ray's retry loop cannot swallow, and what it set up is shut down."""
    fake = SilentRay()
    monkeypatch.setattr(runtime, "import_ray", lambda flag, local=False: fake)
    monkeypatch.setattr(runtime, "INIT_TIMEOUT_S", 0.5)
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        monkeypatch.setattr(runtime, "check_address", lambda address: None)  # Ray's resolution of 127.0.0.1 aside
        address = f"127.0.0.1:{listener.getsockname()[1]}"
        started = time.monotonic()
        with pytest.raises(VolrenError) as err:
            runtime.connect("--shards", address)
        elapsed = time.monotonic() - started
    assert str(err.value) == (f"--ray-address: cannot start or reach the Ray cluster at {address}: no answer within "
                              "0.5 s: is it a Ray cluster's GCS port (the address `ray start --head` prints)?")
    assert elapsed < 3.0, elapsed
    assert (fake.inits, fake.shutdowns) == (1, 1)
    assert signal.getsignal(runtime.WATCHDOG_SIGNAL) == signal.SIG_DFL  # the watchdog's handler put back

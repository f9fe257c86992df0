"""`volren.distributed.runtime.connect`'s failure path, without Ray: a start that fails is cleaned up and tried
again (local), an address is tried once, and the error is one line naming the flag and Ray's reason."""

from __future__ import annotations

import ipaddress

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

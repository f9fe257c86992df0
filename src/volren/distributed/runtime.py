"""Connecting to Ray: a local cluster started on demand (loopback only, no dashboard, no usage reporting) or an
existing one at ``--ray-address``. Every Ray entry point of volren goes through `connect`."""

from __future__ import annotations

import contextlib
import os
import time
from types import ModuleType

from volren.errors import VolrenError

RAY_MISSING = "Ray is not installed: pip install 'volren[ray]'"
LOOPBACK_ONLY = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
LOCAL_STARTS = 2
"""tries of a local start: on 2 busy cores Ray's raylet can give up waiting (15 s, fixed) for its agents' port files"""


def import_ray(flag: str, local: bool = False) -> ModuleType:
    """Ray, or a one-line error naming the flag that asked for it. ``local``: this process may start a local cluster,
    so Ray's single-machine mode is set first (Ray reads it when it is imported: the node's address is 127.0.0.1,
    and the GCS, raylet, agents and workers listen on loopback only; otherwise they bind every interface)."""
    if local:
        os.environ.setdefault(LOOPBACK_ONLY, "0")
    try:
        import ray
    except ImportError:
        raise VolrenError(f"{flag}: {RAY_MISSING}") from None
    return ray


def connect(flag: str, address: str | None = None, num_cpus: int | None = None,
            num_gpus: int | None = None) -> ModuleType:
    """Join the cluster at ``address``, or start a local one holding ``num_cpus`` CPUs (and ``num_gpus`` GPUs) bound
    to 127.0.0.1 with no dashboard. A process already connected (a test session's cluster, a second job in one
    Python session) keeps its connection."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no report sent home from a laptop or a cluster
    ray = import_ray(flag, local=not address)
    if ray.is_initialized():
        return ray
    options = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
    where = f"the Ray cluster at {address}" if address else "a local Ray cluster"
    failure = ""
    for _ in range(1 if address else LOCAL_STARTS):
        started = time.time()
        try:
            if address:
                ray.init(address=address, **options)
            else:
                ray.init(num_cpus=num_cpus, num_gpus=num_gpus, _node_ip_address="127.0.0.1", **options)
            return ray
        except Exception as exc:  # Exception too: Ray raises a bare one when its node does not come up in time
            failure = (str(exc).splitlines() or [type(exc).__name__])[0]
            if not address:
                stop_failed_start(started)
                ray.shutdown()
    raise VolrenError(f"{flag}: cannot start or reach {where}: {failure}")

def stop_failed_start(started: float) -> None:
    """Stop what a failed local start left running: Ray started its GCS, raylet, agents and workers as this process's
    descendants and leaves them behind when its node does not come up; each would add to the load that made it fail."""
    import psutil  # Ray's own copy (ray/thirdparty_files) when psutil is not installed

    for child in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error):
            if child.create_time() >= started - 1.0:  # create_time is rounded; nothing else forks during ray.init
                child.kill()


def shutdown_local(ray: ModuleType) -> None:
    """`ray.shutdown()` of a cluster this process started, its processes killed at once: Ray's own shutdown stops
    them one after the other, each sent SIGTERM and given up to 1 s (the raylet and the GCS take it), 1.35 s of
    `volren serve --shards 2`'s 2 s on 2 idle cores and more on busy ones (issue 44 item 6: SIGTERM took 3.3 s). The
    driver still disconnects first (killed before it, the disconnect waited 5 s on the dead GCS); then every process
    of the node and their descendants (the raylet's workers: the shards) get SIGKILL, and this process's own children
    are reaped. A cluster only joined has no processes here: the call is `ray.shutdown()`."""
    import psutil  # Ray's own copy (ray/thirdparty_files) when psutil is not installed

    node = getattr(getattr(getattr(ray, "_private", None), "worker", None), "_global_node", None)
    started = getattr(node, "all_processes", None)
    if not started or not hasattr(node, "kill_all_processes"):
        ray.shutdown()
        return

    def kill_all_processes(**_: object) -> None:
        popens = [info.process for infos in started.values() for info in infos]
        tree = []
        for p in popens:
            with contextlib.suppress(psutil.Error):
                tree += psutil.Process(p.pid).children(recursive=True)
        for proc in [*tree, *(psutil.Process(p.pid) for p in popens if p.poll() is None)]:
            with contextlib.suppress(psutil.Error):
                proc.kill()
        for p in popens:
            with contextlib.suppress(Exception):
                p.wait(timeout=1.0)

    node.kill_all_processes = kill_all_processes  # ray.shutdown calls it on the node once disconnected
    ray.shutdown()

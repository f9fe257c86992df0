"""Connecting to Ray: a local cluster started on demand (loopback only, no dashboard, no usage reporting) or an
existing one at ``--ray-address``. Every Ray entry point of volren goes through `connect`.

Nothing hangs (issue 45 item 4): an address where nothing listens is refused in seconds with one line
(`check_address`, which the engine also calls before it touches --out), where Ray would log "Failed to connect" for
minutes; ``ray.init`` on an address that answers is bounded too (`INIT_TIMEOUT_S`); and SIGTERM ends a run on Ray as
Ctrl-C does (`terminate_like_ctrl_c`, at its start and again after ``ray.init``, which replaces the handler), where
Ray's native handler dumped a stack and aborted (exit 134)."""

from __future__ import annotations

import _thread
import contextlib
import os
import signal
import socket
import threading
import time
from collections.abc import Iterator
from types import ModuleType

from volren.errors import Terminated, VolrenError

RAY_MISSING = "Ray is not installed: pip install 'volren[ray]'"
LOOPBACK_ONLY = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
LOCAL_STARTS = 2
"""tries of a local start: on 2 busy cores Ray's raylet can give up waiting (15 s, fixed) for its agents' port files"""
CHECK_S = 3.0
"""[s] `check_address` tries to open a TCP connection to the cluster's GCS port for this long (a refused try is
repeated every `CHECK_RETRY_S`: a head that is starting gets these seconds to listen); with Ray's import and the
checks, an address where nothing listens is refused within about 10 s. Ray itself would retry for 20 x 30 s."""
CHECK_RETRY_S = 0.25
INIT_TIMEOUT_S = 30.0
"""[s] ``ray.init`` on an address that took a connection (a GCS; or something else listening there, such as the
dashboard's port 8265, or a cluster too loaded to answer): past this it is refused. The watchdog acts when Ray's code
next checks for signals, which its GCS client does when its own wait for the cluster's id ends (40 s, then it tries
again for ever): an address that listens but does not answer is refused after ~40 s. A healthy cluster answers in a
second or two."""
WATCHDOG_SIGNAL = signal.SIGUSR1
"""the signal whose Python handler `deadline` trips (Ray and Warp use none of SIGUSR1's)"""
ADDRESS_HINT = "start a cluster with `ray start --head` or drop --ray-address"


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
    if address:
        check_address(address)
    failure = ""
    for _ in range(1 if address else LOCAL_STARTS):
        started = time.time()
        try:
            if address:
                with deadline(INIT_TIMEOUT_S):
                    ray.init(address=address, **options)
            else:
                ray.init(num_cpus=num_cpus, num_gpus=num_gpus, _node_ip_address="127.0.0.1", **options)
            terminate_like_ctrl_c()
            return ray
        except SystemExit:  # SIGTERM during ray.init: Ray's handlers (its only sys.exit there) stopped its processes
            raise Terminated from None
        except (Exception, InitTimeout) as exc:  # Exception too: Ray raises a bare one when its node does not come up
            failure = (str(exc).splitlines() or [type(exc).__name__])[0]
            if not address:
                stop_failed_start(started)
            if not address or isinstance(exc, InitTimeout):
                with contextlib.suppress(Exception):  # what a connection cut short set up
                    ray.shutdown()
    raise VolrenError(f"{'--ray-address' if address else flag}: cannot start or reach {where}: {failure}")


def check_address(address: str) -> None:
    """Refuse, with one line naming ``--ray-address ADDR``, an address where no cluster can be found or nothing
    accepts a TCP connection within `CHECK_S`: the address Ray itself would connect to ('auto': ``RAY_ADDRESS`` or
    the cluster this machine started last; Ray turns 127.0.0.1 into this machine's address unless it runs loopback
    only), so that what passes here is what ``ray.init`` meets. Called before anything is written into --out."""
    ray = import_ray("--ray-address")
    named = f"--ray-address {address}"
    target = address.split("://", 1)[1] if "://" in address else address  # ray://host:port: Ray's client server
    if "://" not in address:
        services = getattr(getattr(ray, "_private", None), "services", None)  # another Ray: what was given
        canonicalize = getattr(services, "canonicalize_bootstrap_address", None)
        if canonicalize is not None:
            try:
                target = canonicalize(address) or address
            except ConnectionError:  # 'auto' and nothing to find
                raise VolrenError(f"{named}: no Ray cluster found (RAY_ADDRESS is unset and none was started on this "
                                  f"machine): {ADDRESS_HINT}") from None
            except ValueError:
                raise VolrenError(f"{named}: not host:port or 'auto'") from None
    host, _, port = target.rpartition(":")
    if target in ("auto", "local"):  # another Ray, which keeps its search to itself (INIT_TIMEOUT_S bounds it)
        return
    if not host or not port.isdigit():
        raise VolrenError(f"{named}: not host:port or 'auto'")
    ends = time.monotonic() + CHECK_S
    while True:
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=max(ends - time.monotonic(), 0.5)):
                return
        except OSError as exc:
            reason = exc.strerror or type(exc).__name__
        if time.monotonic() + CHECK_RETRY_S >= ends:
            break
        time.sleep(CHECK_RETRY_S)
    resolved = f" ({target}, as Ray resolves it)" if target != address else ""
    raise VolrenError(f"{named}: nothing answers at {address}{resolved} within {CHECK_S:g} s ({reason}): "
                      f"{ADDRESS_HINT}")


class InitTimeout(BaseException):
    """`INIT_TIMEOUT_S` passed in ``ray.init`` (a BaseException: Ray's connection loop catches Exception and tries
    again)."""

    def __str__(self) -> str:
        return (f"no answer within {INIT_TIMEOUT_S:g} s: is it a Ray cluster's GCS port (the address `ray start "
                "--head` prints)?")


@contextlib.contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Raise `InitTimeout` in the block after ``seconds``: a timer thread trips `WATCHDOG_SIGNAL`'s Python handler
    (no signal is sent, and no process timer is touched: SIGALRM's may be in use, pytest-timeout's for one). It takes
    effect when the block's native code next checks for signals or returns to Python; in the main thread only,
    where signal handlers run: elsewhere the block is not bounded."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    expired = threading.Event()

    def expire(signum, frame):
        if expired.is_set():
            raise InitTimeout

    def ring() -> None:
        expired.set()
        _thread.interrupt_main(WATCHDOG_SIGNAL)

    previous = signal.signal(WATCHDOG_SIGNAL, expire)
    timer = threading.Timer(seconds, ring)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        timer.join()  # a Python call: a handler tripped meanwhile runs here, before the handler is put back
        signal.signal(WATCHDOG_SIGNAL, previous)


def terminate_like_ctrl_c() -> None:
    """From now on SIGTERM raises `Terminated` (a KeyboardInterrupt) in the main thread, as Ctrl-C does: the run stops
    the way Ctrl-C stops it (the engine keeps complete units, the CLI says one line and exits 143). ``ray.init``
    replaced the handler: Ray's core worker's native one printed a stack and aborted (exit 134)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminated)


def _terminated(signum, frame):
    raise Terminated


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

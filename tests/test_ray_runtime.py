"""`volren.distributed.runtime.connect`'s failure path, without Ray: a start that fails is cleaned up and tried
again (local), an address is tried once, and the error is one line naming the flag and Ray's reason."""

from __future__ import annotations

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
    monkeypatch.setattr(runtime, "import_ray", lambda flag: fake)
    monkeypatch.setattr(runtime, "stop_failed_start", stopped.append)
    with pytest.raises(VolrenError) as err:
        runtime.connect("--workers" if address is None else "--ray-address", address, num_cpus=1)
    where = "a local Ray cluster" if address is None else f"the Ray cluster at {address}"
    flag = "--workers" if address is None else "--ray-address"
    assert str(err.value) == f"{flag}: cannot start or reach {where}: node did not come up"
    tries = runtime.LOCAL_STARTS if address is None else 1
    assert fake.inits == tries
    assert (len(stopped), fake.shutdowns) == ((tries, tries) if address is None else (0, 0))

"""The simulated autopilots' UDP endpoints: each its own port, so no drone's poses reach another's."""

from __future__ import annotations

import resource

import pytest

from atlas_onboard.sim.autopilot import SimAutopilot


def test_endpoints_bound_to_port_zero_never_share_a_port():
    # With SO_REUSEADDR on UDP, Linux hands the same "free" port to several sockets bound to port 0
    # (about 11 collisions in 800 here), and the last one bound receives the others' datagrams.
    n = 800
    if resource.getrlimit(resource.RLIMIT_NOFILE)[0] < n + 100:
        pytest.skip("too few file descriptors for the check")
    aps = [SimAutopilot(system_id=1 + k % 250) for k in range(n)]
    try:
        ports = [a.port for a in aps]
        assert len(set(ports)) == n
    finally:
        for a in aps:
            a._sock.close()


def test_recording_holds_the_cyclic_collector_off_and_restores_it():
    import gc

    from atlas_onboard.sim.autopilot import recording

    runs: list[int] = []

    def seen(phase: str, info: dict) -> None:
        if phase == "start":
            runs.append(info["generation"])

    gc.callbacks.append(seen)
    try:
        assert gc.isenabled()
        with pytest.raises(RuntimeError), recording():
            assert not gc.isenabled()
            runs.clear()
            kept = [[] for _ in range(20 * gc.get_threshold()[0])]  # enough to start many collections
            assert runs == [] and len(kept) > 0
            raise RuntimeError
        assert gc.isenabled()  # restored, also when the block raised
        more = [[] for _ in range(20 * gc.get_threshold()[0])]
        assert runs and len(more) > 0  # the same allocations start collections again
        gc.disable()
        try:
            with recording():
                pass
            assert not gc.isenabled()  # it was off before: it stays off
        finally:
            gc.enable()
    finally:
        gc.callbacks.remove(seen)

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

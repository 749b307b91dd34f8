"""The simulator end to end: real node processes, rendered cameras, simulated autopilots, loopback
MAVLink; accuracy against ground truth per scenario, and nothing left behind afterwards."""

import os
import socket

import pytest

from atlas_onboard.sim.command import score_run
from atlas_onboard.sim.runner import SimOptions, run


def run_and_score(scenario, duration, **kw):
    sim = run(SimOptions(scenario=scenario, duration_s=duration, **kw))
    rep, _tracks = score_run(sim)
    assert all(code == 0 for code in sim.exit_codes.values()), sim.exit_codes
    for pid in sim.pids:  # every node process has ended
        assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"
    for port in sim.ports:  # and released its sockets: the ports can be bound again
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", port))
    return {e.entity: e for e in rep.entities}, rep


def test_paper_test1_self_localization():
    e, rep = run_and_score("paper-test1", 8)
    drone = e["ardrone"]
    print(rep.table())
    assert drone.rmse_m <= 0.02, f"RMSE {drone.rmse_m:.4f} m"
    assert drone.attitude_rmse_deg <= 1.0
    assert drone.availability >= 0.9 and drone.messages >= 100


def test_paper_test2_entity_localization():
    e, rep = run_and_score("paper-test2", 6)
    print(rep.table())
    tag = e["tag"]
    assert tag.source == "fused" and tag.messages >= 20
    assert tag.rmse_m <= 0.05, f"tag RMSE {tag.rmse_m:.4f} m"


def test_relay_localizes_a_drone_that_sees_no_world_marker():
    e, rep = run_and_score("relay", 10)
    print(rep.table())
    c = e["drone_c"]
    assert c.availability >= 0.95, f"availability {c.availability:.3f}"
    assert c.rmse_m <= 0.10, f"RMSE {c.rmse_m:.4f} m"


def test_swarm_each_drone_within_its_expected_availability():
    e, rep = run_and_score("swarm", 8)
    print(rep.table())
    for name in ("d1", "d2", "d3", "d4", "d5", "d6"):
        d = e[name]
        # 10 Hz cameras scored in 100 ms bins: a dropped frame empties a bin, hence the 0.1 margin.
        assert d.availability >= d.expected_availability - 0.1, (name, d.availability, d.expected_availability)
        # Never more available than geometry allows, beyond the 250 ms an edge lives.
        assert d.availability <= d.expected_availability + 0.1, (name, d.availability, d.expected_availability)
        if d.messages:
            assert d.rmse_m <= 0.05, (name, d.rmse_m)


def test_no_stale_output_when_a_relay_drone_dies(tmp_path):
    pytest.skip("fault injection in the simulator is not built yet")

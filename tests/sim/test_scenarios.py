"""The scenarios, checked on geometry alone (no node runs): the detection gaps of
``gaps`` and the two paths of ``paths`` are where they are meant to be."""

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.world import SimWorld


def test_occlusions_last_a_tenth_to_six_tenths_of_a_second_and_blank_the_camera():
    sc = scenarios.get("gaps")
    (occ,) = sc.occlusions
    iv = occ.intervals()
    length = iv[:, 1] - iv[:, 0]
    assert length.min() >= 0.1 and length.max() <= 0.6
    assert np.all(iv[1:, 0] - iv[:-1, 1] >= 0.6)  # clear time between gaps
    world = SimWorld(sc)
    sid = next(iter(world.cameras))
    inside = [t for t in np.arange(1.0, 12.0, 0.05) if sc.occluded("drone", "down", t)]
    outside = [t for t in np.arange(1.0, 12.0, 0.05) if not sc.occluded("drone", "down", t)]
    assert all(world.sightings(sid, world.truth(t), t) == [] for t in inside)
    # Without a time the geometry alone decides, and it sees tags at most of those instants.
    assert sum(bool(world.sightings(sid, world.truth(t))) for t in inside) > 0.5 * len(inside)
    assert sum(bool(world.sightings(sid, world.truth(t), t)) for t in outside) > 0.5 * len(outside)


def test_gaps_expected_availability_counts_the_occlusions_and_the_tags_leaving_the_view():
    sc = scenarios.get("gaps")
    # Poses at most 0.1 s old (a 15 Hz camera's every frame): the shortest gaps count too.
    with_occlusions = SimWorld(sc).expected_availability(1.0, 12.0, fresh_s=0.1)["drone"]
    no_occlusions = SimWorld(dataclasses.replace(sc, occlusions=()))
    geometry_only = no_occlusions.expected_availability(1.0, 12.0, fresh_s=0.1)["drone"]
    assert with_occlusions < geometry_only < 1.0
    assert 0.5 < with_occlusions < 0.9


def test_paths_gives_the_lead_a_direct_edge_and_a_chain_through_the_wing():
    world = SimWorld(scenarios.get("paths"))
    for t in np.arange(0.0, 16.0, 0.5):
        edges = set(world.observed_edges(float(t)))
        assert (("lead", WORLD) in edges) and ((WORLD, "wing") in edges) and (("wing", "lead") in edges), t
        assert (WORLD, "lead") not in edges  # the ceiling camera never sees the lead's tag


def test_the_first_test_of_all_markers_at_once_keeps_every_marker_seen():
    """``sightings`` tests one by one only the markers its vectorized first test keeps: over every
    scenario's cameras at many instants, the result is the same as testing every marker."""
    seen, kept, others = 0, 0, 0
    for name in scenarios.SCENARIOS:
        sim, sim_all = SimWorld(scenarios.get(name)), SimWorld(scenarios.get(name))
        first = sim._maybe_in_view

        def counted(sid, own, M, truth, *rest, first=first, sim=sim):
            nonlocal kept, others
            k = first(sid, own, M, truth, *rest)
            kept += len(k)
            others += sum(m.entity != own for m, _, _ in sim._markers)
            return k

        sim._maybe_in_view = counted  # type: ignore[method-assign]
        sim_all._maybe_in_view = lambda _sid, own, *_, s=sim_all: [  # type: ignore[method-assign]
            k for k, (m, _, _) in enumerate(s._markers) if m.entity != own
        ]
        for t in np.linspace(0.0, 20.0, 31):
            truth = sim.truth(float(t))
            for sid in sim.cameras:
                got = sim.sightings(sid, truth, float(t))
                want = sim_all.sightings(sid, truth, float(t))
                assert [(s.marker.id, s.distance_m) for s in got] == [(s.marker.id, s.distance_m) for s in want]
                for a, b in zip(got, want, strict=True):
                    np.testing.assert_array_equal(a.corners_px, b.corners_px)
                    np.testing.assert_array_equal(a.M_sensor_marker, b.M_sensor_marker)
                seen += len(got)
    # Not vacuous: markers were seen, and the first test dropped most of the others (out of view).
    assert seen > 300 and kept < others / 2, (seen, kept, others)


def test_relay_ages_its_edges_at_its_drones_own_speed_and_turn_rate():
    """The relay's followers rest on their leaders' poses, whose edges are up to a frame old: the world
    file's ageing rates must be the drones' real ones (between half and 1.5 times the largest RMS
    per-axis speed and turn rate of its drones, from their trajectories), or the 6x6 covariance the
    followers publish is too sure of the attitude (no attitude ageing) or too cautious (1 m/s)."""
    scenario = scenarios.get("relay")
    world = SimWorld(scenario)
    fusion = scenario.world().fusion
    t = np.arange(1.0, 12.0, 0.01)
    speed, turn = 0.0, 0.0
    for name in scenario.drones:
        p, q = world.truth_series(name, t)
        R = Rotation.from_quat(q)
        v = np.diff(p, axis=0) / 0.01
        w = (R[:-1].inv() * R[1:]).as_rotvec() / 0.01
        speed = max(speed, float(np.sqrt(np.mean(v**2, axis=0)).max()))
        turn = max(turn, float(np.degrees(np.sqrt(np.mean(w**2, axis=0)).max())))
    assert 0.5 * speed <= fusion.age_sigma_m_per_s <= 1.5 * speed, (fusion.age_sigma_m_per_s, speed)
    assert 0.5 * turn <= fusion.age_sigma_deg_per_s <= 1.5 * turn, (fusion.age_sigma_deg_per_s, turn)


def test_node_overrides_reach_every_node_of_a_run(tmp_path):
    """``nodes`` in a run's world overrides are settings of every node (e.g. live map refinement on),
    merged into the generated ``nodes.defaults`` without losing its peer link."""
    from atlas_onboard.config import load_node
    from atlas_onboard.sim.runner import build_run_config

    scenario = scenarios.get("hard-near")
    ports = {name: 14550 + k for k, name in enumerate(scenario.drones)}
    overrides = {"nodes": {"refine": {"per_marker_period_s": 1.0}}, "fusion": {"filter": "ekf"}}
    path = build_run_config(scenario, tmp_path, 14600, ports, overrides)
    world, node = load_node(path, scenario.drones[0])
    assert node.refine is not None and node.refine.per_marker_period_s == 1.0
    assert [p.url for p in node.peers] == ["udpout:127.0.0.1:14600"]
    assert world.fusion.filter == "ekf"
    (tmp_path / "plain").mkdir()
    _, plain = load_node(build_run_config(scenario, tmp_path / "plain", 14600, ports), scenario.drones[0])
    assert plain.refine is None

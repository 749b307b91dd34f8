"""The scenarios built for issue 7, checked on geometry alone (no node runs): the detection gaps of
``gaps`` and the two paths of ``paths`` are where they are meant to be."""

import dataclasses

import numpy as np

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

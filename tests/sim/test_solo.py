"""What a solo node's peers are told (:mod:`atlas_onboard.sim.solo`): a view forged as if its drone stood
elsewhere. The solo node itself, with its autopilot's attitude and its peers played, runs end to end
in tests/e2e/test_trust.py."""

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import load_world
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.peerplay import LEADER, LEADER_SENSOR
from atlas_onboard.sim.solo import forged_view
from atlas_onboard.sim.world import SimWorld

MARKER = 3  # a floor tag


def _seen_from_the_true_pose(offset_m, t_s=2.0):
    """The forged view's marker, placed in the world through the observer's true pose, and the truth."""
    scenario = scenarios.get("relay")
    world = load_world(scenario.world_path())
    sim_world = SimWorld(scenario, world)
    md = forged_view(world, sim_world, LEADER, LEADER_SENSOR, MARKER, t_s, offset_m, 0.002, 123)
    w, x, y, z = md.q_sensor_marker_wxyz
    T_sensor_marker = RigidTransform.from_components(md.p_sensor_marker_m, Rotation.from_quat([x, y, z, w]))
    truth = sim_world.truth(t_s)
    sensor, marker = world.sensors[LEADER_SENSOR], world.markers[MARKER]
    seen = truth[LEADER] * sensor.T_entity_sensor * T_sensor_marker
    return md, seen, truth[marker.entity] * marker.T_entity_marker


def test_an_honest_view_is_the_truth():
    md, seen, true = _seen_from_the_true_pose((0.0, 0.0, 0.0))
    np.testing.assert_allclose(seen.translation, true.translation, atol=1e-9)
    assert (seen.rotation.inv() * true.rotation).magnitude() < 1e-9
    assert md.sigma_m == 0.002 and md.capture_time_us == 123


def test_a_view_forged_as_if_its_drone_stood_off_puts_the_marker_off_by_the_opposite():
    offset = np.array([2.0, -0.5, 0.25])
    _, seen, true = _seen_from_the_true_pose(tuple(offset))
    np.testing.assert_allclose(seen.translation, true.translation - offset, atol=1e-9)
    assert (seen.rotation.inv() * true.rotation).magnitude() < 1e-9

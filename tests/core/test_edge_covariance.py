"""A record whose sigma contradicts its own covariance is refused and counted: the graph would gate
it by one and weigh it by the other."""

from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core import covariance
from atlas_onboard.core.edge_covariance import SIGMA_COVARIANCE_TOLERANCE
from atlas_onboard.core.markerdata import MarkerData, Rejection, matrix_to_upper
from atlas_onboard.listener import Listener
from atlas_onboard.node.setup import make_graph
from tests.helpers import world_from

WORLD = {
    "entities": {
        "world": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0.5, 0, 0]}}]},
        "drone": {"sensors": [{"name": "down", "id": 1, "pose": {"pos": [0.1, 0, 0], "rpy_deg": [0, 90, 0]}}]},
    }
}


def _listener():
    world = world_from(WORLD)
    graph = make_graph(world)
    return graph, Listener(world, graph)


def _camera_spread(p, q_wxyz, C):
    R = Rotation.from_quat(np.roll(q_wxyz, -1)).as_matrix()
    J = np.hstack([-R.T, -covariance.skew(R.T @ p)])
    return float(np.sqrt(np.linalg.eigvalsh(J @ C @ J.T)[-1]))


def _record(sigma, C, p=(0.05, -0.1, 1.4), q=(0.98, 0.1, -0.1, 0.12)):
    q = tuple(np.asarray(q) / np.linalg.norm(q))
    return MarkerData(1, 5, sigma, p, q, 1000, covariance=matrix_to_upper(C))


def test_a_tiny_sigma_with_a_huge_covariance_and_the_reverse_are_refused_and_counted():
    graph, listener = _listener()
    huge = np.diag([400.0, 400.0, 400.0, 1.0, 1.0, 1.0])
    tiny = np.diag([1e-8, 1e-8, 1e-8, 1e-8, 1e-8, 1e-8])
    honest = np.diag([1e-6, 1e-6, 4e-6, 1e-5, 1e-5, 1e-6])
    spread = _camera_spread(np.array([0.05, -0.1, 1.4]), np.array([0.98, 0.1, -0.1, 0.12]) / 1.0, honest)
    reasons = listener.accept_many([(_record(1e-4, huge), 0), (_record(5.0, tiny), 0), (_record(spread, honest), 0)])
    assert reasons == [Rejection.INCONSISTENT_SIGMA, Rejection.INCONSISTENT_SIGMA, None]
    assert listener.rejected[Rejection.INCONSISTENT_SIGMA] == 2 and listener.accepted == 1
    assert set(graph.edges) == {(1, 5)}


@settings(max_examples=80, deadline=None)
@given(
    log_ratio=st.floats(-6.0, 6.0),
    rpy=st.tuples(st.floats(-60, 60), st.floats(-60, 60), st.floats(-180, 180)),
    depth=st.floats(0.3, 6.0),
    att_deg=st.floats(0.05, 5.0),
)
def test_a_record_is_refused_exactly_when_its_sigma_is_beyond_the_tolerance_of_its_covariance(
    log_ratio, rpy, depth, att_deg
):
    """The rule on any pose and covariance: sigma over the camera position spread the covariance
    implies (the detector's own definition of sigma) within [1/tolerance, tolerance]."""
    _, listener = _listener()
    q_xyzw = Rotation.from_euler("xyz", rpy, degrees=True).as_quat()
    q = (q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2])
    p = (0.1, -0.05, depth)
    C = np.diag([1e-6, 1e-6, 1e-5] + [np.radians(att_deg) ** 2] * 3)
    spread = _camera_spread(np.array(p), np.array(q), C)
    ratio = float(np.exp(log_ratio))
    if abs(abs(log_ratio) - np.log(SIGMA_COVARIANCE_TOLERANCE)) < 1e-6:
        return
    md = _record(min(spread * ratio, 99.0), C, p, q)
    reason = listener.accept(md, 0)
    expect = (
        Rejection.INCONSISTENT_SIGMA if abs(np.log(md.sigma_m / spread)) > np.log(SIGMA_COVARIANCE_TOLERANCE) else None
    )
    assert reason is expect


def test_a_record_without_a_covariance_has_nothing_to_contradict():
    _, listener = _listener()
    md = replace(_record(1e-4, np.eye(6)), covariance=())
    assert listener.accept(md, 0) is None

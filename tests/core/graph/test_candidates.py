"""A stage's candidates (eq. 2): each its parent's pose times an edge, with its sigma, time and covariance."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.graph.candidates import PoseOptions, StageEdges, Vertices, compose, weigh_sigma

positions = st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3).map(np.array)
rotations = st.integers(0, 2**32 - 1).map(lambda seed: Rotation.random(random_state=seed))
sigmas = st.floats(1e-3, 0.5)
stamps = st.integers(0, 10**9)


def _edge(p, R, sigma, capture_us, parent=1, child=2):
    cov = np.diag([sigma**2] * 3 + [1e-4] * 3)[None]
    return StageEdges(np.array([0]), np.array([parent]), np.array([child]), p[None], R.as_quat()[None],
                      np.array([sigma]), cov, np.array([capture_us], dtype=np.int64))  # fmt: skip


@settings(max_examples=50)
@given(positions, rotations, sigmas, stamps, positions, rotations, sigmas, stamps)
def test_a_candidate_is_its_parent_s_pose_times_the_edge(p_par, R_par, s_par, t_par, p_pc, R_pc, s_edge, t_edge):
    vx = Vertices.at_root(3)
    vx.p[1], vx.q[1], vx.sigma[1], vx.stamp_us[1] = p_par, R_par.as_quat(), s_par, t_par
    vx.cov[1] = np.diag([s_par**2] * 3 + [1e-4] * 3)
    c = compose(vx, _edge(p_pc, R_pc, s_edge, t_edge), from_root=False)
    expected = RigidTransform.from_components(p_par, R_par) * RigidTransform.from_components(p_pc, R_pc)
    np.testing.assert_allclose(c.p[0], expected.translation, atol=1e-9)
    assert Rotation.from_quat(c.q[0]).approx_equal(expected.rotation, atol=1e-9)
    assert np.isclose(c.s[0], np.hypot(s_edge, s_par))  # variances add along the chain
    assert c.capture_us[0] == max(t_par, t_edge)  # as new as its newest part
    full = c.covariance(vx.cov)[0]
    np.testing.assert_allclose(full, full.T, atol=1e-12)
    assert np.linalg.eigvalsh(full)[0] > 0.0
    # the parent's position uncertainty carries into the candidate's: never below either part's
    assert np.trace(full[:3, :3]) >= 3 * s_par**2 * (1 - 1e-9)


@given(positions, rotations, sigmas, stamps)
def test_from_the_root_a_candidate_is_the_edge_itself(p_pc, R_pc, s_edge, t_edge):
    vx = Vertices.at_root(3)
    e = _edge(p_pc, R_pc, s_edge, t_edge, parent=0, child=1)
    c = compose(vx, e, from_root=True)
    assert c.Jp is None  # the root is exact: no parent term
    np.testing.assert_array_equal(c.p[0], p_pc)
    np.testing.assert_array_equal(c.covariance(None), e.cov)
    assert c.s[0] == s_edge and c.capture_us[0] == t_edge


def test_candidates_are_weighed_by_the_edge_s_sigma_or_with_dijkstra_by_the_chain_s():
    vx = Vertices.at_root(3)
    vx.sigma[1] = 0.3
    c = compose(vx, _edge(np.ones(3), Rotation.identity(), 0.04, 0), from_root=False)
    assert weigh_sigma(PoseOptions(), c, vx)[0] == 0.04  # the paper: the sensor's sigma
    assert np.isclose(weigh_sigma(PoseOptions(path="dijkstra"), c, vx)[0], np.hypot(0.04, 0.3))

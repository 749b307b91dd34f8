"""The pose phase: eq. 2 and 4-7 against ground truth and the paper's weights."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.graph import TransformGraph
from tests.core.graph.builders import MS, add
from tests.helpers import assert_pose_close, pose


def test_pose_phase_fuses_candidates_with_paper_weights():
    g = TransformGraph(["world", "A"], 250 * MS)
    add(g, (1, 1), "world", "A", pose([0, 0, 0]), sigma=0.01)
    add(g, (1, 2), "world", "A", pose([0.3, 0, 0]), sigma=0.02)  # weight 0.5
    add(g, (2, 1), "A", "world", pose([0, -0.6, 0]), sigma=0.04)  # A sees world: T_world_A = (0, 0.6, 0), weight 0.25
    result = g.evaluate(0)
    a = result.poses["A"]
    np.testing.assert_allclose(a.p_world_m, [0.15 / 1.75, 0.15 / 1.75, 0], atol=1e-12)
    assert a.n_observations == 3
    expected_sigma = np.sqrt((1 * 0.01) ** 2 + (0.5 * 0.02) ** 2 + (0.25 * 0.04) ** 2) / 1.75
    assert a.sigma_m == pytest.approx(expected_sigma)


def test_inverse_variance_option_changes_weights():
    g = TransformGraph(["world", "A"], 250 * MS, inverse_variance=True)
    add(g, (1, 1), "world", "A", pose([0, 0, 0]), sigma=0.01)
    add(g, (1, 2), "world", "A", pose([0.5, 0, 0]), sigma=0.02)  # weight 0.25
    np.testing.assert_allclose(g.evaluate(0).poses["A"].p_world_m, [0.1, 0, 0], atol=1e-12)


def test_inverse_variance_weighs_by_the_candidates_covariances():
    """Beyond the paper: with inverse_variance, a candidate's weight is its propagated position
    variance, not its sigma: two views with the same sigma, one placed 3 times more precisely (a
    ceiling camera's view of a tag), weigh 9 : 1; the paper's sigma_min weighting gives 1 : 1."""
    from atlas_onboard.core import covariance

    got = {}
    for inverse in (False, True):
        g = TransformGraph(["world", "A"], 250 * MS, inverse_variance=inverse)
        for key, x, s_p in (((1, 1), 0.0, 0.001), ((1, 2), 1.0, 0.003)):
            T = pose([x, 0, 0])
            C = covariance.diagonal(s_p, 0.01)
            g.update_edge(key, "world", "A", T.translation, T.rotation.as_quat(), 0.01, 0, 0, cov_a_b=C)
        got[inverse] = g.evaluate(0).poses["A"].p_world_m
    np.testing.assert_allclose(got[False], [0.5, 0, 0], atol=1e-12)
    np.testing.assert_allclose(got[True], [0.1, 0, 0], atol=1e-12)


def test_relay_through_another_drone():
    # The paper's Figure 1: B sees no world marker; A sees the world and B.
    truth = {"world": RigidTransform.identity(), "A": pose([1, 1, 2], [0, 10, 45]), "B": pose([3, 0, 1.5], [0, 0, 180])}
    g = TransformGraph(["world", "A", "B"], 250 * MS)
    add(g, (1, 1), "A", "world", truth["A"].inv(), sigma=0.01, capture_us=100)
    add(g, (1, 7), "A", "B", truth["A"].inv() * truth["B"], sigma=0.03, capture_us=250)
    result = g.evaluate(0)
    b = result.poses["B"]
    assert b.level == 2
    assert_pose_close(b.p_world_m, b.q_world_xyzw, truth["B"], 1e-12, 1e-12)
    assert b.sigma_m == pytest.approx(np.hypot(0.01, 0.03))  # the chain's uncertainty adds up
    assert b.capture_time_us == 250
    assert result.poses["A"].capture_time_us == 100


def test_world_has_identity_pose_and_level_zero():
    g = TransformGraph(["A"], 250 * MS)
    result = g.evaluate(0)
    w = result.poses["world"]
    assert w.level == 0 and w.order == 0
    np.testing.assert_array_equal(w.p_world_m, [0, 0, 0])
    assert result.unreached == ("A",)


poses_st = st.tuples(
    st.lists(st.floats(-10, 10), min_size=3, max_size=3),
    st.lists(st.floats(-179, 179), min_size=3, max_size=3).map(lambda a: [a[0], a[1] / 2.1, a[2]]),
)


@settings(max_examples=60, deadline=None)
@given(st.lists(poses_st, min_size=4, max_size=4), st.integers(0, 2**16))
def test_same_pose_whatever_path(truth_list, seed):
    """Exact edges: every entity's pose equals the truth whichever edges the graph happens to use."""
    names = ["world", "A", "B", "C", "D"]
    truth = {"world": RigidTransform.identity()}
    truth.update({n: pose(p, r) for n, (p, r) in zip(names[1:], truth_list, strict=True)})
    rng = np.random.default_rng(seed)
    g = TransformGraph(names, 250 * MS)
    pairs = [("world", "A"), ("A", "B"), ("B", "C"), ("C", "D")]  # a chain so everything is reached
    extra = [(a, b) for a in names for b in names if a < b and (a, b) not in pairs]
    pairs += [extra[i] for i in rng.choice(len(extra), size=3, replace=False)]
    for k, (a, b) in enumerate(pairs):
        if rng.random() < 0.5:
            a, b = b, a
        add(g, (k, k), a, b, truth[a].inv() * truth[b], sigma=float(rng.uniform(0.005, 0.05)))
    result = g.evaluate(0)
    for n in names:
        e = result.poses[n]
        assert_pose_close(e.p_world_m, e.q_world_xyzw, truth[n], 1e-8, 1e-8)


def test_fused_rotation_mean_of_two_candidates():
    g = TransformGraph(["world", "A"], 250 * MS)
    add(g, (1, 1), "world", "A", pose([0, 0, 0], [0, 0, 10]), sigma=0.01)
    add(g, (1, 2), "world", "A", pose([0, 0, 0], [0, 0, 30]), sigma=0.01)
    yaw = Rotation.from_quat(g.evaluate(0).poses["A"].q_world_xyzw).as_euler("ZYX", degrees=True)[0]
    assert yaw == pytest.approx(20.0, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 9).flatmap(
        lambda n: st.lists(
            st.lists(st.floats(-1e6, 1e6) | st.sampled_from([0.5, np.nan, np.inf]), min_size=3, max_size=3),
            min_size=n,
            max_size=n,
        )
    )
)
def test_the_gates_median_is_numpys(rows):
    """The consensus gate's median of its candidates' positions (a sort) is np.median's."""
    from atlas_onboard.core.graph.gate import _median_rows

    x = np.array(rows, dtype=float)
    np.testing.assert_array_equal(_median_rows(x), np.median(x, axis=0))  # NaN where numpy's is (its rule)

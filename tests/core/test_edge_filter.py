"""Each edge's filter: eq. 3, and the per-edge Kalman blend of an edge without the detector's 6x6."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.edge_filter import EdgeFilter, EdgeState

S = 1_000_000_000
positions = st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3).map(np.array)
rotations = st.integers(0, 2**32 - 1).map(lambda seed: Rotation.random(random_state=seed).as_quat())
sigmas = st.floats(1e-3, 1.0)


def _state(p, q, t_ns, sigma):
    return EdgeState(np.asarray(p, float), np.asarray(q, float), t_ns, sigma)


@given(positions, rotations, sigmas, st.booleans())
def test_a_new_or_expired_edge_is_the_measurement(p, q, sigma, has_cov):
    f = EdgeFilter(alpha=0.3, age_sigma_m_per_s=0.5, timeout_ns=S)
    for prior in (None, _state(p + 1.0, q, 0, 0.01)):
        got = f.update(prior, p, q, sigma, has_cov, 2 * S)  # the prior is 2 s old: expired
        assert got.p is p and got.q is q and got.sigma_m == sigma and got.stamp_ns == 2 * S


def test_the_paper_s_setting_keeps_no_state_and_passes_the_measurement_through():
    f = EdgeFilter(alpha=1.0, age_sigma_m_per_s=0.0, timeout_ns=S)
    assert not f.keeps_state
    p, q = np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0, 1.0])
    got = f.update(_state([0, 0, 0], q, 0, 0.1), p, q, 0.02, False, S // 2)
    np.testing.assert_array_equal(got.p, p)
    np.testing.assert_array_equal(got.q, q)
    assert got.sigma_m == 0.02


@settings(max_examples=50)
@given(positions, positions, rotations, st.floats(0.05, 0.95))
def test_eq3_blends_position_and_rotation_and_is_safe_for_minus_q(p_old, p_new, q, alpha):
    f = EdgeFilter(alpha=alpha, age_sigma_m_per_s=0.0, timeout_ns=S)
    assert f.keeps_state
    prior = _state(p_old, q, 0, 0.05)
    got = f.update(prior, p_new, q, 0.05, False, S // 10)
    np.testing.assert_allclose(got.p, alpha * p_new + (1 - alpha) * p_old, atol=1e-12)
    flipped = f.update(prior, p_new, -q, 0.05, False, S // 10)  # -q is the same rotation
    assert Rotation.from_quat(flipped.q).approx_equal(Rotation.from_quat(q), atol=1e-9)


@settings(max_examples=50)
@given(positions, positions, sigmas, sigmas, st.floats(0.0, 0.9), st.floats(0.05, 2.0))
def test_without_a_6x6_the_aged_old_and_the_new_are_weighed_by_inverse_variance(
    p_old, p_new, s_old, s_new, age_s, walk
):
    f = EdgeFilter(alpha=1.0, age_sigma_m_per_s=walk, timeout_ns=S)
    q = np.array([0.0, 0.0, 0.0, 1.0])
    got = f.update(_state(p_old, q, 0, s_old), p_new, q, s_new, False, round(age_s * 1e9))
    var_old = s_old**2 + (round(age_s * 1e9) / 1e9 * walk) ** 2
    w_new = var_old / (var_old + s_new**2)
    np.testing.assert_allclose(got.p, w_new * p_new + (1 - w_new) * p_old, atol=1e-9)
    assert got.sigma_m == pytest.approx(1.0 / np.sqrt(1.0 / var_old + 1.0 / s_new**2), rel=1e-9)
    assert got.sigma_m <= min(np.sqrt(var_old), s_new) * (1 + 1e-12)


@given(positions, positions, rotations, sigmas)
def test_with_the_detector_s_6x6_the_measurement_replaces_the_edge(p_old, p_new, q, sigma):
    f = EdgeFilter(alpha=1.0, age_sigma_m_per_s=1.0, timeout_ns=S)
    got = f.update(_state(p_old, q, 0, 0.001), p_new, q, sigma, True, S // 10)
    assert got.p is p_new and got.sigma_m == sigma

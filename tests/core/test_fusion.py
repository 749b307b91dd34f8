"""Fusion: eq. 3 (EMA), eq. 4 (weighted mean), eq. 5 (quaternion average), eq. 6-7 (weights)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from atlas_onboard.core import fusion
from atlas_onboard.errors import GeometryError

unit_quats = st.integers(0, 2**32 - 1).map(lambda seed: Rotation.random(random_state=seed).as_quat())


def test_weights_eq6_eq7():
    w = fusion.sigma_min_weights(np.array([0.02, 0.01, 0.04]))
    np.testing.assert_allclose(w, [0.5, 1.0, 0.25])


def test_inverse_variance_weights():
    np.testing.assert_allclose(fusion.inverse_variance_weights(np.array([0.02, 0.01])), [0.25, 1.0])


@pytest.mark.parametrize("bad", [[], [0.0, 1.0], [-0.1], [np.nan], [np.inf]])
def test_weights_reject_bad_sigmas(bad):
    with pytest.raises(GeometryError):
        fusion.sigma_min_weights(np.array(bad, dtype=float))


def test_weighted_mean_position_eq4():
    p = np.array([[0.0, 0.0, 0.0], [3.0, 6.0, -3.0]])
    # sigmas 1 and 2 -> weights 1 and 0.5 -> y = (0 + 0.5 * x2) / 1.5 = x2 / 3
    w = fusion.sigma_min_weights(np.array([1.0, 2.0]))
    np.testing.assert_allclose(fusion.weighted_mean_position(p, w), [1.0, 2.0, -1.0])


def test_ema_alpha_one_passes_through():
    prev_p, new_p = np.array([1.0, 2.0, 3.0]), np.array([4.0, 5.0, 6.0])
    np.testing.assert_array_equal(fusion.ema_position(prev_p, new_p, 1.0), new_p)
    q_prev = Rotation.from_euler("z", 10, degrees=True).as_quat()
    q_new = Rotation.from_euler("z", 50, degrees=True).as_quat()
    np.testing.assert_array_equal(fusion.ema_quaternion(q_prev, q_new, 1.0), q_new)


def test_ema_eq3_on_positions():
    out = fusion.ema_position(np.array([0.0, 0.0, 0.0]), np.array([1.0, -2.0, 4.0]), 0.25)
    np.testing.assert_allclose(out, [0.25, -0.5, 1.0])


def test_ema_converges_on_a_constant():
    p, q = np.zeros(3), Rotation.identity().as_quat()
    target_q = Rotation.from_euler("xyz", [20, -30, 40], degrees=True).as_quat()
    for _ in range(200):
        p = fusion.ema_position(p, np.array([1.0, 2.0, 3.0]), 0.1)
        q = fusion.ema_quaternion(q, target_q, 0.1)
    np.testing.assert_allclose(p, [1, 2, 3], atol=1e-8)
    assert (Rotation.from_quat(q).inv() * Rotation.from_quat(target_q)).magnitude() < 1e-8


@given(unit_quats, unit_quats, st.floats(0.05, 0.95))
def test_ema_quaternion_is_sign_safe(q_prev, q_new, alpha):
    a = Rotation.from_quat(fusion.ema_quaternion(q_prev, q_new, alpha))
    b = Rotation.from_quat(fusion.ema_quaternion(q_prev, -q_new, alpha))
    c = Rotation.from_quat(fusion.ema_quaternion(-q_prev, q_new, alpha))
    assert (a.inv() * b).magnitude() < 1e-9
    assert (a.inv() * c).magnitude() < 1e-9


def test_ema_quaternion_halfway_between_identical_axis_rotations():
    # alpha 0.5 between 0 and 60 deg about z, where one arrives as -q: the normalised blend is 30 deg.
    q0 = Rotation.identity().as_quat()
    q60 = -Rotation.from_euler("z", 60, degrees=True).as_quat()
    out = Rotation.from_quat(fusion.ema_quaternion(q0, q60, 0.5))
    assert out.as_euler("zyx", degrees=True)[0] == pytest.approx(30.0, abs=1e-9)


def eigen_mean_reference(q_xyzw, w):
    """Eq. 5 written out literally: the largest eigenvector of Q Q^T with Q = [w_i q_i]."""
    Q = (np.asarray(q_xyzw) * np.asarray(w)[:, None]).T
    vals, vecs = np.linalg.eigh(Q @ Q.T)
    return vecs[:, np.argmax(vals)]


@settings(max_examples=50)
@given(st.integers(1, 8), st.integers(0, 2**32 - 1))
def test_rotation_mean_is_eq5(n, seed):
    rng = np.random.default_rng(seed)
    q = Rotation.random(n, random_state=seed).as_quat()
    w = rng.uniform(0.1, 1.0, n)
    got = fusion.weighted_mean_rotation(q, w)
    ref = Rotation.from_quat(eigen_mean_reference(q, w))
    # Compare only where the largest eigenvalue is well separated (otherwise the mean is not unique).
    Q = (q * w[:, None]).T
    vals = np.sort(np.linalg.eigvalsh(Q @ Q.T))
    if vals[-1] - vals[-2] > 1e-6:
        assert (got.inv() * ref).magnitude() < 1e-6


@given(st.integers(1, 8), st.integers(0, 2**32 - 1), st.integers(0, 255))
def test_rotation_mean_invariant_to_sign_of_each_input(n, seed, flips):
    q = Rotation.random(n, random_state=seed).as_quat()
    w = np.random.default_rng(seed).uniform(0.1, 1.0, n)
    signs = np.array([-1.0 if flips >> i & 1 else 1.0 for i in range(n)])
    a = fusion.weighted_mean_rotation(q, w)
    b = fusion.weighted_mean_rotation(q * signs[:, None], w)
    assert (a.inv() * b).magnitude() < 1e-9


@given(unit_quats, st.integers(1, 10), arrays(float, 10, elements=st.floats(0.01, 1.0)))
def test_rotation_mean_exact_for_identical_inputs(q, n, w):
    got = fusion.weighted_mean_rotation(np.tile(q, (n, 1)), w[:n])
    assert (got.inv() * Rotation.from_quat(q)).magnitude() < 1e-7


def test_rotation_mean_small_angles_follows_weights():
    # Two rotations about z by 0 and 30 deg with weights 1 and 0.5: eq. 5 weighs by w^2 = 1 and 0.25,
    # so for small angles the mean is near 30 * 0.25 / 1.25 = 6 deg (exact value from the eigenvector).
    q = Rotation.from_euler("z", [[0], [30]], degrees=True).as_quat()
    w = fusion.sigma_min_weights(np.array([0.01, 0.02]))
    got = fusion.weighted_mean_rotation(q, w).as_euler("zyx", degrees=True)[0]
    ref = Rotation.from_quat(eigen_mean_reference(q, w)).as_euler("zyx", degrees=True)[0]
    assert got == pytest.approx(ref, abs=1e-9)
    assert 5.5 < got < 6.5


def test_fused_sigma_of_equal_independent_candidates():
    s = np.array([0.02, 0.02, 0.02, 0.02])
    assert fusion.fused_sigma(s, fusion.sigma_min_weights(s)) == pytest.approx(0.01)


def fuse_groups(group, n_groups, p, q_xyzw, sigmas, weights):
    """fusion.fuse_runs on unsorted candidates: positions (G, 3), quaternions (G, 4), sigmas (G,) and
    counts (G,) per group; a group with no candidate has count 0 and NaN values."""
    counts = np.bincount(group, minlength=n_groups)
    pos, quat, sig = np.full((n_groups, 3), np.nan), np.full((n_groups, 4), np.nan), np.full(n_groups, np.nan)
    if len(group):
        order = np.argsort(group, kind="stable")
        runs = fusion.runs_of(group[order])
        fused = fusion.fuse_runs(runs, p[order], q_xyzw[order], sigmas[order], weights[order])
        pos[runs.ids], quat[runs.ids], sig[runs.ids] = fused
    return pos, quat, sig, counts


@settings(max_examples=40)
@given(st.integers(0, 2**32 - 1))
def test_fuse_groups_matches_per_group_fusion(seed):
    rng = np.random.default_rng(seed)
    n_groups = int(rng.integers(1, 6))
    n = int(rng.integers(1, 20))
    group = rng.integers(0, n_groups, n)
    p = rng.normal(size=(n, 3))
    q = Rotation.random(n, random_state=seed).as_quat()
    s = rng.uniform(0.01, 0.1, n)
    w = np.empty(n)
    for g in range(n_groups):
        m = group == g
        if m.any():
            w[m] = fusion.sigma_min_weights(s[m])
    pos, quat, sig, counts = fuse_groups(group, n_groups, p, q, s, w)
    for g in range(n_groups):
        m = group == g
        assert counts[g] == m.sum()
        if not m.any():
            assert np.all(np.isnan(pos[g]))
            continue
        ref_p, ref_r, ref_s = fusion.fuse(p[m], q[m], s[m])
        np.testing.assert_allclose(pos[g], ref_p, atol=1e-12)
        assert sig[g] == pytest.approx(ref_s)
        Q = (q[m] * w[m][:, None]).T
        vals = np.sort(np.linalg.eigvalsh(Q @ Q.T))
        if len(vals) < 2 or vals[-1] - vals[-2] > 1e-6:
            assert (Rotation.from_quat(quat[g]).inv() * ref_r).magnitude() < 1e-6


@settings(max_examples=60)
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_fuse_groups_rotation_is_scipys_weighted_mean(seed, n):
    """The batched eq. 5 equals scipy's Rotation.mean with weights w_i^2, whatever each input's sign."""
    rng = np.random.default_rng(seed)
    base = Rotation.random(random_state=seed)
    rots = base * Rotation.from_rotvec(rng.normal(0.0, 0.3, (n, 3)))  # a spread, not antipodal
    q = rots.as_quat() * rng.choice([-1.0, 1.0], (n, 1))
    w = rng.uniform(0.1, 1.0, n)
    _, quat, _, _ = fuse_groups(np.zeros(n, dtype=np.intp), 1, np.zeros((n, 3)), q, np.full(n, 0.01), w)
    ref = Rotation.from_quat(q).mean(weights=w**2)
    assert (Rotation.from_quat(quat[0]).inv() * ref).magnitude() < 1e-9
    assert quat[0][3] >= 0.0

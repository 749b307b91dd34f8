"""6x6 covariances along chains of transforms: the Jacobians against Monte Carlo, fusion of
correlated candidates, the graph's published covariance, and the outlier gate."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import covariance
from atlas_onboard.core.graph import TransformGraph
from tests.helpers import pose

MS = 1_000_000


def random_cov(rng, scale_p=0.02, scale_a=0.03):
    A = rng.normal(size=(6, 6)) * np.array([scale_p] * 3 + [scale_a] * 3)
    return A @ A.T + np.eye(6) * 1e-6


def perturb(T, e):
    """T with the errors e = [dp (parent frame), dtheta (own axes)] applied, as the convention says.

    ``e`` is one error (6,) or a batch (N, 6); a batch gives a batch of transforms."""
    e = np.asarray(e)
    return RigidTransform.from_components(T.translation + e[..., :3], T.rotation * Rotation.from_rotvec(e[..., 3:]))


def error(T_est, T_true):
    """The error of the estimate against the truth (or a batch of truths), in the same convention."""
    return np.concatenate(
        [T_true.translation - T_est.translation, (T_est.rotation.inv() * T_true.rotation).as_rotvec()], axis=-1
    )


def sampled_cov(errors):
    e = np.array(errors)
    return e.T @ e / len(e)


def test_batched_perturb_and_error_equal_one_at_a_time():
    # The Monte Carlo tests below draw their samples as batches; each sample is the scalar formula.
    rng = np.random.default_rng(3)
    T = pose([1, 2, 0.5], [10, -20, 60])
    E = rng.normal(size=(5, 6)) * 0.05
    batch = error(T, perturb(T, E) * T)
    one = np.array([error(T, perturb(T, e) * T) for e in E])
    np.testing.assert_allclose(batch, one, atol=1e-12)


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(covariance.skew(a) @ b, np.cross(a, b), atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_composition_matches_monte_carlo(seed):
    rng = np.random.default_rng(seed)
    T_wp = pose([1, 2, 0.5], [10, -20, 60])
    T_pc = pose([2.0, -1.0, 0.3], [-30, 15, 100])  # a long lever arm: the parent's attitude error matters
    C_p, C_e = random_cov(rng), random_cov(rng)
    Jp, Je = covariance.compose_jacobians(T_wp.rotation.as_matrix(), T_pc.translation, T_pc.rotation.as_matrix())
    predicted = covariance.transform(Jp, C_p) + covariance.transform(Je, C_e)
    T_wc = T_wp * T_pc
    L_p, L_e = np.linalg.cholesky(C_p), np.linalg.cholesky(C_e)
    n = 20000
    E_p, E_e = rng.normal(size=(n, 6)) @ L_p.T, rng.normal(size=(n, 6)) @ L_e.T
    got = sampled_cov(error(T_wc, perturb(T_wp, E_p) * perturb(T_pc, E_e)))
    # Sampling error of a covariance with 20000 samples: ~1 %; first-order error: small at these sigmas.
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    assert np.max(np.abs(got - predicted) / scale) < 0.05


def test_inverse_matches_monte_carlo():
    rng = np.random.default_rng(7)
    T_ab = pose([1.5, -0.4, 2.0], [20, 30, -45])
    C = random_cov(rng)
    J = covariance.inverse_jacobian(T_ab.translation, T_ab.rotation.as_matrix())
    predicted = covariance.transform(J, C)
    L = np.linalg.cholesky(C)
    T_ba = T_ab.inv()
    got = sampled_cov(error(T_ba, perturb(T_ab, rng.normal(size=(20000, 6)) @ L.T).inv()))
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    assert np.max(np.abs(got - predicted) / scale) < 0.05


@settings(max_examples=50, deadline=None)
@given(st.floats(1e-4, 1.0), st.floats(1e-4, 0.5))
def test_inverse_of_inverse_is_identity_on_covariance(s_p, s_a):
    T = pose([0.3, -1.0, 2.0], [5, 50, -120])
    C = covariance.diagonal(s_p, s_a)
    J1 = covariance.inverse_jacobian(T.translation, T.rotation.as_matrix())
    Ti = T.inv()
    J2 = covariance.inverse_jacobian(Ti.translation, Ti.rotation.as_matrix())
    np.testing.assert_allclose(covariance.transform(J2, covariance.transform(J1, C)), C, rtol=1e-9, atol=1e-15)


def fuse(child, parent, n, weights, Jp, C_parent, edge_term):
    """covariance.fuse_runs on unsorted candidates: the (n, 6, 6) covariance of each child's mean."""
    out = np.zeros((n, 6, 6))
    order = np.lexsort((parent, child))
    kids, pairs = covariance.runs_by_parent(child[order], parent[order])
    out[kids.ids] = covariance.fuse_runs(kids, pairs, weights[order], Jp[order], C_parent, edge_term[order])
    return out


def test_fusion_averages_edge_errors_but_not_the_shared_parent():
    # Two equal candidates of one child: from the same parent (its error is common to both) and
    # from world (exact). Identity Jacobians make the figures exact.
    edge = np.eye(6) * 4.0
    parent_cov = np.stack([np.zeros((6, 6)), np.eye(6) * 9.0])
    Jp = np.stack([np.eye(6), np.eye(6)])
    same = fuse(np.array([0, 0]), np.array([1, 1]), 1, np.ones(2), Jp, parent_cov, np.stack([edge, edge]))
    np.testing.assert_allclose(same[0], np.eye(6) * (9.0 + 4.0 / 2))
    both = fuse(np.array([0, 0]), np.array([0, 1]), 1, np.ones(2), Jp, parent_cov, np.stack([edge, edge]))
    np.testing.assert_allclose(both[0], np.eye(6) * (9.0 / 4 + 4.0 / 2))


def test_graph_covariance_of_a_chain_grows_with_the_lever_arm():
    # world sees A (1 cm, so about 0.6 deg at 1 m); A sees B 3 m ahead with 1 cm: B's lateral
    # variance carries A's attitude error over 3 m, its along-track variance does not.
    g = TransformGraph(["world", "A", "B"], edge_timeout_ns=250 * MS)
    T_wA, T_AB = pose([0, 0, 1]), pose([3, 0, 0])
    g.update_edge((1, 1), "world", "A", T_wA.translation, T_wA.rotation.as_quat(), 0.01, 0, sigma_att_rad=0.01)
    g.update_edge((2, 2), "A", "B", T_AB.translation, T_AB.rotation.as_quat(), 0.01, 0, sigma_att_rad=0.01)
    r = g.evaluate(0)
    np.testing.assert_allclose(r.poses["A"].covariance, covariance.diagonal(0.01, 0.01), atol=1e-15)
    C = r.poses["B"].covariance
    assert C[0, 0] == pytest.approx(2 * 0.01**2)  # along x: two position errors
    assert C[1, 1] == pytest.approx(2 * 0.01**2 + (3 * 0.01) ** 2)  # lateral: plus 3 m x 0.01 rad
    assert C[2, 2] == pytest.approx(2 * 0.01**2 + (3 * 0.01) ** 2)
    assert C[5, 5] == pytest.approx(2 * 0.01**2)


def floor_scene(gate, wrong=None):
    """A drone 1.5 m above four floor tags, each seen with 1 cm; ``wrong`` replaces one observation.

    Each observation is an edge drone -> world (eq. 1 has already taken the tag's placement out)."""
    g = TransformGraph(["world", "d"], edge_timeout_ns=250 * MS, outlier_gate_sigma=gate)
    truth = pose([1.0, 2.0, 1.5], [0, 0, 40])
    for k in range(4):
        T = truth.inv() if k != 1 or wrong is None else wrong(truth)
        g.update_edge((1, k), "d", "world", T.translation, T.rotation.as_quat(), 0.01, 0, 100)
    return g, truth


def test_gate_leaves_out_a_wrong_id_among_four():
    # The second tag's detection is really another tag, 2 m away (eq. 1 then shifts the edge by
    # 2 m): without the gate it drags the drone by 50 cm; with it, the estimate is that of the three
    # good ones and the rejection is counted.
    def wrong(truth):
        return truth.inv() * pose([2.0, 0, 0])

    g_off, truth = floor_scene(0.0, wrong)
    g_on, _ = floor_scene(5.0, wrong)
    off, on = g_off.evaluate(0), g_on.evaluate(0)
    assert np.linalg.norm(off.poses["d"].p_world_m - truth.translation) > 0.3
    np.testing.assert_allclose(on.poses["d"].p_world_m, truth.translation, atol=1e-9)
    assert on.poses["d"].n_observations == 3 and on.gated == 1 and g_on.gated_total == 1
    g_on.evaluate(1)  # the same edge seen again in the next evaluation is not counted twice
    assert g_on.gated_total == 1


def test_gate_keeps_the_estimate_when_a_lone_flipped_pose_arrives():
    # One tag in view. A flipped pose (30 deg tilt, 25 cm off) arrives 33 ms after a good one: the
    # drone keeps its estimate and its capture time (so nothing new is published); once the
    # estimate is older than the edge timeout the next observation is taken whatever it says.
    g = TransformGraph(["world", "d"], edge_timeout_ns=250 * MS, outlier_gate_sigma=5.0)
    truth = pose([1.0, 2.0, 1.5])
    good = truth.inv()
    g.update_edge((1, 0), "d", "world", good.translation, good.rotation.as_quat(), 0.01, 0, 100)
    first = g.evaluate(0).poses["d"]
    flipped = (truth * pose([0.25, 0, 0], [0, 30, 0])).inv()
    g.update_edge((1, 0), "d", "world", flipped.translation, flipped.rotation.as_quat(), 0.01, 33 * MS, 133)
    r = g.evaluate(33 * MS)
    np.testing.assert_allclose(r.poses["d"].p_world_m, first.p_world_m, atol=1e-12)
    assert r.poses["d"].capture_time_us == 100 and g.gated_total == 1
    g.update_edge((1, 0), "d", "world", good.translation, good.rotation.as_quat(), 0.01, 66 * MS, 166)
    r = g.evaluate(66 * MS)
    np.testing.assert_allclose(r.poses["d"].p_world_m, truth.translation, atol=1e-9)
    assert r.poses["d"].capture_time_us == 166
    # 300 ms later the old estimate has expired: a different pose is accepted (re-acquisition).
    moved = pose([2.0, 2.0, 1.5]).inv()
    g.update_edge((1, 0), "d", "world", moved.translation, moved.rotation.as_quat(), 0.01, 400 * MS, 400)
    np.testing.assert_allclose(g.evaluate(400 * MS).poses["d"].p_world_m, [2.0, 2.0, 1.5], atol=1e-9)


def test_gate_off_is_the_paper():
    g, truth = floor_scene(0.0)
    r = g.evaluate(0)
    np.testing.assert_allclose(r.poses["d"].p_world_m, truth.translation, atol=1e-9)
    assert r.gated == 0 and r.poses["d"].n_observations == 4


_quat = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)


@given(st.lists(st.floats(-3, 3), min_size=9, max_size=9), _quat, _quat, _quat, st.floats(0.001, 0.1))
def test_observation_covariance_is_the_product_of_its_jacobians(xyz, q_as, q_sm, q_mb, sigma):
    """The closed form of covariance.observation equals the chain it is derived from: the detection's
    error (camera in the marker frame) through the inverse, then left by T_a_s, right by T_m_b."""

    def matrix(q, p):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_quat(q).as_matrix(), p
        return T

    T_as, T_sm, T_mb = matrix(q_as, xyz[0:3]), matrix(q_sm, xyz[3:6]), matrix(q_mb, xyz[6:9])
    R_sm, p_sm = T_sm[:3, :3], T_sm[:3, 3]
    att = covariance.attitude_sigma_rad(sigma, np.linalg.norm(p_sm))
    C_ms = covariance.diagonal(sigma, att)
    C_sm = covariance.transform(covariance.inverse_jacobian(-R_sm.T @ p_sm, R_sm.T), C_ms)
    J_left = np.eye(6)
    J_left[:3, :3] = T_as[:3, :3]
    C_am = covariance.transform(J_left, C_sm)
    J_right, _ = covariance.compose_jacobians(T_as[:3, :3] @ R_sm, T_mb[:3, 3], T_mb[:3, :3])
    expected = covariance.transform(J_right, C_am)
    got = covariance.observation(T_as[None], T_sm[None], T_mb[None], np.array([sigma]))[0]
    np.testing.assert_allclose(got, expected, atol=1e-12 * max(1.0, np.abs(expected).max()))


def test_detection_covariance_matches_monte_carlo():
    """covariance.detection carries the detector's own covariance of T_s_m through eq. 1's fixed
    mountings (left T_a_s, right T_m_b with a long lever arm): against 20 000 perturbed chains."""
    rng = np.random.default_rng(11)
    T_as = pose([0.1, 0.0, -0.05], [0, 90, 0])
    T_sm = pose([0.3, -0.2, 2.5], [170, 10, 30])
    T_mb = pose([1.5, -0.8, 0.2], [0, 0, 40])  # the entity's origin far from the marker
    C_sm = random_cov(rng, 0.003, 0.01)
    chain = covariance.Chain(
        T_as.rotation.as_matrix()[None], T_sm.rotation.as_matrix()[None], T_sm.translation[None], T_mb.as_matrix()[None]
    )
    predicted = covariance.detection(chain, C_sm[None])[0]
    n = 20000
    E = rng.normal(size=(n, 6)) @ np.linalg.cholesky(C_sm).T
    got = sampled_cov(error(T_as * T_sm * T_mb, T_as * perturb(T_sm, E) * T_mb))
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    assert np.max(np.abs(got - predicted) / scale) < 0.05


def test_attitude_ages_only_when_asked():
    """age_sigma_rad_per_s grows an edge's attitude variance by (age x rate)^2 and nothing else; the age
    is counted on the capture clock from the newest image of a live edge (here another entity's, 100 ms
    newer), not from the evaluation's time."""
    C = covariance.diagonal(0.01, 0.02)
    poses = {}
    for rate in (0.0, 1.5):
        g = TransformGraph(["world", "d", "e"], 250 * MS, age_sigma_rad_per_s=rate)
        g.update_edge(("c", 1), "world", "d", np.array([1.0, 0, 0]), np.array([0, 0, 0, 1.0]), 0.01, 0, 0, cov_a_b=C)
        g.update_edge(("c", 2), "world", "e", np.array([2.0, 0, 0]), np.array([0, 0, 0, 1.0]), 0.01, 0, 100_000)
        poses[rate] = g.evaluate(150 * MS).poses["d"]
    np.testing.assert_allclose(poses[0.0].covariance, C, atol=1e-15)
    grown = C.copy()
    grown[[3, 4, 5], [3, 4, 5]] += (0.1 * 1.5) ** 2
    np.testing.assert_allclose(poses[1.5].covariance, grown, atol=1e-15)
    np.testing.assert_allclose(poses[1.5].p_world_m, poses[0.0].p_world_m)


def test_gate_allows_the_motion_since_the_estimates_frame_not_only_since_the_estimate():
    # Two ceiling cameras, frames at the same instant: the first camera's frame leads to an
    # evaluation whose estimate of the drone rests on the second camera's previous frame, 66 ms old;
    # the second camera's new frame is then evaluated at the same instant. The drone turned 10 deg in
    # those 66 ms (150 deg/s, within MAX_RATE_RAD_S): kept. A flip of 60 deg is still left out.
    for turn_deg, kept in ((10.0, True), (60.0, False)):
        g = TransformGraph(["world", "d"], edge_timeout_ns=250 * MS, outlier_gate_sigma=5.0)
        before, after = pose([1.0, 2.0, 1.5]), pose([1.0, 2.0, 1.5], [turn_deg, 0, 0])
        g.update_edge((2, 0), "world", "d", before.translation, before.rotation.as_quat(), 0.001, 0, 1_000_000)
        g.evaluate(66 * MS)  # the other camera's frame: the estimate made now, from a 66 ms old view
        g.update_edge((2, 0), "world", "d", after.translation, after.rotation.as_quat(), 0.001, 66 * MS, 1_066_000)
        r = g.evaluate(66 * MS)
        assert (r.gated == 0) is kept, (turn_deg, r.gated)
        q = r.poses["d"].q_world_xyzw
        expect = after if kept else before
        assert (Rotation.from_quat(q).inv() * expect.rotation).magnitude() < 1e-9


def _liar_scene(n_liars):
    """The drone's own camera (sensor 1) sees a floor tag; ``n_liars`` peer sensors (world cameras
    10, 11, ...) claim the drone is 1 m east, with a sigma of 1 mm and fresh stamps."""
    g = TransformGraph(["world", "d"], edge_timeout_ns=250 * MS, outlier_gate_sigma=5.0, anchor_sensors={1})
    truth = pose([1.0, 2.0, 1.5], [0, 0, 30])
    lie = pose([2.0, 2.0, 1.5], [0, 0, 30])
    good = truth.inv()
    for t in range(0, 400, 33):  # every frame for 0.4 s: longer than the edge timeout
        now = t * MS
        g.update_edge((1, 0), "d", "world", good.translation, good.rotation.as_quat(), 0.01, now, t * 1000)
        for k in range(n_liars):
            g.update_edge((10 + k, 5), "world", "d", lie.translation, lie.rotation.as_quat(), 0.001, now, t * 1000)
        r = g.evaluate(now)
        np.testing.assert_allclose(r.poses["d"].p_world_m, truth.translation, atol=1e-9)
        assert r.poses["d"].n_observations == 1
    return g


@pytest.mark.parametrize("n_liars", [1, 3])
def test_gate_refuses_a_confident_liar_against_the_own_camera_however_many(n_liars):
    # Without the anchor, one liar and the camera are two candidates that disagree (both out, the
    # estimate held until it expires, then the 1 mm one outweighs the camera ten to one); three
    # liars make the median theirs.
    g = _liar_scene(n_liars)
    assert g.gated_total == 13 * n_liars  # each refused observation counted once


def test_gate_keeps_a_peer_that_agrees_with_the_own_camera():
    g = TransformGraph(["world", "d"], edge_timeout_ns=250 * MS, outlier_gate_sigma=5.0, anchor_sensors={1})
    truth = pose([1.0, 2.0, 1.5], [0, 0, 30])
    peer = pose([1.02, 2.0, 1.5], [0, 0, 30])  # 2 cm off with sigma 1 cm against the camera's 1 cm: 1.4 sigma
    good = truth.inv()
    g.update_edge((1, 0), "d", "world", good.translation, good.rotation.as_quat(), 0.01, 0, 0)
    g.update_edge((10, 5), "world", "d", peer.translation, peer.rotation.as_quat(), 0.01, 0, 0)
    r = g.evaluate(0)
    assert r.poses["d"].n_observations == 2 and g.gated_total == 0
    np.testing.assert_allclose(r.poses["d"].p_world_m, [1.01, 2.0, 1.5], atol=1e-9)


def test_a_leaders_aged_attitude_swings_the_followers_pose_as_monte_carlo_says():
    """world -> a (an edge 80 ms old, aged at 15 deg/s) -> b (a fresh edge, b 1.2 m behind a): the 6x6
    covariance the graph gives b matches 20,000 sampled chains (the leader's attitude error swung over
    the lever arm into the follower's position, and into its attitude): NEES6 of the samples averages
    6 within its sampling error, and each variance within 10 %."""
    from scipy.spatial.transform import Rotation

    from atlas_onboard.core.graph import TransformGraph

    rate_rad_s, age_s = np.radians(15.0), 0.08
    g = TransformGraph(["world", "a", "b"], 250_000_000, age_sigma_rad_per_s=rate_rad_s)
    p_wa, q_wa = np.array([2.0, 0.5, 1.2]), Rotation.from_euler("ZYX", [30, 5, -4], degrees=True)
    p_ab, q_ab = np.array([-1.2, 0.1, 0.05]), Rotation.from_euler("ZYX", [-10, 3, 2], degrees=True)
    C_wa = np.diag([0.004**2] * 3 + [np.radians(0.5) ** 2] * 3)
    C_ab = np.diag([0.01**2] * 3 + [np.radians(1.5) ** 2] * 3)
    g.update_edge((1, 10), "world", "a", p_wa, q_wa.as_quat(), 0.004, 0, 0, cov_a_b=C_wa)
    now_ns = int(age_s * 1e9)  # b's image is taken (and arrives) 80 ms after a's
    g.update_edge((2, 20), "a", "b", p_ab, q_ab.as_quat(), 0.01, now_ns, now_ns // 1000, cov_a_b=C_ab)
    got = g.evaluate(now_ns).poses["b"]
    rng = np.random.default_rng(7)
    n = 20_000
    aged = C_wa + np.diag([0, 0, 0] + [(rate_rad_s * age_s) ** 2] * 3)
    e1 = rng.multivariate_normal(np.zeros(6), aged, n)
    e2 = rng.multivariate_normal(np.zeros(6), C_ab, n)
    R1 = q_wa * Rotation.from_rotvec(e1[:, 3:])  # R_true = R Exp(dtheta), about the body's own axes
    R2 = q_ab * Rotation.from_rotvec(e2[:, 3:])
    p_b = p_wa + e1[:, :3] + R1.apply(p_ab + e2[:, :3])
    R_b = R1 * R2
    q_nom = Rotation.from_quat(got.q_world_xyzw)
    err = np.hstack([p_b - got.p_world_m, (q_nom.inv() * R_b).as_rotvec()])
    C = got.covariance
    nees = np.einsum("ij,ij->i", err, np.linalg.solve(C, err.T).T)
    assert abs(nees.mean() - 6.0) < 0.15, nees.mean()
    np.testing.assert_allclose(np.diag(np.cov(err.T)), np.diag(C), rtol=0.1)

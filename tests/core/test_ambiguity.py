"""Planar-pose ambiguity against ground truth: real IPPE flips (the detector's solve, OpenCV IPPE) from
projected corners of a nearly face-on tag, corrected with a prior, undecidable without one."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import ambiguity
from atlas_onboard.core.ambiguity import Verdict
from atlas_onboard.detector import pose
from atlas_onboard.errors import GeometryError

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
SIZE_M = 0.15
FLIP_DEG = 10.0  # a solution this far from the truth in attitude is a flip (as benchmarks/bench_detector.py)


def ippe(T_true: RigidTransform, noise_px: float, seed: int) -> tuple[RigidTransform, RigidTransform, float, float]:
    """The detector's two IPPE solutions (chosen, other), their ratio and its sigma (m) for noisy
    projections of the true corners."""
    obj = pose.object_corners(SIZE_M)
    img, _ = cv2.projectPoints(obj, T_true.rotation.as_rotvec(), T_true.translation, K, None)
    img = img.reshape(-1, 2) + np.random.default_rng(seed).normal(0.0, noise_px, (4, 2))
    mp = pose.solve(img, SIZE_M, K, pose.SIGMA_PX_APRILTAG)
    assert mp is not None and mp.p_alt_m is not None and mp.q_alt_xyzw is not None
    a = RigidTransform.from_components(mp.p_m, Rotation.from_quat(mp.q_xyzw))
    b = RigidTransform.from_components(mp.p_alt_m, Rotation.from_quat(mp.q_alt_xyzw))
    return a, b, mp.ambiguity, mp.sigma_m


def angle_deg(a: RigidTransform, b: RigidTransform) -> float:
    return math.degrees((a.rotation.inv() * b.rotation).magnitude())


# A 15 cm tag 4 m away, tilted 15 degrees from face-on: with 0.3 px of corner noise IPPE's chosen
# solution is the mirror image in a large share of frames.
T_TRUE = RigidTransform.from_components([0.1, 0.05, 4.0], Rotation.from_euler("x", 180 + 15, degrees=True))
NOISE_PX = 0.3


def flipped_seed() -> int:
    for seed in range(200):
        a, b, _, _ = ippe(T_TRUE, NOISE_PX, seed)
        if angle_deg(a, T_TRUE) > FLIP_DEG and angle_deg(b, T_TRUE) < FLIP_DEG:
            return seed
    raise AssertionError("no flip in 200 seeds")


def estimate_of(T: RigidTransform, rot_deg: float, pos_m: float, seed: int) -> RigidTransform:
    """``T`` with an estimation error of ``rot_deg`` and ``pos_m`` in random directions."""
    rng = np.random.default_rng(seed)
    axis, d = rng.normal(size=3), rng.normal(size=3)
    err = RigidTransform.from_components(
        d / np.linalg.norm(d) * pos_m, Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(rot_deg))
    )
    return err * T


def sigmas(T_obs: RigidTransform, sigma_obs_m: float) -> tuple[float, float]:
    """The listener's sigmas for a drone (attitude 0.05 rad, 2 cm) observing a world marker with an
    observation of sigma ``sigma_obs_m`` (the detector's model)."""
    s_rad, s_m = ambiguity.prediction_sigmas(np.linalg.norm(T_obs.translation), sigma_obs_m, 0.02, 0.0, 0.05, 0.0)
    return float(s_rad), float(s_m)


def test_real_ippe_flip_is_corrected_given_the_estimate():
    a, b, ratio, sigma = ippe(T_TRUE, NOISE_PX, flipped_seed())
    assert ratio > ambiguity.AMBIGUITY_THRESHOLD
    # The estimates of a drone and its camera, 3 degrees and 2 cm off, predict the marker's pose.
    T_world_drone = RigidTransform.from_components(
        [1.0, 2.0, 4.2], Rotation.from_euler("xyz", [3, -4, 70], degrees=True)
    )
    T_drone_sensor = RigidTransform.from_components([0.2, 0, -0.05], Rotation.from_euler("y", 90, degrees=True))
    T_world_marker = T_world_drone * T_drone_sensor * T_TRUE
    T_world_drone_est = estimate_of(T_world_drone, 3.0, 0.02, seed=1)
    pred = ambiguity.predict_sensor_marker(T_world_drone_est, T_drone_sensor, RigidTransform.identity(), T_world_marker)
    res = ambiguity.resolve(a, b, pred, *sigmas(a, sigma))
    assert res.verdict is Verdict.ALT
    assert angle_deg(b, T_TRUE) < FLIP_DEG < angle_deg(a, T_TRUE)
    assert res.r2_alt < res.r2_primary


def test_without_a_prediction_nothing_is_decided():
    a, b, _, sigma = ippe(T_TRUE, NOISE_PX, flipped_seed())
    res = ambiguity.resolve(a, b, None, *sigmas(a, sigma))
    assert res.verdict is Verdict.NO_PREDICTION and not res.verdict.decided


def test_a_prediction_far_from_both_decides_nothing():
    a, b, _, sigma = ippe(T_TRUE, NOISE_PX, flipped_seed())
    wrong = RigidTransform.from_components(
        T_TRUE.translation, Rotation.from_euler("y", 90, degrees=True) * T_TRUE.rotation
    )
    assert ambiguity.resolve(a, b, wrong, *sigmas(a, sigma)).verdict is Verdict.BOTH_FAR
    sigma_rad, sigma_m = sigmas(a, sigma)
    moved = RigidTransform.from_components(T_TRUE.translation + np.array([6 * sigma_m, 0, 0]), T_TRUE.rotation)
    assert ambiguity.resolve(a, b, moved, sigma_rad, sigma_m).verdict is Verdict.BOTH_FAR


def test_a_prediction_halfway_between_the_solutions_decides_nothing():
    a, b, _, sigma = ippe(T_TRUE, NOISE_PX, flipped_seed())
    half = (a.rotation.inv() * b.rotation).as_rotvec() / 2
    mid = RigidTransform.from_components((a.translation + b.translation) / 2, a.rotation * Rotation.from_rotvec(half))
    res = ambiguity.resolve(a, b, mid, *sigmas(a, sigma))
    # Equidistant: undecidable (here also beyond the gate, as each solution is 16 degrees away).
    assert res.r2_primary == pytest.approx(res.r2_alt, rel=1e-6)
    assert res.verdict in (Verdict.TOO_CLOSE, Verdict.BOTH_FAR)


def test_solutions_closer_than_the_uncertainty_are_too_close():
    # 4 degrees of tilt from face-on: the two solutions are about 8 degrees apart, within the
    # estimate's uncertainty (sigma about 3.5 degrees), so even a perfect prediction cannot choose.
    T = RigidTransform.from_components([0.0, 0.0, 3.0], Rotation.from_euler("x", 184, degrees=True))
    a, b, _, sigma = ippe(T, 0.05, seed=0)
    assert angle_deg(a, b) < 12.0
    assert ambiguity.resolve(a, b, T, *sigmas(a, sigma)).verdict is Verdict.TOO_CLOSE


def test_over_many_noisy_frames_every_decision_is_right():
    """Every frame of the flip-prone view, with an estimate 3 degrees and 2 cm off: a decision is never
    the flip (the solution farther from the truth; corner noise alone can put the right one a few
    degrees off), and most ambiguous frames are decided."""
    decided = ambiguous = 0
    for seed in range(200):
        a, b, ratio, sigma = ippe(T_TRUE, NOISE_PX, seed)
        if ratio <= ambiguity.AMBIGUITY_THRESHOLD:
            continue
        ambiguous += 1
        pred = estimate_of(T_TRUE, 3.0, 0.02, seed=seed + 1000)
        res = ambiguity.resolve(a, b, pred, *sigmas(a, sigma))
        if res.verdict.decided:
            decided += 1
            chosen, other = (a, b) if res.verdict is Verdict.PRIMARY else (b, a)
            assert angle_deg(chosen, T_TRUE) < angle_deg(other, T_TRUE), f"seed {seed}: chose the flip"
    assert ambiguous >= 100
    assert decided >= 0.9 * ambiguous, f"{decided} of {ambiguous} decided"


def test_predict_sensor_marker_inverts_eq1():
    T_world_a = RigidTransform.from_components([1, 2, 3], Rotation.from_euler("xyz", [10, 20, 30], degrees=True))
    T_world_b = RigidTransform.from_components([-1, 0, 1], Rotation.from_euler("xyz", [0, -40, 100], degrees=True))
    T_a_sensor = RigidTransform.from_components([0.1, 0, 0], Rotation.from_euler("y", 90, degrees=True))
    T_b_marker = RigidTransform.from_components([0, 0.2, 0], Rotation.from_euler("z", 45, degrees=True))
    T2 = ambiguity.predict_sensor_marker(T_world_a, T_a_sensor, T_world_b, T_b_marker)
    T_a_b = T_a_sensor * T2 * T_b_marker.inv()  # eq. 1
    np.testing.assert_allclose(T_a_b.as_matrix(), (T_world_a.inv() * T_world_b).as_matrix(), atol=1e-12)


def test_bad_sigmas_are_refused():
    with pytest.raises(GeometryError, match="sigma_rad > 0"):
        ambiguity.resolve(T_TRUE, T_TRUE, T_TRUE, 0.0, 0.1)


rotvecs = st.tuples(*[st.floats(-3.0, 3.0)] * 3)
positions = st.tuples(*[st.floats(-5.0, 5.0)] * 3)


@settings(max_examples=200, deadline=None)
@given(
    truth_rv=rotvecs,
    truth_p=positions,
    err_dir=rotvecs,
    err_frac=st.floats(0.0, 1.0),
    flip_axis=rotvecs,
    flip_sigmas=st.floats(6.0, 40.0),
    sigma_rad=st.floats(0.01, 0.1),
)
def test_a_prediction_within_one_sigma_picks_a_solution_six_sigma_away_from_the_other(
    truth_rv, truth_p, err_dir, err_frac, flip_axis, flip_sigmas, sigma_rad
):
    """With the prediction at most 1 sigma off in attitude and in position, and the other solution
    at least 6 sigma away in attitude, the truth is always chosen whichever slot it is in."""
    axis, e = np.array(flip_axis), np.array(err_dir)
    if np.linalg.norm(axis) < 1e-3 or np.linalg.norm(e) < 1e-3 or flip_sigmas * sigma_rad > math.pi:
        return
    sigma_m = 0.05
    truth = RigidTransform.from_components(truth_p, Rotation.from_rotvec(truth_rv))
    other = RigidTransform.from_components(
        truth.translation, truth.rotation * Rotation.from_rotvec(axis / np.linalg.norm(axis) * flip_sigmas * sigma_rad)
    )
    u = e / np.linalg.norm(e)
    pred = RigidTransform.from_components(
        truth.translation + u * err_frac * sigma_m, truth.rotation * Rotation.from_rotvec(u * err_frac * sigma_rad)
    )
    assert ambiguity.resolve(truth, other, pred, sigma_rad, sigma_m).verdict is Verdict.PRIMARY
    assert ambiguity.resolve(other, truth, pred, sigma_rad, sigma_m).verdict is Verdict.ALT


@settings(max_examples=200, deadline=None)
@given(a_rv=rotvecs, b_rv=rotvecs, pred_rv=rotvecs, a_p=positions, b_p=positions, pred_p=positions)
def test_the_verdict_is_symmetric_and_never_picks_the_farther(a_rv, b_rv, pred_rv, a_p, b_p, pred_p):
    a = RigidTransform.from_components(a_p, Rotation.from_rotvec(a_rv))
    b = RigidTransform.from_components(b_p, Rotation.from_rotvec(b_rv))
    pred = RigidTransform.from_components(pred_p, Rotation.from_rotvec(pred_rv))
    ab = ambiguity.resolve(a, b, pred, 0.05, 0.5)
    ba = ambiguity.resolve(b, a, pred, 0.05, 0.5)
    mirror = {Verdict.PRIMARY: Verdict.ALT, Verdict.ALT: Verdict.PRIMARY}
    assert ba.verdict is mirror.get(ab.verdict, ab.verdict) or (ab.r2_primary == ab.r2_alt)
    if ab.verdict is Verdict.PRIMARY:
        assert ab.r2_primary <= ab.r2_alt
    if ab.verdict is Verdict.ALT:
        assert ab.r2_alt < ab.r2_primary


@settings(max_examples=200, deadline=None)
@given(
    p=positions,
    rv=rotvecs,
    d_rv=st.tuples(*[st.floats(-0.5, 0.5)] * 3),
    d_p=st.tuples(*[st.floats(-0.05, 0.05)] * 3),
    scale=st.floats(-3.0, 1.0),
    seed=st.integers(0, 2**16),
)
def test_a_cover_is_close_exactly_within_the_gate_and_holds_both_solutions_within_one_sigma(
    p, rv, d_rv, d_p, scale, seed
):
    """``close`` is d^T C^-1 d <= COVER_R2, and each solution lies within one sigma of the mixture
    (its offset in the mixture's convention, against the grown covariance)."""
    A = np.random.default_rng(seed).normal(size=(6, 6))
    C = (A @ A.T + 0.1 * np.eye(6)) * 10.0**scale * np.diag([1e-4] * 3 + [1e-2] * 3)
    R_a = Rotation.from_rotvec(rv)
    R_b = R_a * Rotation.from_rotvec(d_rv)
    p_b = np.array(p) + np.array(d_p)
    prim = ambiguity.Poses(np.array([p]), R_a.as_quat()[None])
    alt = ambiguity.Poses(p_b[None], R_b.as_quat()[None])
    got = ambiguity.cover(prim, alt, C[None])
    d = np.r_[d_p, d_rv]
    assert bool(got.close[0]) == (d @ np.linalg.solve(C, d) <= ambiguity.COVER_R2)
    R_m = Rotation.from_quat(got.pose.q_xyzw[0])
    for q, R in ((p, R_a), (p_b, R_b)):
        e = np.r_[np.asarray(q) - got.pose.p_m[0], (R_m.inv() * R).as_rotvec()]
        assert e @ np.linalg.solve(got.covariance[0], e) <= 1.0 + 1e-9


def test_a_cover_of_face_on_ippe_pairs_holds_the_truth():
    """Real face-on pairs (the detector's solve of noisy corners of a tag 1.5 m away, 0.3 px) that
    lie within their covariance: the mixture's NEES6 against the truth is chi-square(6)'s or less."""
    nees = []
    for seed in range(300):
        rng = np.random.default_rng(seed)
        tilt = Rotation.from_rotvec(np.r_[rng.normal(0, 0.03, 2), 0.0])
        T = RigidTransform.from_components([0.05, -0.05, 1.5], tilt * Rotation.from_euler("x", 180, degrees=True))
        obj = pose.object_corners(SIZE_M)
        img, _ = cv2.projectPoints(obj, T.rotation.as_rotvec(), T.translation, K, None)
        mp = pose.solve(img.reshape(-1, 2) + rng.normal(0, 0.3, (4, 2)), SIZE_M, K, 0.0, measured_sigma_px=0.3)
        if (
            mp is None
            or mp.q_alt_xyzw is None
            or mp.covariance is None
            or not mp.ambiguity > ambiguity.AMBIGUITY_THRESHOLD
        ):
            continue
        got = ambiguity.cover(
            ambiguity.Poses(mp.p_m[None], mp.q_xyzw[None]), ambiguity.Poses(mp.p_alt_m[None], mp.q_alt_xyzw[None]),
            mp.covariance[None],
        )  # fmt: skip
        if got.close[0]:
            R_m = Rotation.from_quat(got.pose.q_xyzw[0])
            e = np.r_[T.translation - got.pose.p_m[0], (R_m.inv() * T.rotation).as_rotvec()]
            nees.append(float(e @ np.linalg.solve(got.covariance[0], e)))
    assert len(nees) >= 40
    assert np.mean(nees) <= 6.0 * 1.25 and np.mean(np.array(nees) <= 16.81) >= 0.95  # chi2(6): mean 6, 0.99 at 16.81

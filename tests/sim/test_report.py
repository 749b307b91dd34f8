"""NEES of published covariances: errors drawn from a known covariance score ~dimension, whatever
the frames, and an unknown covariance scores NaN."""

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import frames
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink.covariance import covariance_ned_frd, covariance_upper_triangle
from atlas_onboard.sim import report, scenarios
from atlas_onboard.sim.autopilot import Received
from atlas_onboard.sim.command import autopilot_track
from atlas_onboard.sim.world import SimWorld, fresh_share

N = 4000


def _chi2_mean_bound(dof: int, n: int) -> float:
    """Five standard deviations of the mean of n chi-square(dof) draws."""
    return 5.0 * np.sqrt(2.0 * dof / n)


def _random_spd(rng: np.random.Generator, scales: np.ndarray) -> np.ndarray:
    """A correlated covariance with the given standard deviations along random axes."""
    Q, _ = np.linalg.qr(rng.normal(size=(len(scales), len(scales))))
    return Q @ np.diag(scales**2) @ Q.T


def _truth(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    return rng.uniform(-3, 3, (n, 3)), Rotation.random(n, rng=rng).as_quat()


def test_errors_drawn_from_the_published_covariance_give_nees_of_the_dimension():
    rng = np.random.default_rng(1)
    cov = _random_spd(rng, np.array([0.01, 0.02, 0.05, 0.01, 0.03, 0.1]))
    p_true, q_true = _truth(rng, N)
    T_true = frames.enu_flu_to_ned_frd(RigidTransform.from_components(p_true, Rotation.from_quat(q_true)))
    e = rng.multivariate_normal(np.zeros(6), cov, N)
    p_est = T_true.translation + e[:, :3]
    q_est = (T_true.rotation * Rotation.from_rotvec(e[:, 3:])).as_quat()
    got = report.pose_errors_ned_frd(p_est, q_est, p_true, q_true)
    np.testing.assert_allclose(got, e, atol=1e-9)
    covs = np.repeat(cov[None], N, axis=0)
    n6 = report.nees(got, covs)
    n3 = report.nees(got[:, :3], covs[:, :3, :3])
    assert abs(n6.mean() - 6.0) < _chi2_mean_bound(6, N), n6.mean()
    assert abs(n3.mean() - 3.0) < _chi2_mean_bound(3, N), n3.mean()
    # Twice too small a covariance is caught: NEES doubles.
    assert report.nees(got, covs / 2).mean() > 6.0 + 10 * _chi2_mean_bound(6, N)


def test_a_covariance_published_from_enu_flu_is_consistent_after_the_autopilot_conversion():
    """Anisotropic in ENU (east) and about the FLU body x axis, with the drone yawed 90 deg and tilted:
    the covariance goes through the publisher's conversion and the MAVLink triangle, the errors
    through the NED/FRD frames, and NEES stays at the dimension only if both agree."""
    rng = np.random.default_rng(2)
    cov_enu_flu = np.diag([0.2, 0.005, 0.01, 0.2, 0.004, 0.01]) ** 2
    cov_enu_flu[0, 3] = cov_enu_flu[3, 0] = 0.8 * 0.2 * 0.2  # east error goes with roll error
    tri = covariance_upper_triangle(covariance_ned_frd(cov_enu_flu))
    cov_sent = report.covariance_from_upper_triangle(np.tile(tri, (N, 1)))
    p_true = rng.uniform(-3, 3, (N, 3))
    R_true = Rotation.from_euler("ZYX", np.column_stack([np.full(N, 90.0), rng.uniform(-20, 20, (N, 2))]), degrees=True)
    e_enu_flu = rng.multivariate_normal(np.zeros(6), cov_enu_flu, N)
    R_est = R_true * Rotation.from_rotvec(e_enu_flu[:, 3:])
    T_est = frames.enu_flu_to_ned_frd(RigidTransform.from_components(p_true + e_enu_flu[:, :3], R_est))
    e = report.pose_errors_ned_frd(T_est.translation, T_est.rotation.as_quat(), p_true, R_true.as_quat())
    n6 = report.nees(e, cov_sent)
    n3 = report.nees(e[:, :3], cov_sent[:, :3, :3])
    assert abs(n6.mean() - 6.0) < _chi2_mean_bound(6, N), n6.mean()
    assert abs(n3.mean() - 3.0) < _chi2_mean_bound(3, N), n3.mean()
    # The same matrix taken as if it were already NED/FRD is badly inconsistent: the rotation matters.
    wrong = np.repeat(cov_enu_flu[None], N, axis=0)
    assert report.nees(e, wrong).mean() > 100.0


def test_score_reports_nees_and_nan_for_an_unknown_covariance():
    rng = np.random.default_rng(3)
    world = SimWorld(scenarios.get("paper-test1"))
    t = np.linspace(1.0, 9.0, 2000)
    p_true, q_true = world.truth_series("ardrone", t)
    cov = _random_spd(rng, np.array([0.02, 0.02, 0.04, 0.02, 0.02, 0.05]))
    T_true = frames.enu_flu_to_ned_frd(RigidTransform.from_components(p_true, Rotation.from_quat(q_true)))
    e = rng.multivariate_normal(np.zeros(6), cov, len(t))
    T_est = RigidTransform.from_components(
        T_true.translation + e[:, :3], T_true.rotation * Rotation.from_rotvec(e[:, 3:])
    )
    T_enu = frames.ned_frd_to_enu_flu(T_est)
    tri = np.tile(np.asarray(covariance_upper_triangle(cov)), (len(t), 1))
    track = report.Track(
        capture_s=t, arrival_s=t + 0.01, p_m=T_enu.translation, q_xyzw=T_enu.rotation.as_quat(),
        p_ned_m=T_est.translation, q_ned_frd_xyzw=T_est.rotation.as_quat(),
        covariance_ned_frd=report.covariance_from_upper_triangle(tri),
    )  # fmt: skip
    s = report.score("ardrone", "autopilot", track, world, 1.0, 10.0, 1.0)
    assert abs(s.position_nees - 3.0) < _chi2_mean_bound(3, len(t)), s.position_nees
    assert abs(s.pose_nees - 6.0) < _chi2_mean_bound(6, len(t)), s.pose_nees
    assert "NEES" in report.RunReport("x", 1, 0, "", {}, [s]).table()
    tri[:, 0] = np.nan  # MAVLink: NaN in the first element means the covariance is unknown
    track.covariance_ned_frd = report.covariance_from_upper_triangle(tri)
    s = report.score("ardrone", "autopilot", track, world, 1.0, 10.0, 1.0)
    assert np.isnan(s.position_nees) and np.isnan(s.pose_nees)


def test_nees_refuses_a_malformed_triangle_and_marks_a_singular_covariance():
    with pytest.raises(AtlasError, match="shape"):
        report.covariance_from_upper_triangle(np.zeros((2, 20)))
    assert np.isnan(report.nees(np.ones((1, 3)), np.zeros((1, 3, 3))))[0]


def test_availability_is_the_share_of_time_with_a_pose_at_most_fresh_s_old():
    every_100ms = np.arange(0.0, 1.0001, 0.1)  # poses until 1.0 s, then nothing
    assert fresh_share(every_100ms, 0.0, 2.0, 0.2) == pytest.approx(0.6, abs=0.005)  # fresh until 1.2 s
    # A 0.5 s hole in a 10 Hz stream: stale from 0.2 s after the last pose until the next one.
    holed = np.concatenate((np.arange(0.0, 0.95, 0.1), np.arange(1.4, 2.05, 0.1)))
    assert fresh_share(holed, 0.0, 2.0, 0.2) == pytest.approx(1.0 - 0.3 / 2.0, abs=0.005)
    # Gaps shorter than fresh_s cost nothing; a pose before t0 counts; none at all gives 0.
    assert fresh_share(np.arange(-0.1, 2.0, 0.15), 0.0, 2.0, 0.2) == 1.0
    assert fresh_share(np.zeros(0), 0.0, 2.0, 0.2) == 0.0
    # Order of arrivals does not matter.
    assert fresh_share(holed[::-1], 0.0, 2.0, 0.2) == fresh_share(holed, 0.0, 2.0, 0.2)


def test_autopilot_track_reads_both_messages_back_to_the_enu_pose_sent():
    rng = np.random.default_rng(5)
    n = 40
    T_enu = RigidTransform.from_components(rng.normal(size=(n, 3)), Rotation.random(n, random_state=5))
    T_ned = frames.enu_flu_to_ned_frd(T_enu)
    q = T_ned.rotation.as_quat()
    rpy = T_ned.rotation.as_euler("ZYX")[:, ::-1]
    records = []
    for k in range(n):
        odometry = k % 2 == 1  # ODOMETRY carries a quaternion, VISION_POSITION_ESTIMATE roll/pitch/yaw
        kind = "ODOMETRY" if odometry else "VISION_POSITION_ESTIMATE"
        angles = None if odometry else tuple(rpy[k])
        wxyz = (q[k, 3], *q[k, :3]) if odometry else None
        xyz = tuple(T_ned.translation[k])
        records.append(Received(10.0 + k, kind, int((5.0 + k) * 1e6), xyz, angles, wxyz, (0.0,) * 21, 0, 1, 197))
    track = autopilot_track(records, 2.0)
    np.testing.assert_allclose(track.p_m, T_enu.translation, atol=1e-12)
    dq = (Rotation.from_quat(track.q_xyzw).inv() * T_enu.rotation).magnitude()
    assert dq.max() < 1e-9
    np.testing.assert_allclose(track.capture_s, 3.0 + np.arange(n))
    np.testing.assert_allclose(track.arrival_s, 8.0 + np.arange(n))
    assert autopilot_track([], 0.0).p_m.shape == (0, 3)

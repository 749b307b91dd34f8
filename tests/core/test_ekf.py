"""The pose EKF against ground truth: convergence, prediction through gaps, gating, consistency."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.core.ekf import EkfSettings, PoseEkf


def R_of(sigma_p, sigma_r):
    return np.diag([sigma_p**2] * 3 + [sigma_r**2] * 3)


def noisy(rng, p, q, sigma_p, sigma_r):
    return p + rng.normal(0, sigma_p, 3), q * Rotation.from_rotvec(rng.normal(0, sigma_r, 3))


def test_static_pose_converges_below_measurement_noise():
    rng = np.random.default_rng(1)
    p_true, q_true = np.array([1.0, 2.0, 3.0]), Rotation.from_euler("ZYX", [40, 5, -3], degrees=True)
    ekf = PoseEkf(EkfSettings(accel_noise=0.1, angular_accel_noise=0.1))  # a vehicle that barely moves
    err_p, err_q = [], []
    for k in range(240):  # 8 s at 30 Hz
        z_p, z_q = noisy(rng, p_true, q_true, 0.02, 0.02)
        ekf.update(k / 30, z_p, z_q, R_of(0.02, 0.02))
        if k >= 120:
            err_p.append(ekf.p - p_true)
            err_q.append((ekf.q.inv() * q_true).as_rotvec())
    # Per-axis RMS error after convergence is well below the 2 cm / 0.02 rad of one measurement, and
    # agrees with the filter's own sigma.
    rms_p, rms_q = np.sqrt(np.mean(np.square(err_p))), np.sqrt(np.mean(np.square(err_q)))
    sigma_p = np.sqrt(ekf.P[0, 0])
    assert rms_p < 0.6 * 0.02 and rms_q < 0.6 * 0.02
    assert 0.5 * sigma_p < rms_p < 2.0 * sigma_p


def test_constant_velocity_is_tracked_and_predicted_through_a_gap():
    rng = np.random.default_rng(2)
    v = np.array([0.5, -0.2, 0.1])
    q_true = Rotation.from_euler("z", 30, degrees=True)
    ekf = PoseEkf(EkfSettings(accel_noise=0.3))
    for k in range(90):  # 3 s at 30 Hz
        t = k / 30
        ekf.update(t, *noisy(rng, v * t, q_true, 0.01, 0.01), R_of(0.01, 0.01))
    # 200 ms without measurements: the prediction stays close (the paper's "extrapolate the pose"),
    # within three of its own predicted sigmas, and its uncertainty grew while predicting.
    p, _, cov = ekf.pose_at(3.2)
    err = np.linalg.norm(p - v * 3.2)
    assert err < 0.04
    assert err < 3 * np.sqrt(np.trace(cov[:3, :3]))
    np.testing.assert_allclose(ekf.v, v, atol=0.1)
    assert np.trace(cov[:3, :3]) > np.trace(ekf.P[:3, :3])


def test_outlier_is_gated_and_changes_nothing():
    ekf = PoseEkf()
    q = Rotation.identity()
    for k in range(30):
        ekf.update(k / 30, np.zeros(3), q, R_of(0.01, 0.01))
    before = (ekf.p.copy(), ekf.q.as_quat().copy(), ekf.P.copy())
    assert ekf.update(1.0, np.array([1.0, 0, 0]), q, R_of(0.01, 0.01)) == "gated"  # 1 m jump at 1 cm sigma
    assert ekf.gated == 1
    # A flipped orientation (the planar ambiguity) is gated too.
    assert ekf.update(1.0, np.zeros(3), Rotation.from_euler("x", 40, degrees=True), R_of(0.01, 0.01)) == "gated"
    np.testing.assert_array_equal(ekf.p, before[0])
    np.testing.assert_array_equal(ekf.q.as_quat(), before[1])
    np.testing.assert_array_equal(ekf.P, before[2])


def test_sign_of_measured_quaternion_does_not_matter():
    a, b = PoseEkf(), PoseEkf()
    q = Rotation.from_euler("ZYX", [10, 20, 30], degrees=True)
    q_neg = Rotation.from_quat(-q.as_quat())
    for k in range(10):
        a.update(k / 30, np.zeros(3), q, R_of(0.01, 0.01))
        b.update(k / 30, np.zeros(3), q_neg if k % 2 else q, R_of(0.01, 0.01))
    assert (a.q.inv() * b.q).magnitude() < 1e-9


def test_late_measurement_is_dropped_and_long_gap_resets():
    ekf = PoseEkf()
    for k in range(10):
        ekf.update(k / 30, np.zeros(3), Rotation.identity(), R_of(0.01, 0.01))
    assert ekf.update(0.0, np.zeros(3), Rotation.identity(), R_of(0.01, 0.01)) == "late"
    assert ekf.update(5.0, np.array([3.0, 0, 0]), Rotation.identity(), R_of(0.01, 0.01)) == "reset"
    np.testing.assert_array_equal(ekf.p, [3.0, 0, 0])


def simulate_truth(rng, settings, n, dt):
    """Truth drawn from the filter's own motion model: white acceleration and angular acceleration."""
    p, v = np.zeros(3), rng.normal(0, 0.3, 3)
    q, w = Rotation.random(random_state=int(rng.integers(1 << 31))), rng.normal(0, 0.3, 3)
    out = []
    for _ in range(n):
        out.append((p.copy(), q))
        for sd, vec in ((settings.accel_noise, "p"), (settings.angular_accel_noise, "q")):
            # Exact discretisation of white (angular) acceleration over dt, per axis.
            cov = sd**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
            d = rng.multivariate_normal([0, 0], cov, 3)
            if vec == "p":
                p, v = p + v * dt + d[:, 0], v + d[:, 1]
            else:
                q, w = q * Rotation.from_rotvec(w * dt + d[:, 0]), w + d[:, 1]
    return out


@pytest.mark.parametrize("seed", [3, 4])
def test_nees_is_consistent(seed):
    """Normalised estimation error squared of the 6-dof pose averages near its dimension (6) when the
    truth follows the filter's model (the textbook consistency check)."""
    rng = np.random.default_rng(seed)
    settings = EkfSettings()
    dt, n = 1 / 30, 90
    nees = []
    for _ in range(30):
        ekf = PoseEkf(settings)
        truth = simulate_truth(rng, settings, n, dt)
        for k, (p, q) in enumerate(truth):
            ekf.update(k * dt, *noisy(rng, p, q, 0.02, 0.02), R_of(0.02, 0.02))
        p_est, q_est, cov = ekf.pose_at((n - 1) * dt)
        p_true, q_true = truth[-1]
        e = np.concatenate([p_est - p_true, (q_est.inv() * q_true).as_rotvec()])
        nees.append(float(e @ np.linalg.solve(cov, e)))
    # 30 runs of a 6-dof chi-square: the mean lies in [4.3, 7.9] with 99 % probability.
    assert 4.3 < np.mean(nees) < 7.9, np.mean(nees)

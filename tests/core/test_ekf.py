"""The pose EKF against ground truth: convergence, prediction through gaps, gating, consistency."""

import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from atlas_onboard.config import FusionConfig
from atlas_onboard.core.covariance import skew
from atlas_onboard.core.ekf import EkfSettings, PoseEkf
from tests.core.trajectories import oscillating

MS = 1_000_000


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
    assert ekf.outcomes["gated"] == 1
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


def floor_tag_covariance(q):
    """A camera 1.5 m over floor tags: its lateral position error is its tilt error swung over the height
    (strongly correlated with the attitude error), plus a little independent noise."""
    L = 1.5 * skew(np.array([0.0, 0.0, 1.0])) @ q.as_matrix()
    s_th = np.radians(np.diag([0.3, 0.3, 0.2])) ** 2
    s_n = np.diag([1.0, 1.0, 3.0]) ** 2 * 1e-6
    return np.block([[L @ s_th @ L.T + s_n, L @ s_th], [s_th @ L.T, s_th]])


def test_default_accel_noise_on_an_oscillating_drone():
    """With the default ekf_accel_noise (the constant-velocity filter, without the manoeuvre model the
    node adds), on an oscillating drone seen at
    30 Hz with correlated position/attitude errors: the filter beats the raw measurements, its covariance
    is honest, and so is its 0.1 s prediction."""
    rng = np.random.default_rng(0)
    ekf = PoseEkf(EkfSettings(accel_noise=FusionConfig().ekf_accel_noise, max_gap_s=0.5, constant_rate=False))
    raw, filt, nees_f, pred, nees_p = [], [], [], [], []
    for k in range(600):
        t = k / 30
        p, q = oscillating(t)
        R = floor_tag_covariance(q)
        e = rng.multivariate_normal(np.zeros(6), R)
        ekf.update(t, p + e[:3], q * Rotation.from_rotvec(e[3:]), R)
        if t < 2.0:
            continue
        raw.append(e[:3])
        d = p - ekf.p
        filt.append(d)
        nees_f.append(d @ np.linalg.solve(ekf.P[:3, :3], d))
        p_pred, _, cov = ekf.pose_at(t + 0.1)
        d = oscillating(t + 0.1)[0] - p_pred
        pred.append(d)
        nees_p.append(d @ np.linalg.solve(cov[:3, :3], d))

    def rmse(a):
        return float(np.sqrt(np.mean(np.sum(np.square(a), axis=1))))

    assert rmse(filt) < 0.8 * rmse(raw), (rmse(filt), rmse(raw))
    assert 1.5 < np.mean(nees_f) < 4.5, np.mean(nees_f)
    assert rmse(pred) < 0.032, rmse(pred)
    assert 1.5 < np.mean(nees_p) < 4.5, np.mean(nees_p)


def node_settings() -> EkfSettings:
    """The filter settings the node runs with ``fusion.filter: ekf`` and default keys."""
    from atlas_onboard.config import parse_world
    from atlas_onboard.node.output import make_ekf

    bank = make_ekf(parse_world({"fusion": {"filter": "ekf"}, "entities": {"world": {}}}))
    assert bank is not None
    return bank.settings


def singer_truth(rng, t_s, sigma=1.5, tau=0.5, jitter=0.5):
    """A quadrotor's manoeuvring flight sampled at ``t_s``: an acceleration that is a stationary
    Gauss-Markov process (spread ``sigma`` m/s^2 per axis, about a 9 degree tilt, correlation time
    ``tau`` s) plus white acceleration (``jitter``, m/s^2/sqrt(Hz)), integrated finely."""
    dt = 0.002
    n = round(t_s[-1] / dt) + 1
    a0 = rng.normal(0, sigma, 3)
    v0, p0 = rng.normal(0, 0.5, 3), np.zeros(3)
    decay, kick = np.exp(-dt / tau), sigma * np.sqrt(1 - np.exp(-2 * dt / tau))
    # The steps' draws in the order a step-by-step loop takes them (its velocity's jitter, then its
    # acceleration's kick), the recursions as a filter and sums: the same flight, in one pass.
    noise = rng.normal(size=(n, 2, 3))
    a = lfilter([1.0], [1.0, -decay], np.vstack([a0, kick * noise[:-1, 1]]), axis=0)  # a_0 .. a_(n-1)
    v = v0 + np.vstack([np.zeros(3), np.cumsum(a * dt + jitter * np.sqrt(dt) * noise[:, 0], axis=0)])  # v_0 .. v_n
    p = p0 + np.vstack([np.zeros(3), np.cumsum(v[:-1] * dt + 0.5 * a * dt**2, axis=0)])  # p_0 .. p_n
    return p[np.searchsorted(np.arange(n) * dt + 1e-9, t_s)]  # each time's first step at or after it


def gap_end_nees(settings, truth_of, rng, gaps_s, runs, sigma_m=0.003):
    """Mean position NEES of the filter's prediction at the end of each gap length: 1.5 s of 30 Hz
    measurements (``sigma_m`` noise), then nothing for the gap."""
    R = np.diag([sigma_m**2] * 3 + [np.radians(0.3) ** 2] * 3)
    means = {}
    for gap in gaps_s:
        nees = []
        for _ in range(runs):
            t_meas = np.arange(45) / 30
            t_all = np.append(t_meas, t_meas[-1] + gap)
            p_true = truth_of(rng, t_all)
            ekf = PoseEkf(settings)
            for t, p in zip(t_meas, p_true[:-1], strict=True):
                ekf.update(float(t), p + rng.normal(0, sigma_m, 3), Rotation.identity(), R)
            p_pred, _, cov = ekf.pose_at(float(t_all[-1]))
            d = p_pred - p_true[-1]
            nees.append(d @ np.linalg.solve(cov[:3, :3], d))
        means[gap] = float(np.mean(nees))
    return means


def test_prediction_covariance_is_honest_at_the_end_of_a_gap():
    """The node's filter, on drones manoeuvring as a quadrotor does (random accelerations of 1.5 m/s^2
    lasting about 0.5 s, and jitter): the position NEES of its prediction at the end of gaps of 0.1-0.5 s
    is chi-square with 3 degrees of freedom (a constant-velocity filter with 0.5 m/s^2 of white
    acceleration was 3-4 times overconfident, and more so the longer the gap)."""
    means = gap_end_nees(node_settings(), singer_truth, np.random.default_rng(11), (0.1, 0.3, 0.5), runs=60)
    # The mean of 60 chi-square(3) draws lies in [2.2, 3.9] with 99.7 % probability (std 0.32).
    assert all(2.2 < m < 3.9 for m in means.values()), means


def test_prediction_through_a_gap_on_a_figure_eight_is_not_overconfident():
    """A figure-eight flown in 6 s (1.5 m x 0.75 m, accelerations up to 3.3 m/s^2, known in closed
    form): the node filter's predictions 0.1-0.5 s into a gap are at most as far off as their
    covariance says (NEES3 at most about 3; it may be cautious on so smooth a path), and the NEES does not
    grow with the gap (the constant-velocity filter went from 3 to 8 between 0.1 and 0.5 s)."""
    w = 2 * np.pi / 6

    def figure_eight(r, t):
        t = t + r.uniform(0, 6)
        return np.stack([1.5 * np.sin(w * t), 0.75 * np.sin(2 * w * t), 1.2 + 0.1 * np.sin(0.5 * w * t)], axis=1)

    means = gap_end_nees(node_settings(), figure_eight, np.random.default_rng(12), (0.1, 0.3, 0.5), runs=40)
    assert all(m < 3.9 for m in means.values()), means
    assert means[0.5] < 2 * means[0.1], means


def manoeuvring_pose(rng, t_s, sigma=1.5, tau=0.5, yaw_sigma=0.15):
    """Positions and attitudes (FLU) of a quadrotor manoeuvring as :func:`singer_truth`'s: its roll and
    pitch are the tilt its acceleration needs (thrust along a + g), its heading swings as a stationary
    Gauss-Markov process (``yaw_sigma`` rad, correlation time ``tau``)."""
    dt = 0.005
    n = round(t_s[-1] / dt) + 2  # a step past the last time, which rounding may put after n - 1 steps
    a0, v0, p0 = rng.normal(0, sigma, 3), rng.normal(0, 0.5, 3), np.zeros(3)
    yaw0 = rng.normal(0, yaw_sigma)
    decay = np.exp(-dt / tau)
    kick, yaw_kick = sigma * np.sqrt(1 - decay**2), yaw_sigma * np.sqrt(1 - decay**2)
    # As singer_truth: each step's draws (velocity jitter, acceleration kick, heading kick) in a loop's order.
    noise = rng.normal(size=(n, 7))
    a = lfilter([1.0], [1.0, -decay], np.vstack([a0, kick * noise[:-1, 3:6]]), axis=0)
    yaw = lfilter([1.0], [1.0, -decay], np.append(yaw0, yaw_kick * noise[:-1, 6]))
    v = v0 + np.vstack([np.zeros(3), np.cumsum(a[:-1] * dt + 0.5 * np.sqrt(dt) * noise[:-1, :3], axis=0)])
    p = p0 + np.vstack([np.zeros(3), np.cumsum(v[:-1] * dt + 0.5 * a[:-1] * dt**2, axis=0)])
    k = np.searchsorted(np.arange(n) * dt + 1e-9, t_s)
    thrust = a[k] + np.array([0.0, 0.0, 9.81])
    pitch = np.arctan2(np.hypot(thrust[:, 0], 0.0) * np.sign(thrust[:, 0]), thrust[:, 2])
    roll = np.arctan2(-thrust[:, 1], np.hypot(thrust[:, 0], thrust[:, 2]))
    return p[k], Rotation.from_euler("ZYX", np.column_stack([yaw[k], pitch, roll]))


def test_prediction_pose_covariance_is_honest_at_the_end_of_a_gap():
    """The 6x6 of the node's filter at the end of a gap, not only its position block. The
    filter holds the attitude through a gap; the drone's tilt follows its manoeuvre meanwhile. The pose
    NEES (position and attitude) of the prediction at the end of 0.1-0.5 s gaps is chi-square with 6
    degrees of freedom (with a random walk of 1 rad/s/sqrt(Hz) the attitude block was tens of times too
    cautious, which hid the position's errors in the 6x6: a pose NEES near 3)."""
    settings = node_settings()
    rng = np.random.default_rng(21)
    sigma_m, sigma_rad = 0.003, np.radians(0.5)
    R = np.diag([sigma_m**2] * 3 + [sigma_rad**2] * 3)
    for gap in (0.1, 0.3, 0.5):
        nees = []
        for _ in range(60):
            t_meas = np.arange(45) / 30
            t_all = np.append(t_meas, t_meas[-1] + gap)
            p_true, q_true = manoeuvring_pose(rng, t_all)
            ekf = PoseEkf(settings)
            for k, t in enumerate(t_meas):
                q_meas = q_true[k] * Rotation.from_rotvec(rng.normal(0, sigma_rad, 3))
                ekf.update(float(t), p_true[k] + rng.normal(0, sigma_m, 3), q_meas, R)
            p_pred, q_pred, cov = ekf.pose_at(float(t_all[-1]))
            e = np.concatenate([p_true[-1] - p_pred, (q_pred.inv() * q_true[-1]).as_rotvec()])
            nees.append(float(e @ np.linalg.solve(cov, e)))
        # The mean of 60 chi-square(6) draws lies in [4.6, 7.4] with 99.7 % probability (std 0.45).
        assert 4.6 < np.mean(nees) < 7.4, (gap, np.mean(nees))

"""The camera's time model: rows' instants, corners moved to the stamp, the motion's covariance."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.shutter import (
    GYRO_SIGMA_RAD_S,
    RATE_CHANGE_RAD_S2,
    CameraMotion,
    RateHistory,
    RowClock,
    from_stamp,
    motion_covariance,
    planar_depths,
    square_to_stamp,
    to_stamp,
)

F, CX, CY, W, H = 500.0, 320.0, 240.0, 640, 480
SIZE = 0.2
OBJ = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]], dtype=float) * SIZE / 2


def tag_at_stamp(rng: np.random.Generator) -> np.ndarray:
    """A tag's corners (4, 3) in the camera frame at the stamp: 0.7-1.5 m ahead, tilted, anywhere in view."""
    R = Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, 3)) * Rotation.from_euler("x", np.pi)
    p = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.25, 0.25), rng.uniform(0.7, 1.5)])
    return R.apply(np.hstack([OBJ, np.zeros((4, 1))])) + p


def rolling_projection(P0: np.ndarray, omega: np.ndarray, v: np.ndarray, clock: RowClock) -> tuple:
    """Each corner projected at its own row's instant, found by iterating t = dt(row(projection at t))
    to convergence: the exact rolling-shutter image of points ``P0`` (camera frame at the stamp)."""
    px, dts = [], []
    for P in P0:
        t = 0.0
        for _ in range(50):
            Pt = Rotation.from_rotvec(-omega * t).apply(P - v * t)
            uv = F * Pt[:2] / Pt[2] + [CX, CY]
            t_new = float(clock.dt_s(np.array([uv[1]]))[0])
            if abs(t_new - t) < 1e-12:
                break
            t = t_new
        px.append(uv)
        dts.append(t)
    return np.array(px), np.array(dts)


def normalised(px: np.ndarray) -> np.ndarray:
    return (px - [CX, CY]) / F


def test_row_instants_follow_the_readout() -> None:
    clock = RowClock(0.025, H)
    assert np.allclose(clock.dt_s(np.array([0.0, (H - 1) / 2, H - 1.0])), [-0.0125, 0.0, 0.0125])
    assert np.allclose(RowClock(0.025, H, bottom_up=True).dt_s(np.array([0.0])), [0.0125])
    assert np.all(RowClock(0.0, H).dt_s(np.array([0.0, 479.0])) == 0.0)


def test_compensated_corners_match_the_stamp_projection() -> None:
    """A tag seen by a camera turning at up to ~60 deg/s and moving at ~1 m/s through a 25 ms readout:
    the corners moved to the stamp are where a global shutter at the stamp sees them, to far below 0.05 px,
    though the shear itself is pixels."""
    rng = np.random.default_rng(7)
    clock = RowClock(0.025, H)
    worst, shear = 0.0, 0.0
    for _ in range(200):
        P0 = tag_at_stamp(rng)
        omega = rng.uniform(-1.0, 1.0, 3)
        v = rng.uniform(-1.0, 1.0, 3)
        seen, _ = rolling_projection(P0, omega, v, clock)
        truth = F * P0[:, :2] / P0[:, 2:] + [CX, CY]
        motion = CameraMotion(omega, np.zeros((3, 3)), v, np.zeros((3, 3)), True, True)
        x0, _ = square_to_stamp(normalised(seen), OBJ, clock.dt_s(seen[:, 1]), motion)
        worst = max(worst, float(np.abs(F * x0 + [CX, CY] - truth).max()))
        shear = max(shear, float(np.abs(seen - truth).max()))
    assert shear > 2.0
    assert worst < 0.005


def test_planar_depths_are_exact_for_a_perspective_image() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        P = tag_at_stamp(rng)
        z = planar_depths(P[:, :2] / P[:, 2:], OBJ)
        assert z is not None and np.allclose(z, P[:, 2], rtol=1e-9)


def _motion_draw(rng: np.random.Generator) -> tuple:
    omega = rng.uniform(-1.0, 1.0, 3)
    v = rng.uniform(-1.0, 1.0, 3)
    return omega, v


def test_rate_and_velocity_errors_have_the_covariance_said() -> None:
    """Monte Carlo: rates with noise and bias, velocity with its error, a stamp off by its sigma: the
    corrected corners' error against the stamp projection has a NEES (8 dof, against the motion's
    covariance plus a small corner noise) whose mean is 8 within three standard errors."""
    rng = np.random.default_rng(11)
    clock = RowClock(0.025, H)
    sigma_w, bias_w, sigma_v, sigma_t, sigma_px = 0.02, 0.03, 0.1, 0.002, 0.02
    w_cov = (sigma_w**2 + bias_w**2) * np.eye(3)
    v_cov = sigma_v**2 * np.eye(3)
    nees = []
    for _ in range(1500):
        P0 = tag_at_stamp(rng)
        omega, v = _motion_draw(rng)
        tau = rng.normal(0.0, sigma_t)  # the true stamp is tau after the one the node has
        # What the camera saw: rows at dt + tau after the node's stamp; truth is the node's stamp's view.
        P_true_stamp = Rotation.from_rotvec(-omega * tau).apply(P0 - v * tau)
        shifted = RowClock(clock.readout_s, H)
        seen, _ = rolling_projection(P_true_stamp, omega, v, shifted)
        seen = seen + rng.normal(0.0, sigma_px, seen.shape)
        measured = CameraMotion(
            omega + rng.normal(0.0, sigma_w, 3) + rng.normal(0.0, bias_w, 3),
            w_cov,
            v + rng.normal(0.0, sigma_v, 3),
            v_cov,
            True,
            True,
            sigma_t,
        )
        dt = clock.dt_s(seen[:, 1])
        x0, z = square_to_stamp(normalised(seen), OBJ, dt, measured)
        truth = F * P0[:, :2] / P0[:, 2:] + [CX, CY]
        C = motion_covariance(x0, z, dt, measured, F, F) + sigma_px**2 * np.eye(8)
        r = (F * x0 + [CX, CY] - truth).ravel()
        nees.append(float(r @ np.linalg.solve(C, r)))
    nees = np.array(nees)
    se = nees.std() / np.sqrt(len(nees))
    assert abs(nees.mean() - 8.0) < 3.0 * se, (nees.mean(), se)


def test_without_rates_the_covariance_covers_the_shear() -> None:
    """No rate from the autopilot: the corners are left sheared, the rate known only as a bound (its
    value with a covariance); at least 99 % of corners within 3 sigma of the stamp projection per axis."""
    rng = np.random.default_rng(5)
    clock = RowClock(0.025, H)
    bound = np.radians(30.0)
    inside, n = 0, 0
    for _ in range(1000):
        P0 = tag_at_stamp(rng)
        omega = rng.normal(0.0, bound, 3)
        v = rng.uniform(-1.0, 1.0, 3)
        seen, _ = rolling_projection(P0, omega, v, clock)
        v_seen = v + rng.normal(0, 0.1, 3)
        motion = CameraMotion(np.zeros(3), bound**2 * np.eye(3), v_seen, 0.01 * np.eye(3), False, True)
        dt = clock.dt_s(seen[:, 1])
        x0, z = square_to_stamp(normalised(seen), OBJ, dt, motion)
        truth = F * P0[:, :2] / P0[:, 2:] + [CX, CY]
        sigma = np.sqrt(np.diag(motion_covariance(x0, z, dt, motion, F, F)) + 0.01**2)
        err = np.abs(F * x0 + [CX, CY] - truth).ravel()
        inside += int(np.sum(err <= 3 * sigma))
        n += err.size
    assert inside / n >= 0.99, inside / n


def test_a_rate_error_shears_corners_coherently() -> None:
    """The rate's error moves every corner together: its covariance is correlated, of rank 3, not diagonal."""
    x = np.array([[-0.1, -0.2], [0.1, -0.2], [0.1, 0.2], [-0.1, 0.2]])
    dt = RowClock(0.025, H).dt_s(F * x[:, 1] + CY)
    C = motion_covariance(x, np.ones(4), dt, CameraMotion(np.zeros(3), 0.01 * np.eye(3), omega_known=True), F, F)
    assert np.linalg.matrix_rank(C, tol=1e-9 * np.abs(C).max()) == 3
    assert abs(C[1, 5]) > 0.5 * np.sqrt(C[1, 1] * C[5, 5])


finite = st.floats(-3.0, 3.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)


@settings(max_examples=60, deadline=None)
@given(vec3, vec3, st.floats(0.0, 0.05), st.integers(0, 10_000))
def test_to_stamp_then_back_is_identity(omega: np.ndarray, v: np.ndarray, readout: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    P = tag_at_stamp(rng)
    x = P[:, :2] / P[:, 2:]
    dt = RowClock(readout, H).dt_s(F * x[:, 1] + CY)
    motion = CameraMotion(omega, np.zeros((3, 3)), v, np.zeros((3, 3)), True, True)
    x0 = to_stamp(x, P[:, 2], dt, motion)
    P0 = Rotation.from_rotvec(dt[:, None] * omega).apply(P) + dt[:, None] * v
    back = from_stamp(x0, P0[:, 2], dt, motion)
    assert np.allclose(back, x, atol=1e-10)


@settings(max_examples=60, deadline=None)
@given(vec3, vec3, st.integers(0, 10_000))
def test_zero_readout_or_zero_motion_is_identity(omega: np.ndarray, v: np.ndarray, seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 0.5, (4, 2))
    moving = CameraMotion(omega, np.eye(3), v, np.eye(3), True, True)
    still = CameraMotion(np.zeros(3), np.zeros((3, 3)), np.zeros(3), np.zeros((3, 3)), True, True)
    zero = RowClock(0.0, H).dt_s(F * x[:, 1] + CY)
    some = RowClock(0.03, H).dt_s(F * x[:, 1] + CY)
    assert np.allclose(to_stamp(x, np.ones(4), zero, moving), x, atol=1e-14)
    assert np.allclose(to_stamp(x, np.ones(4), some, still), x, atol=1e-14)
    assert np.allclose(motion_covariance(x, np.ones(4), zero, moving, F, F), 0.0)


@settings(max_examples=60, deadline=None)
@given(vec3, st.integers(0, 10_000))
def test_rate_from_either_sign_of_the_quaternion(omega: np.ndarray, seed: int) -> None:
    """A rate is the same whichever sign the attitude quaternions it came from carry."""
    rng = np.random.default_rng(seed)
    q0 = Rotation.random(random_state=seed).as_quat()
    R0 = Rotation.from_quat(q0)
    R1 = R0 * Rotation.from_rotvec(omega * 0.02)
    w_pos = (Rotation.from_quat(q0).inv() * Rotation.from_quat(R1.as_quat())).as_rotvec() / 0.02
    w_neg = (Rotation.from_quat(-q0).inv() * Rotation.from_quat(-R1.as_quat())).as_rotvec() / 0.02
    x = rng.uniform(-0.5, 0.5, (4, 2))
    dt = RowClock(0.025, H).dt_s(F * x[:, 1] + CY)
    a = to_stamp(x, np.ones(4), dt, CameraMotion(w_pos, omega_known=True))
    b = to_stamp(x, np.ones(4), dt, CameraMotion(w_neg, omega_known=True))
    assert np.allclose(a, b, atol=1e-12)
    assert np.allclose(w_pos, omega, atol=1e-9)


def test_a_rate_asked_for_before_its_next_sample_is_predicted_with_the_sigma_it_has() -> None:
    """A drone swaying at 1.1 Hz (0.5 rad/s on each axis), its gyro read at 25 Hz with 0.015 rad/s of
    noise per sample, each reading arriving 15 ms late: a camera asks for the rate at its stamp, before
    the next reading has come (15-55 ms after the newest). The rate returned is nearer the truth than
    the newest reading is (the rate has changed since), and its covariance is honest: >= 97 % within
    3 sigma on every axis, with a sigma at most half of that of a rate changing at the a-priori bound."""
    rng = np.random.default_rng(3)
    phase = rng.uniform(0.0, 2.0 * np.pi, 3)

    def truth(t_s: float) -> np.ndarray:
        return 0.5 * np.sin(2.0 * np.pi * 1.1 * t_s + phase)

    history = RateHistory()
    period, delay = 0.04, 0.015
    errors, held, sigmas, bounds, inside = [], [], [], [], []
    newest = None
    for k in range(400):
        t_s = k * period
        newest = (t_s, truth(t_s) + rng.normal(0.0, 0.015, 3))
        history.add(round((t_s + delay) * 1e6), newest[1])
        for ask in rng.uniform(t_s + delay, t_s + period + delay, 2):  # before the next reading arrives
            rate = history.rate_at(round(ask * 1e6))
            if k < 10 or rate is None:
                continue
            e = rate.omega_flu - truth(ask - delay)  # the readings' stamps carry the send delay
            sd = np.sqrt(np.diag(rate.cov))
            errors.append(e)
            held.append(newest[1] - truth(ask - delay))
            sigmas.append(sd[0])
            age_s = ask - (t_s + delay)
            bounds.append(np.sqrt(GYRO_SIGMA_RAD_S**2 + (RATE_CHANGE_RAD_S2 * age_s) ** 2))
            inside.append(np.abs(e) <= 3.0 * sd)
    assert len(errors) > 700
    assert np.sqrt(np.mean(np.square(errors))) < np.sqrt(np.mean(np.square(held)))
    assert np.mean(inside, axis=0).min() >= 0.97, np.mean(inside, axis=0)
    assert np.median(np.array(sigmas) / np.array(bounds)) <= 0.5

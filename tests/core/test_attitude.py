"""The gravity check of a single tag's two solutions and the attitude history."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.attitude import (
    AttitudeHistory,
    CameraTurn,
    TiltVerdict,
    choose_by_tilt,
    tilt_error_rad,
    up_in_body,
)

DEG = math.pi / 180


@given(st.floats(-60, 60), st.floats(-60, 60), st.floats(-180, 180))
def test_tilt_error_ignores_heading(roll, pitch, yaw):
    R = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True)
    R_other_heading = Rotation.from_euler("z", 77, degrees=True) * R
    assert tilt_error_rad(R_other_heading, up_in_body(R))[0] < 1e-7


@given(st.floats(-60, 60), st.floats(0.0, 40.0), st.floats(0, 360))
def test_tilt_error_is_the_angle_tilted(roll, extra, axis_deg):
    R = Rotation.from_euler("x", roll, degrees=True)
    axis = np.array([math.cos(axis_deg * DEG), math.sin(axis_deg * DEG), 0.0])  # a horizontal axis
    tilted = Rotation.from_rotvec(axis * extra * DEG) * R
    assert tilt_error_rad(tilted, up_in_body(R))[0] == pytest.approx(extra * DEG, abs=1e-7)


def test_the_solution_that_agrees_with_gravity_wins_and_neither_is_rejected():
    truth = Rotation.from_euler("ZYX", [40, 5, -3], degrees=True)
    flip = Rotation.from_euler("y", 25, degrees=True) * truth
    up = up_in_body(truth)
    assert choose_by_tilt(truth, flip, up, 0.01).verdict is TiltVerdict.PRIMARY
    assert choose_by_tilt(flip, truth, up, 0.01).verdict is TiltVerdict.ALT
    both_off = Rotation.from_euler("x", 30, degrees=True) * truth
    assert choose_by_tilt(flip, both_off, up, 0.01).verdict is TiltVerdict.NEITHER
    # Two solutions that differ by a turn about the vertical: gravity cannot tell them apart.
    turned = Rotation.from_euler("z", 30, degrees=True) * truth
    assert choose_by_tilt(truth, turned, up, 0.01).verdict is TiltVerdict.BOTH
    # An observation too uncertain in attitude to be judged: both agree, nothing decided.
    assert choose_by_tilt(truth, flip, up, 0.5).verdict is TiltVerdict.BOTH


def test_history_interpolates_and_says_none_outside_its_samples():
    h = AttitudeHistory(max_gap_us=100_000)
    assert h.attitude_at(0) is None
    h.add(1_000_000, Rotation.from_euler("x", 0, degrees=True))
    h.add(1_040_000, Rotation.from_euler("x", 4, degrees=True))
    h.add(1_030_000, Rotation.from_euler("x", 50, degrees=True))  # out of order: ignored
    assert h.attitude_at(1_010_000).as_euler("xyz", degrees=True)[0] == pytest.approx(1.0)
    assert h.attitude_at(1_040_000 + 50_000) is not None
    assert h.attitude_at(1_040_000 + 50_001) is None  # the stream stopped
    assert h.attitude_at(1_000_000 - 50_001) is None  # before the first sample
    h.add(1_400_000, Rotation.identity())
    assert h.attitude_at(1_200_000) is None  # inside a gap longer than max_gap_us


@given(
    st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(-1.5, 1.5)),
    st.integers(1, 39_999),
    st.integers(20_000, 60_000),
)
def test_with_rates_a_capture_gets_the_same_attitude_before_and_after_the_next_sample_arrives(
    omega, after_us, period_us
):
    # A drone turning at a constant body rate, sampled with its rate: the attitude at a capture between
    # two samples is the earlier one turned on by its rate, the truth, whether the later one is there yet.
    omega = np.array(omega)
    R_start = Rotation.from_euler("ZYX", [40, 5, -3], degrees=True)

    def truth(t_us):
        return R_start * Rotation.from_rotvec(omega * t_us * 1e-6)

    t_capture = 1_000_000 + min(after_us, period_us - 1)
    h = AttitudeHistory()
    for t in (1_000_000 - period_us, 1_000_000):
        h.add(t, truth(t), omega)
    before = h.attitude_at(t_capture)
    h.add(1_000_000 + period_us, truth(1_000_000 + period_us), omega)
    after = h.attitude_at(t_capture)
    assert np.allclose(before.as_matrix(), after.as_matrix(), atol=1e-12)
    assert (before.inv() * truth(t_capture)).magnitude() < 1e-9


def test_without_rates_the_history_interpolates_and_with_rates_it_turns_the_sample_before_on():
    h = AttitudeHistory()
    h.add(0, Rotation.identity())
    h.add(40_000, Rotation.from_euler("x", 4, degrees=True))
    assert h.attitude_at(10_000).as_euler("xyz", degrees=True)[0] == pytest.approx(1.0)  # slerp: no rates
    rated = AttitudeHistory()
    rated.add(0, Rotation.identity(), np.array([math.radians(50.0), 0.0, 0.0]))  # 50 deg/s about x
    rated.add(40_000, Rotation.from_euler("x", 4, degrees=True), np.array([math.radians(50.0), 0.0, 0.0]))
    assert rated.attitude_at(10_000).as_euler("xyz", degrees=True)[0] == pytest.approx(0.5)  # 10 ms at 50 deg/s
    assert rated.attitude_at(40_000 + 100_000).as_euler("xyz", degrees=True)[0] == pytest.approx(9.0)
    assert rated.attitude_at(40_000 + 100_001) is None  # beyond max_gap_us of the newest sample
    rated.add(50_000, Rotation.identity(), np.array([np.nan, 0.0, 0.0]))  # a non-finite rate: none
    assert rated.attitude_at(50_000 + 50_001) is None  # held no longer than half the gap


def _pose_scene(seed: int):
    rng = np.random.default_rng(seed)
    R_world_marker = Rotation.from_euler("xz", [rng.choice([0.0, 90.0]), rng.uniform(0, 360)], degrees=True)
    R_body_sensor = Rotation.from_euler("y", rng.uniform(30, 90), degrees=True) * Rotation.from_euler(
        "zx", [-90, -90], degrees=True
    )
    R_sm_true = Rotation.from_euler(
        "zxz", [rng.uniform(0, 360), 180 + rng.uniform(5, 40), rng.uniform(0, 360)], degrees=True
    )
    p_true = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(1.0, 3.0)])
    return R_world_marker, R_body_sensor, R_sm_true, p_true


@pytest.mark.parametrize("seed", range(6))
def test_constrain_tilt_pulls_a_tilted_single_tag_back_along_its_coupling(seed):
    from atlas_onboard.core.attitude import TagPose, constrain_tilt

    R_wm, R_bs, R_sm_true, p_true = _pose_scene(seed)
    up = up_in_body(R_wm * R_sm_true.inv() * R_bs.inv())
    # A detection off by a tilt d about the marker's x axis at the right position (a single tag's image
    # position is well determined, its tilt is not): the camera, seen from the marker, is off by range x d.
    # The covariance says that the tilt is poorly known.
    d = np.array([math.radians(3.0), 0.0, 0.0])
    R_sm = R_sm_true * Rotation.from_rotvec(d)
    C = np.diag([1e-8] * 3 + [math.radians(3.0) ** 2, math.radians(3.0) ** 2, 1e-6])
    tag = TagPose(p_true, R_sm.as_matrix(), C)
    new = constrain_tilt(tag, R_bs.as_matrix(), R_wm.as_matrix(), up, math.radians(0.3))

    def camera_in_marker(R, p):
        return -R.inv().apply(p)

    c_true = camera_in_marker(R_sm_true, p_true)
    err_before = np.linalg.norm(camera_in_marker(R_sm, p_true) - c_true)
    err_after = np.linalg.norm(
        camera_in_marker(Rotation.from_matrix(new.R_sensor_marker), new.p_sensor_marker_m) - c_true
    )
    ang_after = (Rotation.from_matrix(new.R_sensor_marker).inv() * R_sm_true).magnitude()
    assert err_after < 0.25 * err_before and ang_after < 0.25 * d[0]
    assert np.all(np.linalg.eigvalsh(new.covariance) > 0)
    assert np.trace(new.covariance) < np.trace(C)


def test_constrain_tilt_with_the_implied_up_changes_nothing_but_the_covariance():
    from atlas_onboard.core.attitude import TagPose, constrain_tilt

    R_wm, R_bs, R_sm, p = _pose_scene(9)
    up = up_in_body(R_wm * R_sm.inv() * R_bs.inv())
    C = np.diag([1e-4] * 3 + [1e-3] * 3)
    new = constrain_tilt(TagPose(p, R_sm.as_matrix(), C), R_bs.as_matrix(), R_wm.as_matrix(), up)
    np.testing.assert_allclose(new.p_sensor_marker_m, p, atol=1e-12)
    np.testing.assert_allclose(new.R_sensor_marker, R_sm.as_matrix(), atol=1e-12)
    # Yaw (about world up) stays as uncertain as it was; the tilt shrinks.
    assert np.trace(new.covariance[3:, 3:]) < np.trace(C[3:, 3:])


rotations = st.tuples(st.floats(-180, 180), st.floats(-80, 80), st.floats(-180, 180)).map(
    lambda a: Rotation.from_euler("ZYX", a, degrees=True)
)


@given(rotations, rotations, rotations, st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.1, 1)))
def test_the_camera_turn_maps_a_fixed_direction_seen_now_to_where_it_was_seen(R_then, R_now, R_body_cam, d):
    """Whatever the mount and the attitudes, a direction fixed in the level frame, seen by the camera now,
    is turned to where the camera saw it at the previous frame."""
    turn = CameraTurn(R_body_cam)
    assert turn.since_last(R_then) is None  # no previous frame
    R = turn.since_last(R_now)
    seen_then = (R_then * R_body_cam).inv().apply(d)
    seen_now = (R_now * R_body_cam).inv().apply(d)
    assert np.allclose(R.apply(seen_now), seen_then, atol=1e-9)


def test_a_frame_without_attitude_breaks_the_chain_of_turns():
    turn = CameraTurn(Rotation.identity())
    yaw = [Rotation.from_euler("z", a, degrees=True) for a in (0, 10, 20, 30)]
    assert turn.since_last(yaw[0]) is None
    assert turn.since_last(yaw[1]).magnitude() == pytest.approx(10 * DEG)
    assert turn.since_last(None) is None
    assert turn.since_last(yaw[3]) is None  # the previous frame had none: no turn to give
    assert turn.since_last(yaw[2]).magnitude() == pytest.approx(10 * DEG)


def _follower_through_a_tilted_leader(seed):
    """A follower placed through its leader's marker 1.2-2.5 m ahead, composed with a leader attitude off
    by a tilt: (true follower position, attitude, the composed pose and its covariance from the
    composition's Jacobians)."""
    from atlas_onboard.core.covariance import compose_jacobians

    rng = np.random.default_rng(seed)
    p_wl = rng.uniform(-2, 2, 3)
    R_wl = Rotation.from_euler("ZYX", [rng.uniform(-180, 180), *rng.uniform(-8, 8, 2)], degrees=True)
    p_lf = np.array([-rng.uniform(1.2, 2.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])  # behind it
    R_lf = Rotation.from_euler("ZYX", [rng.uniform(-30, 30), *rng.uniform(-8, 8, 2)], degrees=True)
    d = np.r_[rng.uniform(-3, 3, 2), 0.0] * DEG  # the leader's tilt error (its estimate at the wrong time)
    R_wl_est = R_wl * Rotation.from_rotvec(d)
    C_leader = np.diag([1e-6] * 3 + [(3 * DEG) ** 2, (3 * DEG) ** 2, (0.2 * DEG) ** 2])
    C_edge = np.diag([1e-6] * 3 + [(0.1 * DEG) ** 2] * 3)
    Jp, Je = compose_jacobians(R_wl_est.as_matrix(), p_lf, R_lf.as_matrix())
    C = Jp @ C_leader @ Jp.T + Je @ C_edge @ Je.T
    return p_wl + R_wl.apply(p_lf), R_wl * R_lf, p_wl + R_wl_est.apply(p_lf), R_wl_est * R_lf, C


@pytest.mark.parametrize("seed", range(6))
def test_constrain_body_tilt_levels_a_follower_and_its_lever_arm(seed):
    """Gravity from the follower's own autopilot undoes a leader's tilt error in its attitude and, through
    the composition's coupling, in its position (range x tilt)."""
    from atlas_onboard.core.attitude import BodyPose, constrain_body_tilt

    p_true, R_true, p, R, C = _follower_through_a_tilted_leader(seed)
    new = constrain_body_tilt(BodyPose(p, R.as_matrix(), C), up_in_body(R_true), math.radians(0.2))
    err_before = np.linalg.norm(p - p_true)
    err_after = np.linalg.norm(new.p_world_m - p_true)
    tilt_after = tilt_error_rad(Rotation.from_matrix(new.R_world_body), up_in_body(R_true))[0]
    assert err_before > 0.01
    assert err_after < 0.2 * err_before
    assert tilt_after < 0.2 * tilt_error_rad(R, up_in_body(R_true))[0]
    assert np.all(np.linalg.eigvalsh(C - new.covariance) > -1e-15)  # never less certain than before
    assert np.all(np.linalg.eigvalsh(new.covariance) > 0)


@given(rotations, st.floats(1e-4, 0.1), st.floats(0.1 * DEG, 5 * DEG))
def test_constrain_body_tilt_with_the_implied_up_moves_nothing_and_keeps_the_heading_variance(R, sigma_p, sigma_a):
    from atlas_onboard.core.attitude import BodyPose, constrain_body_tilt

    C = np.diag([sigma_p**2] * 3 + [sigma_a**2] * 3)
    p = np.array([1.0, -2.0, 1.5])
    new = constrain_body_tilt(BodyPose(p, R.as_matrix(), C), up_in_body(R))
    np.testing.assert_allclose(new.p_world_m, p, atol=1e-12)
    np.testing.assert_allclose(new.R_world_body, R.as_matrix(), atol=1e-12)
    # The heading (rotation about world up, seen in the body frame) is as uncertain as it was; tilt shrinks.
    u = up_in_body(R)
    assert u @ new.covariance[3:, 3:] @ u == pytest.approx(sigma_a**2, rel=1e-9)
    assert np.trace(new.covariance[3:, 3:]) < np.trace(C[3:, 3:])

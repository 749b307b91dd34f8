"""The node's output side: the own pose levelled with the autopilot's gravity when it rests on peers alone."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.core.attitude import AUTOPILOT_TILT_SIGMA_RAD, tilt_error_rad, up_in_body
from atlas_onboard.core.covariance import compose_jacobians
from atlas_onboard.core.graph import EntityPose, GraphResult
from atlas_onboard.node.output import level_own

DEG = math.pi / 180


def _result(own_view, covariance=True):
    """A follower 1.8 m behind its leader, composed with the leader's attitude 2 degrees off in pitch:
    (the graph's result, the follower's true position and attitude)."""
    p_wl, R_wl = np.array([1.0, 0.5, 1.2]), Rotation.from_euler("z", 30, degrees=True)
    p_lf, R_lf = np.array([-1.8, 0.1, -0.1]), Rotation.from_euler("z", 5, degrees=True)
    R_est = R_wl * Rotation.from_euler("y", 2.0, degrees=True)
    Jp, Je = compose_jacobians(R_est.as_matrix(), p_lf, R_lf.as_matrix())
    C = (
        Jp @ np.diag([1e-6] * 3 + [(2.5 * DEG) ** 2] * 2 + [(0.2 * DEG) ** 2]) @ Jp.T
        + Je @ np.diag([1e-6] * 3 + [(0.1 * DEG) ** 2] * 3) @ Je.T
    )
    follower = EntityPose(
        "follower", p_wl + R_est.apply(p_lf), (R_est * R_lf).as_quat(), 2, 2, 1, 0.05, 1_000_000,
        covariance=C if covariance else None, own_view=own_view,
    )  # fmt: skip
    leader = EntityPose("leader", p_wl, R_wl.as_quat(), 1, 1, 1, 0.001, 1_000_000, covariance=np.eye(6) * 1e-6)
    result = GraphResult({"leader": leader, "follower": follower}, ("world", "leader", "follower"), {}, (), 2)
    return result, p_wl + R_wl.apply(p_lf), R_wl * R_lf


def test_a_follower_resting_on_its_leader_is_levelled_by_its_own_gravity():
    result, p_true, R_true = _result(own_view=False)
    asked = []

    def up_at(t_us):
        asked.append(t_us)
        return up_in_body(R_true)

    out = level_own(result, "follower", up_at)
    before, after = result.poses["follower"], out.poses["follower"]
    assert asked == [before.capture_time_us]
    # The leader's pitch error (sigma 2.5 degrees) is all of the follower's tilt and lever-arm error, so a
    # gravity of sigma s leaves the Kalman share s^2 / (s^2 + 2.5^2) of both.
    left = AUTOPILOT_TILT_SIGMA_RAD**2 / (AUTOPILOT_TILT_SIGMA_RAD**2 + (2.5 * DEG) ** 2)
    err_before = np.linalg.norm(before.p_world_m - p_true)
    assert err_before > 0.05  # 1.8 m x 2 degrees
    assert np.linalg.norm(after.p_world_m - p_true) == pytest.approx(left * err_before, rel=0.05)
    tilt = tilt_error_rad(Rotation.from_quat(after.q_world_xyzw), up_in_body(R_true))[0]
    assert tilt == pytest.approx(left * 2.0 * DEG, rel=0.05)
    assert np.trace(after.covariance[:3, :3]) < np.trace(before.covariance[:3, :3])
    assert after.sigma_m < before.sigma_m
    assert out.poses["leader"] is result.poses["leader"]  # only the own pose


@pytest.mark.parametrize(
    ("own_view", "covariance", "up"),
    [(True, True, True), (None, True, True), (False, False, True), (False, True, False)],
    ids=["own-view", "unknown", "no-covariance", "no-attitude"],
)
def test_a_pose_on_an_own_view_or_without_what_levelling_needs_is_left_as_it_is(own_view, covariance, up):
    """An own view of the world was already constrained tag by tag (gravity counted once); without a
    covariance or an attitude at the capture time there is nothing to update."""
    result, _, R_true = _result(own_view, covariance)
    out = level_own(result, "follower", lambda _t: up_in_body(R_true) if up else None)
    assert out is result
    assert level_own(result, "follower", None) is result

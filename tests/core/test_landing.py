"""The landing decision: frames against hand-computed truth, the covariance against finite differences,
and the refusals (stale, extrapolated, uncertain, not below)."""

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.landing import Limits, PoseSample, Verdict, decide, relative_target

LIMITS = Limits(max_age_s=0.3, max_sigma_m=0.05)
IDENTITY = RigidTransform.identity()


def sample(p, R=None, sigma=0.01, stamp=1_000_000, observed=None, exact=False, cov=None, v=None):
    C = np.diag([sigma**2] * 3 + [1e-6] * 3) if cov is None else cov
    R = Rotation.identity() if R is None else R
    return PoseSample(np.asarray(p, float), R.as_quat(), C, sigma, stamp, stamp if observed is None else observed,
                      exact, None if v is None else np.asarray(v, float))  # fmt: skip


def test_fields_against_hand_computed_truth():
    # The drone at ENU (1, 2, 3), nose north (yaw 90 deg); the target 1 m north of it on the floor,
    # its x axis east. In the drone's FRD: 1 m forward, 0 right, 3 m down; distance sqrt(10);
    # angle_x = atan(0 / 3) = 0, angle_y = atan(-1 / 3). PX4 local NED: north 3, east 1, down 0, the
    # target's FRD x east: yaw 90 deg in NED, q = (cos 45, 0, 0, sin 45).
    drone = sample([1, 2, 3], Rotation.from_euler("z", 90, degrees=True))
    target = sample([1, 3, 0])
    d = decide(drone, target, IDENTITY, 1_000_000, LIMITS)
    assert d.verdict is Verdict.SEND
    a = d.ardupilot
    assert (a.x_m, a.y_m, a.z_m) == pytest.approx((1.0, 0.0, 3.0), abs=1e-12)
    assert a.distance_m == pytest.approx(math.sqrt(10.0))
    assert (a.angle_x_rad, a.angle_y_rad) == pytest.approx((0.0, math.atan(-1 / 3)), abs=1e-12)
    p = d.px4
    assert (p.x_m, p.y_m, p.z_m) == pytest.approx((3.0, 1.0, 0.0), abs=1e-12)
    assert p.q_wxyz == pytest.approx((math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)), abs=1e-12)


def test_point_offset_on_the_target():
    # A rover at ENU (4, 0, 0) turned 90 deg (its x north); the pad 0.5 m ahead of its origin and
    # 0.3 m up: ENU (4, 0.5, 0.3), NED (0.5, 4, -0.3). The drone right above it at 2 m, nose east:
    # FRD (0, 0, 1.7) relative.
    rover = sample([4, 0, 0], Rotation.from_euler("z", 90, degrees=True))
    drone = sample([4, 0.5, 2.0])
    d = decide(drone, rover, RigidTransform.from_translation([0.5, 0.0, 0.3]), 1_000_000, LIMITS)
    assert (d.px4.x_m, d.px4.y_m, d.px4.z_m) == pytest.approx((0.5, 4.0, -0.3), abs=1e-12)
    assert (d.ardupilot.x_m, d.ardupilot.y_m, d.ardupilot.z_m) == pytest.approx((0.0, 0.0, 1.7), abs=1e-12)


unit = st.floats(-1.0, 1.0)
rotations = st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1).map(Rotation.from_quat)
positions = st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-5, 5)).map(np.array)


@settings(max_examples=60, deadline=None)
@given(rotations, positions, rotations, positions, positions)
def test_ardupilot_line_of_sight_gives_back_the_vector(R_d, p_d, R_t, p_t, o):
    # ArduPilot rebuilds the body vector as (-tan(angle_y), tan(angle_x), 1) / |.| * distance
    # (AC_PrecLand_Companion); the position fields are the same vector. Truth: R_FRD_FLU R_d^T (p - p_d).
    d = decide(sample(p_d, R_d), sample(p_t, R_t), RigidTransform.from_translation(o), 1_000_000,
               Limits(1.0, 1e9))  # fmt: skip
    truth_flu = R_d.as_matrix().T @ (p_t + R_t.apply(o) - p_d)
    truth_frd = np.array([truth_flu[0], -truth_flu[1], -truth_flu[2]])
    assume(abs(truth_frd[2]) > 1e-6)  # not on the boundary, where rounding decides
    if truth_frd[2] < 0.0:
        assert d.verdict is Verdict.NOT_BELOW
        return
    a = d.ardupilot
    assert np.allclose((a.x_m, a.y_m, a.z_m), truth_frd, atol=1e-9)
    los = np.array([-math.tan(a.angle_y_rad), math.tan(a.angle_x_rad), 1.0])
    assert np.allclose(los / np.linalg.norm(los) * a.distance_m, truth_frd, atol=1e-7 * max(1.0, a.distance_m))
    # PX4: the point in NED (north = ENU y, east = ENU x, down = -z).
    p = p_t + R_t.apply(o)
    assert np.allclose((d.px4.x_m, d.px4.y_m, d.px4.z_m), (p[1], p[0], -p[2]), atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(rotations, positions, rotations, positions, positions, st.integers(0, 11))
def test_covariance_is_the_first_order_propagation(R_d, p_d, R_t, p_t, o, k):
    # One error component at a time, through the exact composition: the change of [p, dtheta] matches
    # the covariance's Jacobian column (the covariance with a unit variance on that component alone).
    eps = 1e-6
    T = RigidTransform.from_translation(o)
    base = relative_target(sample(p_d, R_d, exact=False), sample(p_t, R_t), T)
    dp_d, dth_d, dp_t, dth_t = (np.zeros(3) for _ in range(4))
    [dp_d, dth_d, dp_t, dth_t][k // 3][k % 3] = eps
    moved = relative_target(
        sample(p_d + dp_d, R_d * Rotation.from_rotvec(dth_d)), sample(p_t + dp_t, R_t * Rotation.from_rotvec(dth_t)), T
    )
    change = np.concatenate(
        [moved.p_drone_m - base.p_drone_m, (base.R_drone_point.inv() * moved.R_drone_point).as_rotvec()]
    )
    C = np.zeros((6, 6))
    C[k % 6, k % 6] = 1.0
    zero = np.zeros((6, 6))
    drone_cov, target_cov = (C, zero) if k < 6 else (zero, C)
    rel = relative_target(sample(p_d, R_d, cov=drone_cov), sample(p_t, R_t, cov=target_cov), T)
    column = change / eps
    assert np.allclose(rel.covariance, np.outer(column, column), atol=1e-4 * max(1.0, np.abs(column).max() ** 2))


@given(st.floats(0.0, 5.0))
def test_never_a_stale_target(age_s):
    now = 10_000_000
    observed = now - round(age_s * 1e6)
    d = decide(sample([0, 0, 2], observed=observed, stamp=observed), sample([0, 0, 0], stamp=observed), IDENTITY,
               now, LIMITS)  # fmt: skip
    assert (d.verdict is Verdict.SEND) == (observed >= now - 300_000)
    if d.verdict is not Verdict.SEND:
        assert d.verdict is Verdict.STALE and d.px4 is None and d.ardupilot is None


def test_the_older_pose_sets_the_age_and_the_world_never_ages():
    now = 10_000_000
    drone = sample([0, 0, 2], stamp=now - 50_000)
    assert decide(drone, sample([0, 0, 0], stamp=now - 400_000), IDENTITY, now, LIMITS).verdict is Verdict.STALE
    world = sample([0, 0, 0], stamp=0, exact=True)
    d = decide(drone, world, IDENTITY, now, LIMITS)
    assert d.verdict is Verdict.SEND and d.age_s == pytest.approx(0.05) and d.time_usec == now - 50_000


def test_never_an_extrapolated_target():
    now = 10_000_000
    predicted = sample([0, 0, 0], stamp=now, observed=now - 20_000)  # a filter's prediction to now
    assert decide(sample([0, 0, 2], stamp=now), predicted, IDENTITY, now, LIMITS).verdict is Verdict.EXTRAPOLATED


def test_uncertainty_and_the_motion_since_capture():
    now = 10_000_000
    drone = sample([0, 0, 2], stamp=now)
    assert decide(drone, sample([0, 0, 0], sigma=0.06, stamp=now), IDENTITY, now, LIMITS).verdict is Verdict.UNCERTAIN
    # sigma 0.03 of the target, 0.01 of the drone and its attitude's 1 mrad over the 2 m lever:
    # 0.0009 + 0.0001 + 0.000004 m^2, 0.0317 m; a rover at 0.3 m/s seen 0.15 s ago has moved up to
    # 4.5 cm since: sqrt(0.001004 + 0.045^2) = 0.055 m > 0.05.
    old = now - 150_000
    still = decide(drone, sample([0, 0, 0], sigma=0.03, stamp=old), IDENTITY, now, LIMITS)
    moving = decide(drone, sample([0, 0, 0], sigma=0.03, stamp=old, v=[0.3, 0, 0]), IDENTITY, now, LIMITS)
    assert still.verdict is Verdict.SEND and still.sigma_m == pytest.approx(math.sqrt(0.001004), rel=1e-6)
    assert moving.verdict is Verdict.UNCERTAIN and moving.sigma_m == pytest.approx(math.sqrt(0.001004 + 0.045**2))


def test_an_unknown_uncertainty_is_not_small_enough():
    bad = np.diag([np.nan, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])
    d = decide(sample([0, 0, 2]), sample([0, 0, 0], cov=bad), IDENTITY, 1_000_000, LIMITS)
    assert d.verdict is Verdict.UNCERTAIN and d.px4 is None


def test_missing_poses():
    assert decide(None, sample([0, 0, 0]), IDENTITY, 0, LIMITS).verdict is Verdict.NO_OWN_POSE
    assert decide(sample([0, 0, 0]), None, IDENTITY, 0, LIMITS).verdict is Verdict.NO_TARGET

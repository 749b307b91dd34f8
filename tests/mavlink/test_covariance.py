"""The covariance sent to the autopilot: MAVLink's 21 values in row-major order, floored, checked and
gathered in one step as in two, and ODOMETRY's quality from a sigma or from the worst position axis."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import codec, covariance

DIAG = [0, 6, 11, 15, 18, 20]


def test_upper_triangle_order_is_row_major():
    C = np.arange(36, dtype=float).reshape(6, 6)
    C = C + C.T + 100 * np.eye(6)
    out = covariance.covariance_upper_triangle(C)
    expected = [C[i, j] for i in range(6) for j in range(i, 6)]
    assert out == expected


def test_zero_variance_is_floored_never_sent():
    cov = covariance.covariance_upper_triangle(np.zeros((6, 6)))
    assert [cov[i] for i in DIAG] == pytest.approx([1e-8] * 6)
    assert all(cov[i] > 0 for i in DIAG)
    assert all(v > 0 and math.isfinite(v) for v in (codec.pose_covariance(0.0)[i] for i in DIAG))


@pytest.mark.parametrize(("sigma", "quality"), [(0.005, 100), (0.01, 100), (0.1, 41), (0.5, 1), (math.nan, 0)])
def test_quality(sigma, quality):
    assert covariance.quality_percent(sigma) == quality


@given(st.lists(st.floats(-1, 1), min_size=36, max_size=36), st.floats(1e-8, 1.0))
def test_covariance_21_from_enu_flu_is_the_two_steps(values, scale):
    """The one-gather triangle equals covariance_upper_triangle(covariance_ned_frd(C)) for symmetric
    positive semi-definite C (tiny variances floored alike), and refuses what they refuse."""
    A = np.array(values).reshape(6, 6) * scale
    C = A @ A.T
    expected = covariance.covariance_upper_triangle(covariance.covariance_ned_frd(C))
    np.testing.assert_allclose(covariance.covariance_21_from_enu_flu(C), expected, rtol=1e-12, atol=0)


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (np.ones((5, 5)), "shape"),
        (np.full((6, 6), np.nan), "finite"),
        (np.diag([1, 1, 1, 1, 1, -1.0]), "non-negative"),
        (np.triu(np.ones((6, 6))), "symmetric"),
    ],
)
def test_covariance_21_from_enu_flu_refuses_bad_matrices(bad, message):
    with pytest.raises(AtlasError, match=message):
        covariance.covariance_upper_triangle(covariance.covariance_ned_frd(bad) if bad.shape == (6, 6) else bad)
    with pytest.raises(AtlasError, match=message):
        covariance.covariance_21_from_enu_flu(bad)


def test_quality_from_covariance_follows_the_worst_position_axis():
    iso_1cm = np.diag([1e-4] * 3 + [1e-3] * 3)
    assert covariance.quality_from_covariance(iso_1cm) == 100
    tall = np.diag([1e-4, 1e-4, 0.1**2] + [1e-3] * 3)  # 1 cm across, 10 cm along z
    assert covariance.quality_from_covariance(tall) == covariance.quality_percent(0.1) == 41
    # A correlated block: its worst direction is the largest eigenvalue's, not any diagonal entry.
    R = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    rotated = np.eye(6) * 1e-3
    rotated[:3, :3] = R @ np.diag([0.2**2, 0.01**2, 0.01**2]) @ R.T
    assert max(rotated[0, 0], rotated[1, 1]) < 0.2**2 * 0.51  # each diagonal entry is about half of it
    assert covariance.quality_from_covariance(rotated) == covariance.quality_percent(0.2)
    assert covariance.quality_from_covariance(np.full((6, 6), np.nan)) == 0  # unknown, never -1


@pytest.mark.parametrize(("sigma", "quality"), [(0.005, 100), (0.01, 100), (0.5, 1), (2.0, 1), (math.nan, 0)])
def test_quality_mapping(sigma, quality):
    assert covariance.quality_percent(sigma) == quality


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=36, max_size=36))
def test_ned_frd_is_the_axis_swap_and_flips_applied_to_both_sides(values):
    """Position: NED x = ENU y (north), y = ENU x (east), z = -up; rotation: FRD x = FLU x, y = -y, z = -z.
    So every entry is an ENU/FLU entry, with the sign of the flips of its row and column."""
    A = np.array(values).reshape(6, 6)
    C = A @ A.T
    perm, sign = [1, 0, 2, 3, 4, 5], np.array([1, 1, -1, 1, -1, -1])
    expected = C[np.ix_(perm, perm)] * np.outer(sign, sign)
    np.testing.assert_allclose(covariance.covariance_ned_frd(C), expected, rtol=1e-12, atol=1e-12)


def test_a_sigma_gives_a_diagonal_with_the_attitude_of_its_lever_arm_clamped_to_1_and_30_degrees():
    np.testing.assert_allclose(
        covariance.covariance_from_sigma(0.02), np.diag([0.02**2] * 3 + [(0.02 / 0.25) ** 2] * 3), rtol=1e-15
    )
    assert covariance.attitude_sigma_rad(0.001) == pytest.approx(math.radians(1.0), rel=1e-15)
    assert covariance.attitude_sigma_rad(10.0) == pytest.approx(math.radians(30.0), rel=1e-15)
    np.testing.assert_allclose(covariance.covariance_from_sigma(0.02, 0.1).diagonal()[3:], [0.01] * 3, rtol=1e-15)
    with pytest.raises(AtlasError, match="attitude sigma"):
        covariance.covariance_from_sigma(0.02, math.nan)

"""The MarkerData record on its own: each reason it is rejected, the other planar solution's state,
the quaternion orders and the covariance's upper triangle to and from a symmetric matrix."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.core.markerdata import (
    MAX_RANGE_M,
    MAX_SIGMA_M,
    AltState,
    MarkerData,
    matrix_to_upper,
    upper_to_matrix,
)
from atlas_onboard.core.rejection import Rejection

GOOD = MarkerData(1, 7, 0.01, (0.1, -0.2, 1.5), (0.5, 0.5, -0.5, 0.5), 1_000_000)
COV = matrix_to_upper(np.diag([1e-4, 1e-4, 4e-4, 1e-3, 1e-3, 2e-3]))


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({}, None),
        ({"covariance": COV}, None),
        ({"reprojection_error_px": 0.3, "ambiguity_ratio": 1.0}, None),
        ({"p_sensor_marker_m": (math.nan, 0.0, 1.0)}, Rejection.NON_FINITE),
        ({"q_sensor_marker_wxyz": (1.0, 0.0, math.inf, 0.0)}, Rejection.NON_FINITE),
        ({"sigma_m": math.nan}, Rejection.NON_FINITE),
        ({"q_sensor_marker_wxyz": (0.0, 0.0, 0.0, 0.0)}, Rejection.ZERO_QUATERNION),
        ({"sigma_m": 0.0}, Rejection.BAD_SIGMA),
        ({"sigma_m": MAX_SIGMA_M * 1.001}, Rejection.BAD_SIGMA),
        ({"p_sensor_marker_m": (0.0, 0.0, MAX_RANGE_M * 1.001)}, Rejection.OUT_OF_RANGE),
        ({"reprojection_error_px": -0.1}, Rejection.BAD_QUALITY),
        ({"reprojection_error_px": math.inf}, Rejection.BAD_QUALITY),
        ({"ambiguity_ratio": 1.01}, Rejection.BAD_QUALITY),
        ({"covariance": COV[:20]}, Rejection.BAD_COVARIANCE),
        ({"covariance": (0.0, *COV[1:])}, Rejection.BAD_COVARIANCE),  # a zero variance
        ({"covariance": (*COV[:5], math.nan, *COV[6:])}, Rejection.BAD_COVARIANCE),
    ],
)
def test_each_defect_is_its_own_rejection(change, reason):
    assert replace(GOOD, **change).rejection() is reason


def test_the_record_at_the_limits_is_valid():
    edge = replace(GOOD, sigma_m=MAX_SIGMA_M, p_sensor_marker_m=(0.0, 0.0, MAX_RANGE_M), reprojection_error_px=0.0)
    assert edge.rejection() is None


@pytest.mark.parametrize(
    ("p", "q", "state"),
    [
        ((math.nan,) * 3, (math.nan,) * 4, AltState.ABSENT),
        ((0.1, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), AltState.VALID),
        ((0.1, math.nan, 2.0), (1.0, 0.0, 0.0, 0.0), AltState.INVALID),
        ((0.1, 0.0, 2.0), (0.0, 0.0, 0.0, 0.0), AltState.INVALID),
        ((0.0, 0.0, MAX_RANGE_M * 1.001), (1.0, 0.0, 0.0, 0.0), AltState.INVALID),
    ],
)
def test_the_other_solution_is_absent_valid_or_invalid(p, q, state):
    md = replace(GOOD, p_sensor_marker_alt_m=p, q_sensor_marker_alt_wxyz=q)
    assert md.alt_state() is state
    assert md.rejection() is None  # the record stands on its primary solution


def test_quaternions_come_out_in_scipys_order():
    md = replace(GOOD, q_sensor_marker_wxyz=(0.1, 0.2, 0.3, 0.4), q_sensor_marker_alt_wxyz=(0.5, 0.6, 0.7, 0.8))
    assert md.q_sensor_marker_xyzw().tolist() == [0.2, 0.3, 0.4, 0.1]
    assert md.q_sensor_marker_alt_xyzw().tolist() == [0.6, 0.7, 0.8, 0.5]


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=36, max_size=36))
def test_the_upper_triangle_row_by_row_rebuilds_the_symmetric_matrix(values):
    A = np.array(values).reshape(6, 6)
    C = A + A.T
    upper = matrix_to_upper(C)
    assert list(upper) == [float(C[i, j]) for i in range(6) for j in range(i, 6)]
    np.testing.assert_array_equal(upper_to_matrix(np.array(upper)), C)
    # Several at once, and through the record.
    np.testing.assert_array_equal(upper_to_matrix(np.stack([upper, upper])), np.stack([C, C]))
    np.testing.assert_array_equal(replace(GOOD, covariance=upper).covariance_matrix(), C)


def test_a_record_without_a_covariance_has_no_matrix():
    assert GOOD.covariance_matrix() is None

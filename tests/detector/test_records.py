"""The detector's records against known answers: the frame report's one line, the misfit pair, and
the one builder of MarkerData (quaternion order, the other solution, the covariance's triangle)."""

from __future__ import annotations

import math

import numpy as np

from atlas_onboard.core.markerdata import AltState
from atlas_onboard.detector.records import FrameReport, JointResult, LeftOut, marker_data


def test_the_frame_report_says_what_was_found_reported_and_why_not():
    assert FrameReport().explain() == "no tag found"
    assert FrameReport([4], [4]).explain() == "1 tag found (ids 4); reported 4"
    none = FrameReport([5, 1], [], {5: "too small", 1: "at the border"})
    assert none.explain() == "2 tags found (ids 5, 1); none reported: marker 1: at the border; marker 5: too small"
    some = FrameReport([1, 2, 3], [1, 3], {2: "left out"})
    assert some.explain() == "3 tags found (ids 1, 2, 3); reported 1, 3; not: marker 2: left out"


def test_the_misfit_pair_is_the_unfit_markers_only_when_their_offset_is_known():
    pair = LeftOut(7, np.array([0.1, 0.0, 0.0]), 0.1)
    assert JointResult(None, None, unfit=[2, 7], pair_offset=pair).misfit_pair == [2, 7]
    assert JointResult(None, None, unfit=[2, 7, 9]).misfit_pair == []


def test_marker_data_turns_scipys_order_into_mavlinks_and_carries_the_rest():
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    cov[0, 5] = cov[5, 0] = 0.5
    md = marker_data(
        1, 9, np.array([0.1, 0.2, 1.5]), np.array([0.1, 0.2, 0.3, 0.9]), 0.01, 0.4, 0.2, 123,
        alt=(np.array([0.1, 0.2, 1.6]), np.array([0.5, 0.6, 0.7, 0.8])), covariance=cov,
    )  # fmt: skip
    assert md.q_sensor_marker_wxyz == (0.9, 0.1, 0.2, 0.3)
    assert md.q_sensor_marker_alt_wxyz == (0.8, 0.5, 0.6, 0.7)
    assert md.p_sensor_marker_alt_m == (0.1, 0.2, 1.6) and md.alt_state() is AltState.VALID
    assert (md.sensor_id, md.marker_id, md.sigma_m, md.capture_time_us) == (1, 9, 0.01, 123)
    assert (md.reprojection_error_px, md.ambiguity_ratio) == (0.4, 0.2)
    assert md.covariance[:6] == (1.0, 0.0, 0.0, 0.0, 0.0, 0.5) and md.covariance[-1] == 6.0
    np.testing.assert_array_equal(md.covariance_matrix(), cov)
    bare = marker_data(1, 9, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), 0.01, math.nan, math.nan, 0)
    assert bare.alt_state() is AltState.ABSENT and bare.covariance == ()

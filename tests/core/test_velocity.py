"""The autopilot's velocity: LOCAL_POSITION_NED's NED read as level ENU, interpolated to a capture time and
turned into the body's axes by the attitude then, with a covariance that grows away from the samples."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.velocity import AUTOPILOT_VELOCITY_SIGMA_M_S, VelocityHistory, level_enu_of_ned

finite = st.floats(-5.0, 5.0, allow_nan=False)


def test_ned_reads_as_level_enu_and_an_unfilled_velocity_is_none():
    np.testing.assert_array_equal(level_enu_of_ned(1.0, 2.0, 3.0), [2.0, 1.0, -3.0])  # north, east, down
    assert level_enu_of_ned(0.0, 0.0, 0.0) is None
    assert level_enu_of_ned(float("nan"), 0.1, 0.0) is None


def test_a_vehicle_facing_north_flying_north_moves_along_its_forward_axis():
    history = VelocityHistory()
    history.add(0, np.array([0.0, 1.0, 0.0]))  # level ENU: north
    history.add(20_000, np.array([0.0, 1.0, 0.0]))
    facing_north = Rotation.from_euler("z", 90, degrees=True)  # body FLU x along ENU north
    got = history.velocity_at(10_000, facing_north)
    assert got is not None
    np.testing.assert_allclose(got.velocity_flu, [1.0, 0.0, 0.0], atol=1e-12)


@given(st.lists(finite, min_size=3, max_size=3), st.lists(finite, min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1))  # fmt: skip
def test_the_body_velocity_turned_back_by_the_attitude_is_the_level_velocity(v, q):
    history = VelocityHistory()
    history.add(0, np.array(v))
    history.add(30_000, np.array(v))
    R = Rotation.from_quat(q)
    got = history.velocity_at(12_000, R)
    assert got is not None
    np.testing.assert_allclose(R.apply(got.velocity_flu), v, atol=1e-9)


def test_interpolated_between_samples_its_covariance_growing_with_the_distance_to_one():
    history = VelocityHistory()
    for k in range(4):  # a steady acceleration of 0.5 m/s^2 east, a sample every 33 ms
        history.add(33_000 * k, np.array([0.5 * 0.033 * k, 0.0, 0.0]))
    at_sample = history.velocity_at(33_000, Rotation.identity())
    between = history.velocity_at(50_000, Rotation.identity())
    assert at_sample is not None and between is not None
    assert between.velocity_flu[0] == pytest.approx(0.5 * 0.050)
    assert at_sample.cov[0, 0] == pytest.approx(AUTOPILOT_VELOCITY_SIGMA_M_S**2)
    assert between.cov[0, 0] > at_sample.cov[0, 0]


def test_none_without_an_attitude_or_a_sample_near_enough():
    history = VelocityHistory(max_gap_us=100_000)
    assert history.velocity_at(0, Rotation.identity()) is None
    history.add(0, np.array([0.1, 0.0, 0.0]))
    assert history.velocity_at(0, None) is None
    assert history.velocity_at(90_000, Rotation.identity()) is not None  # the newest, aged
    assert history.velocity_at(150_000, Rotation.identity()) is None  # the stream stopped

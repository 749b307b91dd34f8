"""The gravity check of a single tag's two solutions, the attitude history and the boot-time mapping."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.attitude import (
    AttitudeHistory,
    BootClock,
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


def test_boot_clock_converges_on_the_smallest_lag_and_restarts_after_a_reboot():
    c = BootClock()
    assert c.wall_us(2_000_000, 7_000_000 + 9_000) == 7_000_000 + 9_000  # first: arrival
    assert c.wall_us(2_001_000, 7_001_000 + 3_000) == 7_001_000 + 3_000  # a smaller lag wins
    assert c.wall_us(2_002_000, 7_002_000 + 20_000) == 7_002_000 + 3_000  # a late arrival is not believed
    assert c.wall_us(0, 9_000_000) == 9_000_000  # boot time went back: a reboot

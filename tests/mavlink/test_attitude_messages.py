"""ATTITUDE / ATTITUDE_QUATERNION (NED/FRD) into the node's level ENU / body FLU frame: a known roll, pitch
and heading of a real body show up as the right tilt of its axes; the two messages agree; the sim
autopilot's conversion (the other way) is inverted exactly."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core import frames
from atlas_onboard.core.attitude import up_in_body
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import autopilot

DEG = math.pi / 180
FORWARD, LEFT, UP = np.eye(3)


def test_roll_right_wing_down_lowers_the_right_wing():
    # FRD roll +20 deg: the right wing (FLU -y) points down by 20 deg in the level ENU frame.
    R = autopilot.attitude_level_flu(20 * DEG, 0.0, 0.0)
    right = R.apply(-LEFT)
    assert right[2] == pytest.approx(-math.sin(20 * DEG), abs=1e-12)
    assert R.apply(FORWARD)[2] == pytest.approx(0.0, abs=1e-12)


def test_pitch_nose_up_raises_the_nose():
    R = autopilot.attitude_level_flu(0.0, 15 * DEG, 0.0)
    assert R.apply(FORWARD)[2] == pytest.approx(math.sin(15 * DEG), abs=1e-12)
    assert R.apply(LEFT)[2] == pytest.approx(0.0, abs=1e-12)


def test_heading_north_is_enu_y_and_east_is_enu_x():
    np.testing.assert_allclose(autopilot.attitude_level_flu(0.0, 0.0, 0.0).apply(FORWARD), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(autopilot.attitude_level_flu(0.0, 0.0, 90 * DEG).apply(FORWARD), [1, 0, 0], atol=1e-12)


@given(
    st.floats(-80, 80), st.floats(-80, 80), st.floats(-180, 180), st.floats(-180, 180),
)  # fmt: skip
def test_up_depends_on_roll_and_pitch_only_and_both_messages_agree(roll, pitch, yaw, yaw2):
    R = autopilot.attitude_level_flu(roll * DEG, pitch * DEG, yaw * DEG)
    R2 = autopilot.attitude_level_flu(roll * DEG, pitch * DEG, yaw2 * DEG)
    np.testing.assert_allclose(up_in_body(R), up_in_body(R2), atol=1e-9)
    q_xyzw = Rotation.from_euler("ZYX", [yaw * DEG, pitch * DEG, roll * DEG]).as_quat()
    Rq = autopilot.attitude_quaternion_level_flu((q_xyzw[3], *q_xyzw[:3]))
    assert (Rq.inv() * R).magnitude() < 1e-9
    # The inverse conversion (what the sim autopilot does from the truth) gives the angles back.
    _yaw, p, r = (frames.R_ENU_NED.inv() * R * frames.R_FLU_FRD).as_euler("ZYX")
    assert (r, p) == (pytest.approx(roll * DEG, abs=1e-9), pytest.approx(pitch * DEG, abs=1e-9))


def test_a_tilted_enu_body_reads_back_as_its_own_tilt():
    # A body FLU pitched nose-down 30 deg about its left axis (FLU +y: positive pitch is nose down),
    # heading east in ENU: the autopilot reports NED pitch -30 deg; converted back, the same up vector.
    R_enu_flu = Rotation.from_euler("zy", [0.0, 30.0], degrees=True)
    R_ned_frd = frames.R_ENU_NED.inv() * R_enu_flu * frames.R_FLU_FRD
    yaw, pitch, roll = R_ned_frd.as_euler("ZYX")
    assert pitch == pytest.approx(-30 * DEG) and roll == pytest.approx(0.0, abs=1e-12)
    assert yaw == pytest.approx(90 * DEG)  # nose east
    back = autopilot.attitude_level_flu(roll, pitch, yaw)
    np.testing.assert_allclose(up_in_body(back), up_in_body(R_enu_flu), atol=1e-12)


@pytest.mark.parametrize("angles", [(math.nan, 0.0, 0.0), (0.0, math.inf, 0.0)])
def test_non_finite_attitude_is_refused(angles):
    with pytest.raises(AtlasError, match="finite"):
        autopilot.attitude_level_flu(*angles)
    with pytest.raises(AtlasError, match="quaternion"):
        autopilot.attitude_quaternion_level_flu((0.0, 0.0, 0.0, 0.0))


def test_set_message_interval_asks_for_attitude():
    f = autopilot.set_message_interval_fields(1, 1, autopilot.MSG_ATTITUDE, 20_000)
    assert (f["command"], f["param1"], f["param2"]) == (511, 30.0, 20_000.0)

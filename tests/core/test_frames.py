"""Frame conventions: each conversion checked on hand-computed numbers and by property tests."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import frames
from atlas_onboard.core.geometry import make_pose, rotation_from_rpy_deg, rpy_deg

finite = st.floats(-100, 100, allow_nan=False)
angles = st.floats(-179, 179, allow_nan=False)


def test_enu_flu_to_ned_frd_design_example():
    # A drone at ENU (1, 2, 3) with yaw 90 deg (nose north) is at NED (2, 1, -3) with yaw 0 (nose north).
    T = make_pose([1.0, 2.0, 3.0], rotation_from_rpy_deg([0, 0, 90]))
    T_ned = frames.enu_flu_to_ned_frd(T)
    np.testing.assert_allclose(T_ned.translation, [2.0, 1.0, -3.0], atol=1e-12)
    np.testing.assert_allclose(rpy_deg(T_ned.rotation), [0.0, 0.0, 0.0], atol=1e-9)


def test_enu_yaw_zero_is_ned_yaw_90():
    # ENU yaw 0 = nose east = NED yaw +90 deg (clockwise from north).
    T_ned = frames.enu_flu_to_ned_frd(make_pose([0, 0, 0], rotation_from_rpy_deg([0, 0, 0])))
    np.testing.assert_allclose(rpy_deg(T_ned.rotation), [0.0, 0.0, 90.0], atol=1e-9)


def test_roll_and_pitch_keep_their_sense():
    # Nose north, rolled 10 deg about the forward axis: both FLU and FRD call it roll +10, since the
    # x axis is shared. Pitch flips sign: +pitch about FLU's y (left) dips the nose, about FRD's y
    # (right) raises it, so FLU pitch -20 (nose up) is FRD pitch +20 (nose up).
    T_ned = frames.enu_flu_to_ned_frd(make_pose([0, 0, 0], rotation_from_rpy_deg([10, -20, 90])))
    np.testing.assert_allclose(rpy_deg(T_ned.rotation), [10.0, 20.0, 0.0], atol=1e-9)


@given(finite, finite, finite, angles, st.floats(-89, 89), angles)
def test_enu_ned_round_trip(x, y, z, r, p, yaw):
    T = make_pose([x, y, z], rotation_from_rpy_deg([r, p, yaw]))
    back = frames.ned_frd_to_enu_flu(frames.enu_flu_to_ned_frd(T))
    np.testing.assert_allclose(back.as_matrix(), T.as_matrix(), atol=1e-9)


@pytest.mark.parametrize(
    ("R_name", "axis_from", "axis_to"),
    [
        ("R_ENU_NED", [1, 0, 0], [0, 1, 0]),  # north
        ("R_ENU_NED", [0, 1, 0], [1, 0, 0]),  # east
        ("R_ENU_NED", [0, 0, 1], [0, 0, -1]),  # down
        ("R_FLU_FRD", [1, 0, 0], [1, 0, 0]),  # forward
        ("R_FLU_FRD", [0, 1, 0], [0, -1, 0]),  # right
        ("R_FLU_FRD", [0, 0, 1], [0, 0, -1]),  # down
        ("R_FLU_OPTICAL", [0, 0, 1], [1, 0, 0]),  # the optical axis looks forward
        ("R_FLU_OPTICAL", [1, 0, 0], [0, -1, 0]),  # image right = body right
        ("R_FLU_OPTICAL", [0, 1, 0], [0, 0, -1]),  # image down = body down
        ("R_FRD_OPTICAL", [0, 0, 1], [1, 0, 0]),
        ("R_FRD_OPTICAL", [1, 0, 0], [0, 1, 0]),
        ("R_FRD_OPTICAL", [0, 1, 0], [0, 0, 1]),
    ],
)
def test_each_conversion_maps_the_named_axes(R_name, axis_from, axis_to):
    np.testing.assert_allclose(getattr(frames, R_name).apply(axis_from), axis_to, atol=1e-12)


def test_optical_frame_of_a_forward_camera():
    T = frames.mount_to_optical(RigidTransform.identity(), frames.BodyConvention.FLU)
    R = T.rotation
    np.testing.assert_allclose(R.apply([0, 0, 1]), [1, 0, 0], atol=1e-12)  # optical z = forward
    np.testing.assert_allclose(R.apply([1, 0, 0]), [0, -1, 0], atol=1e-12)  # image right = body right
    np.testing.assert_allclose(R.apply([0, 1, 0]), [0, 0, -1], atol=1e-12)  # image down = body down


def test_optical_frame_same_for_flu_and_frd_mounts():
    # The same physical camera written in FRD: its mount frame in FLU is T_FLU_FRD * T_frd_mount.
    T_frd = make_pose([0.1, 0.2, -0.3], rotation_from_rpy_deg([5, 30, -40]))
    opt_frd = frames.mount_to_optical(T_frd, frames.BodyConvention.FRD)
    flu_body = frames.T_FLU_FRD * opt_frd
    # Written in FLU, the same mount has the FRD mount frame re-expressed: T_flu_mountflu.
    T_flu_mount = frames.T_FLU_FRD * T_frd * frames.T_FLU_FRD.inv()
    opt_flu = frames.mount_to_optical(T_flu_mount, frames.BodyConvention.FLU)
    np.testing.assert_allclose(flu_body.as_matrix(), opt_flu.as_matrix(), atol=1e-12)


def test_downward_camera_looks_down():
    T = frames.mount_to_optical(make_pose([0, 0, 0], rotation_from_rpy_deg([0, 90, 0])), frames.BodyConvention.FLU)
    np.testing.assert_allclose(T.rotation.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(T.rotation.apply([0, -1, 0]), [1, 0, 0], atol=1e-12)  # image up = forward


@given(angles, st.floats(-89, 89), angles)
def test_rpy_round_trip(r, p, y):
    np.testing.assert_allclose(rpy_deg(rotation_from_rpy_deg([r, p, y])), [r, p, y], atol=1e-7)


def test_rpy_order_is_yaw_then_pitch_then_roll():
    R = rotation_from_rpy_deg([10, 20, 30])
    expected = Rotation.from_euler("z", 30, degrees=True) * Rotation.from_euler("y", 20, degrees=True)
    expected = expected * Rotation.from_euler("x", 10, degrees=True)
    np.testing.assert_allclose(R.as_matrix(), expected.as_matrix(), atol=1e-12)


@given(finite, finite, finite, angles, st.floats(-89, 89), angles)
def test_fast_ned_conversion_equals_the_reference(x, y, z, r, p, yaw):
    T = make_pose([x, y, z], rotation_from_rpy_deg([r, p, yaw]))
    ref = frames.enu_flu_to_ned_frd(T)
    p_ned, R_ned = frames.enu_flu_to_ned_frd_arrays(T.translation, T.rotation.as_quat())
    np.testing.assert_allclose(p_ned, ref.translation, atol=1e-9)
    assert (R_ned.inv() * ref.rotation).magnitude() < 1e-9

"""Autopilot messages as pure functions: NED/FRD numbers, covariance layout, ODOMETRY frames, the
reset counter, HEARTBEAT, TIMESYNC and the EKF origin."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.graph import EntityPose
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import autopilot, codec, covariance, dialect

DIAG = [0, 6, 11, 15, 18, 20]


def enu(p, yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0):
    rot = Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True)
    return RigidTransform.from_components(np.asarray(p, float), rot)


def test_enu_yaw_90_arrives_as_ned_yaw_0():
    f = autopilot.vision_position_estimate_fields(enu([1, 2, 3], 90), 1_700_000_000_000_000, 4, sigma_m=0.02)
    assert (f["x"], f["y"], f["z"]) == pytest.approx((2.0, 1.0, -3.0), abs=1e-12)
    assert (f["roll"], f["pitch"], f["yaw"]) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert f["usec"] == 1_700_000_000_000_000 and f["reset_counter"] == 4


@pytest.mark.parametrize(
    ("yaw_enu", "yaw_ned"), [(0.0, 90.0), (90.0, 0.0), (180.0, -90.0), (-90.0, 180.0), (45.0, 45.0), (30.0, 60.0)]
)
def test_yaw_mapping(yaw_enu, yaw_ned):
    f = autopilot.vision_position_estimate_fields(enu([0, 0, 0], yaw_enu), 1, 0, sigma_m=0.01)
    # yaw_ned = 90 - yaw_enu, wrapped to (-180, 180]
    assert math.cos(f["yaw"] - math.radians(yaw_ned)) == pytest.approx(1.0, abs=1e-12)


def test_roll_and_pitch_keep_their_meaning():
    # FLU pitch -10 deg (about the left axis: nose up) is FRD pitch +10 deg (about the right axis: nose up).
    f = autopilot.vision_position_estimate_fields(enu([0, 0, 0], 90, pitch_deg=-10), 1, 0, sigma_m=0.01)
    assert math.degrees(f["pitch"]) == pytest.approx(10.0, abs=1e-9)
    # FLU roll +10 deg (left wing up) is FRD roll +10 deg (right wing down): the same motion, same sign.
    f = autopilot.vision_position_estimate_fields(enu([0, 0, 0], 90, roll_deg=10), 1, 0, sigma_m=0.01)
    assert math.degrees(f["roll"]) == pytest.approx(10.0, abs=1e-9)
    assert math.degrees(f["yaw"]) == pytest.approx(0.0, abs=1e-9)


def test_covariance_from_sigma_has_real_variances_on_the_diagonal():
    f = autopilot.vision_position_estimate_fields(enu([1, 2, 3], 90), 1, 0, sigma_m=0.02)
    cov = np.array(f["covariance"])
    assert cov.shape == (21,)
    assert cov[[0, 6, 11]] == pytest.approx([0.0004] * 3)
    att = math.radians(1.0) ** 2  # 0.02 m / 0.25 m = 0.08 rad, above the 1 deg floor
    assert cov[[15, 18, 20]] == pytest.approx([0.08**2] * 3) and cov[15] > att
    assert np.all(np.delete(cov, DIAG) == 0.0)


def test_full_covariance_rotates_into_ned_frd():
    # ENU variances east 1, north 4, up 9 (m^2), east-north covariance 0.5; attitude roll 0.01,
    # pitch 0.02, yaw 0.03 (rad^2) about FLU axes with a roll-pitch term 0.001 and an east-yaw term 0.002.
    C = np.diag([1.0, 4.0, 9.0, 0.01, 0.02, 0.03])
    C[0, 1] = C[1, 0] = 0.5
    C[3, 4] = C[4, 3] = 0.001
    C[0, 5] = C[5, 0] = 0.002
    f = autopilot.vision_position_estimate_fields(enu([0, 0, 0], 90), 1, 0, covariance_enu_flu=C)
    cov = f["covariance"]
    # NED: x = north (4), y = east (1), z = down (9); x-y covariance stays 0.5.
    assert [cov[i] for i in DIAG] == pytest.approx([4.0, 1.0, 9.0, 0.01, 0.02, 0.03])
    assert cov[1] == pytest.approx(0.5)  # (0, 1): north-east
    assert cov[16] == pytest.approx(-0.001)  # (3, 4): roll-pitch flips with the pitch axis
    assert cov[10] == pytest.approx(-0.002)  # (1, 5): east-yaw, yaw axis flips
    assert cov[5] == pytest.approx(0.0)  # (0, 5): north-yaw


@pytest.mark.parametrize(
    "bad",
    [
        np.full((6, 6), math.nan),
        np.diag([1, 1, 1, 1, 1, math.inf]),
        np.diag([1, 1, -1, 1, 1, 1]),
        np.triu(np.ones((6, 6))),  # asymmetric
        np.eye(5),
    ],
)
def test_bad_covariance_is_refused(bad):
    with pytest.raises(AtlasError):
        autopilot.vision_position_estimate_fields(enu([0, 0, 0]), 1, 0, covariance_enu_flu=bad)


@pytest.mark.parametrize("sigma", [math.nan, math.inf, -0.01, 0.0, None])
def test_bad_sigma_is_refused(sigma):
    with pytest.raises(AtlasError):
        autopilot.vision_position_estimate_fields(enu([0, 0, 0]), 1, 0, sigma_m=sigma)


def test_non_finite_pose_is_refused():
    pose = EntityPose("d", np.array([math.nan, 0, 0]), np.array([0, 0, 0, 1.0]), 1, 1, 1, 0.01, 5)
    with pytest.raises(AtlasError):
        codec.vision_position_estimate_fields(pose, 0)
    pose = EntityPose("d", np.zeros(3), np.array([0, 0, 0, 1.0]), 1, 1, 1, math.nan, 5)
    with pytest.raises(AtlasError):
        codec.odometry_fields(pose, 0)


def test_odometry_frames_and_quaternion():
    f = autopilot.odometry_fields(enu([1, 2, 3], 90), 77, 300, sigma_m=0.01)
    assert (f["frame_id"], f["child_frame_id"], f["estimator_type"]) == (20, 12, 2)
    assert (f["x"], f["y"], f["z"]) == pytest.approx((2, 1, -3))
    assert f["q"] == pytest.approx([1, 0, 0, 0], abs=1e-12)  # NED yaw 0: identity, w first
    assert f["quality"] == 100 and f["time_usec"] == 77 and f["reset_counter"] == 300 % 256
    assert math.isnan(f["vx"]) and math.isnan(f["velocity_covariance"][0])
    assert [f["pose_covariance"][i] for i in DIAG[:3]] == pytest.approx([1e-4] * 3)
    msg = dialect.load().MAVLink_odometry_message(**f)  # every field fits the message
    assert msg.frame_id == 20


def test_entity_pose_path_equals_rigid_transform_path():
    T = enu([0.3, -1.2, 2.5], 37, 5, -8)
    x, y, z, w = T.rotation.as_quat()
    pose = EntityPose("d", T.translation, np.array([x, y, z, w]), 1, 1, 2, 0.05, 123)
    a = codec.vision_position_estimate_fields(pose, 2)
    b = autopilot.vision_position_estimate_fields(T, 123, 2, sigma_m=0.05)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], abs=1e-12), k


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-100, 100), min_size=3, max_size=3),
    st.floats(-179, 179),
    st.floats(-80, 80),
    st.floats(-179, 179),
)
def test_vision_fields_rebuild_the_ned_pose(p, yaw, pitch, roll):
    """Rebuilding the pose from the message (NED, ZYX Euler) and converting back gives the ENU pose."""
    T = enu(p, yaw, pitch, roll)
    f = autopilot.vision_position_estimate_fields(T, 1, 0, sigma_m=0.1)
    R_ned_frd = Rotation.from_euler("ZYX", [f["yaw"], f["pitch"], f["roll"]])
    R_enu_ned = Rotation.from_matrix([[0, 1, 0], [1, 0, 0], [0, 0, -1]])
    R_flu_frd = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))
    R_back = R_enu_ned * R_ned_frd * R_flu_frd.inv()
    assert (R_back.inv() * T.rotation).magnitude() < 1e-9
    np.testing.assert_allclose(R_enu_ned.apply([f["x"], f["y"], f["z"]]), p, atol=1e-9)


def test_heartbeat_fields():
    f = autopilot.heartbeat_fields()
    assert (f["type"], f["autopilot"], f["system_status"]) == (18, 8, 4)
    d = dialect.load()
    msg = d.MAVLink_heartbeat_message(**f)
    assert msg.type == d.MAV_TYPE_ONBOARD_CONTROLLER and msg.autopilot == d.MAV_AUTOPILOT_INVALID
    assert autopilot.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY == d.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY == 197


def test_timesync_answers_requests_only_on_the_given_clock_addressed_to_the_requester():
    reply = autopilot.timesync_reply(0, 123_456_789, 1_700_000_000_123_456_789, requester=(7, 1), own_system=7)
    assert reply == {"tc1": 1_700_000_000_123_456_789, "ts1": 123_456_789, "target_system": 7, "target_component": 1}
    assert autopilot.timesync_reply(5, 1, 9, (7, 1), 7) is None  # a reply, not a request
    assert autopilot.timesync_reply(0, 1, 9, (7, 1), 7, target_system=9) is None  # a request to another system
    assert autopilot.timesync_reply(0, 1, 9, (7, 1), 7, target_system=7) is not None
    d = dialect.load()  # the dialect carries TIMESYNC's target extension fields, on the wire and back
    mav = d.MAVLink(None, srcSystem=7, srcComponent=197)
    back = d.MAVLink(None).parse_char(d.MAVLink_timesync_message(**reply).pack(mav))
    assert (back.tc1, back.ts1, back.target_system, back.target_component) == (reply["tc1"], 123_456_789, 7, 1)


def test_origin_fields():
    f = autopilot.set_gps_global_origin_fields(1, 47.397742, 8.545594, 488.0, 5)
    assert f == {"target_system": 1, "latitude": 473977420, "longitude": 85455940, "altitude": 488000, "time_usec": 5}
    with pytest.raises(AtlasError):
        autopilot.set_gps_global_origin_fields(1, 91.0, 0.0, 0.0)
    with pytest.raises(AtlasError):
        autopilot.set_gps_global_origin_fields(1, 0.0, math.nan, 0.0)


@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1))
@example(q=[1.0, 1e-8, 1.0, 0.0])  # 1e-8 from the lock: n - 2 (x^2 + y^2) turned roll by 1.0000000236e-8
def test_euler_zyx_is_scipys(q):
    """The scalar Euler angles of the hot path are scipy's as_euler("ZYX"), for any non-zero
    quaternion, either sign; near gimbal lock (where the split of yaw and roll is not unique) they
    still rebuild the same rotation."""
    r = Rotation.from_quat(q)
    got = np.array(autopilot.euler_zyx(np.array(q)))
    # 1e-8 rad: within 1e-8 of the lock the angles are ill-conditioned (scipy's own round trip is
    # off by 1.4e-7 rad at q = (1, 1e-7, 1, 0)).
    assert (Rotation.from_euler("ZYX", got).inv() * r).magnitude() < 1e-8
    assert autopilot.euler_zyx(-np.array(q)) == pytest.approx(tuple(got), abs=1e-12)
    if abs(got[1]) < np.radians(89.0):
        wrapped = np.angle(np.exp(1j * (got - r.as_euler("ZYX"))))  # +pi and -pi are one angle
        np.testing.assert_allclose(wrapped, 0.0, atol=1e-9)


def test_odometry_quality_comes_from_the_covariance():
    cov = np.diag([1e-4, 1e-4, 0.3**2] + [1e-3] * 3)  # the pose's sigma says 1 cm; z is 30 cm
    p = EntityPose("d1", np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), 1, 1, 1, 0.01, 5, covariance=cov)
    assert codec.odometry_fields(p, 0)["quality"] == covariance.quality_percent(0.3) < 100


def test_heartbeat_status_follows_the_pose():
    assert [autopilot.heartbeat_fields(s)["system_status"] for s in (3, 4, 5)] == [3, 4, 5]
    assert all(len(name) <= 10 for name in autopilot.TELEMETRY_NAMES)


_unit = st.floats(-1.0, 1.0, allow_nan=False)


@given(
    st.tuples(_unit, _unit, _unit, _unit).filter(lambda q: sum(a * a for a in q) > 0.01),
    st.tuples(*(st.floats(-5.0, 5.0, allow_nan=False) for _ in range(3))).filter(lambda v: max(map(abs, v)) > 1e-3),
)
@settings(max_examples=200, deadline=None)
def test_odometry_velocity_in_the_body_is_turned_into_the_local_frame_by_its_attitude(q_wxyz, v_ned):
    """An autopilot's ODOMETRY with its velocity in BODY_FRD (its attitude ``q``, body FRD in local NED) gives
    back the velocity in local NED; the same velocity sent in LOCAL_NED or LOCAL_FRD is taken as it is."""
    w, x, y, z = q_wxyz
    R = Rotation.from_quat([x, y, z, w])
    v_body = R.inv().apply(v_ned)
    got = autopilot.odometry_velocity_ned(
        autopilot.MAV_FRAME_LOCAL_NED, autopilot.MAV_FRAME_BODY_FRD, q_wxyz, v_body, 8
    )
    np.testing.assert_allclose(got, v_ned, atol=1e-9)
    for child in (autopilot.MAV_FRAME_LOCAL_NED, autopilot.MAV_FRAME_LOCAL_FRD):
        same = autopilot.odometry_velocity_ned(autopilot.MAV_FRAME_LOCAL_FRD, child, q_wxyz, v_ned, 8)
        np.testing.assert_allclose(same, v_ned, atol=0)


def test_odometry_velocity_refuses_other_frames_and_our_own_vision_looped_back():
    ned, frd, body = autopilot.MAV_FRAME_LOCAL_NED, autopilot.MAV_FRAME_LOCAL_FRD, autopilot.MAV_FRAME_BODY_FRD
    q = (1.0, 0.0, 0.0, 0.0)
    assert autopilot.odometry_velocity_ned(ned, body, q, (0.0, 0.0, 0.0), 8) is None  # not filled
    assert autopilot.odometry_velocity_ned(ned, body, q, (math.nan, 0.1, 0.0), 8) is None
    for frame, child, estimator, qq in (
        (4, body, 8, q),  # LOCAL_ENU: not an autopilot's
        (ned, 8, 8, q),  # BODY_NED
        (frd, body, autopilot.MAV_ESTIMATOR_TYPE_VISION, q),  # PX4's loopback of the vision it was sent
        (ned, body, autopilot.MAV_ESTIMATOR_TYPE_VIO, q),
        (ned, body, 8, (0.0, 0.0, 0.0, 0.0)),
    ):
        with pytest.raises(AtlasError):
            autopilot.odometry_velocity_ned(frame, child, qq, (0.3, 0.0, 0.0), estimator)

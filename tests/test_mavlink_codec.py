"""Wire format: observation and TUNNEL round trips, fused poses, autopilot message fields."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink import codec, dialect

D = dialect.load()
MD = MarkerData(7, 33, 0.0125, (0.1, -0.2, 1.5), (0.9, 0.1, -0.3, 0.2), 1_700_000_000_123_456, 0.42, 0.8, 9, 65535)


def roundtrip(msg):
    tx = D.MAVLink(None, srcSystem=9, srcComponent=197)
    rx = D.MAVLink(None)
    rx.robust_parsing = True
    out = rx.parse_buffer(msg.pack(tx))
    assert out is not None and len(out) == 1
    return out[0]


def assert_md_equal(a, b):
    assert (a.sensor_id, a.marker_id, a.capture_time_us, a.origin, a.seq) == (
        b.sensor_id, b.marker_id, b.capture_time_us, b.origin, b.seq,
    )  # fmt: skip
    for x, y in zip(
        (*a.p_sensor_marker_m, *a.q_sensor_marker_wxyz, a.sigma_m, a.reprojection_error_px, a.ambiguity_ratio),
        (*b.p_sensor_marker_m, *b.q_sensor_marker_wxyz, b.sigma_m, b.reprojection_error_px, b.ambiguity_ratio),
        strict=True,
    ):
        assert x == pytest.approx(y, rel=1e-6, abs=1e-7)  # float32 on the wire


def test_observation_round_trip():
    msg = roundtrip(codec.encode_observation(D, MD, 0xDEADBEEF))
    assert msg.get_type() == "ATLAS_OBSERVATION" and msg.get_msgId() == 43100
    assert_md_equal(codec.decode_observation(msg, origin=9, fingerprint=0xDEADBEEF), MD)


def test_tunnel_round_trip_and_size():
    payload = codec.tunnel_payload(MD, 0xDEADBEEF)
    assert len(payload) == codec.TUNNEL_STRUCT.size + 1 == 88
    msg = roundtrip(
        D.MAVLink_tunnel_message(0, 0, codec.TUNNEL_PAYLOAD_OBSERVATION, len(payload), list(payload) + [0] * (128 - 88))
    )
    got = codec.decode_tunnel(msg.payload_type, msg.payload_length, msg.payload, 9, 0xDEADBEEF)
    assert_md_equal(got, MD)


@pytest.mark.parametrize(
    ("ptype", "length", "reason"), [(1234, 87, "tunnel_unknown_type"), (43100, 86, "tunnel_bad_length")]
)
def test_tunnel_rejections(ptype, length, reason):
    with pytest.raises(codec.RejectionError) as info:
        codec.decode_tunnel(ptype, length, [0] * 128, 9, 1)
    assert info.value.reason == reason


def test_wrong_fingerprint_and_version_are_refused():
    msg = roundtrip(codec.encode_observation(D, MD, 1))
    with pytest.raises(codec.RejectionError, match="wrong_fingerprint"):
        codec.decode_observation(msg, 9, 2)
    msg.format_version = 2
    with pytest.raises(codec.RejectionError, match="bad_version"):
        codec.decode_observation(msg, 9, 1)


def pose_enu(p, rpy_deg, sigma=0.02, capture=123):
    q = Rotation.from_euler("ZYX", rpy_deg[::-1], degrees=True).as_quat()
    return EntityPose("d", np.array(p, float), q, 1, 1, 3, sigma, capture)


def test_vision_position_estimate_fields():
    msg = roundtrip(codec.vision_position_estimate(D, pose_enu([1, 2, 3], [0, 0, 90]), reset_counter=3))
    assert (msg.x, msg.y, msg.z) == pytest.approx((2, 1, -3))
    assert (msg.roll, msg.pitch, msg.yaw) == pytest.approx((0, 0, 0), abs=1e-6)
    assert msg.usec == 123 and msg.reset_counter == 3
    cov = np.array(msg.covariance)
    assert cov[[0, 6, 11]] == pytest.approx([0.02**2] * 3)
    assert np.all(cov[[15, 18, 20]] > 0)
    off_diag = np.delete(cov, [0, 6, 11, 15, 18, 20])
    assert np.all(off_diag == 0)


def test_covariance_never_zero_or_nan():
    cov = codec.pose_covariance(0.0)
    assert all(cov[i] > 0 and math.isfinite(cov[i]) for i in (0, 6, 11, 15, 18, 20))


def test_odometry_fields():
    msg = roundtrip(codec.odometry(D, pose_enu([1, 2, 3], [0, 0, 0], sigma=0.01), reset_counter=1))
    assert (msg.frame_id, msg.child_frame_id, msg.estimator_type) == (20, 12, 2)
    w, x, y, z = msg.q
    # ENU yaw 0 (nose east) is NED yaw 90.
    assert Rotation.from_quat([x, y, z, w]).as_euler("ZYX", degrees=True) == pytest.approx([90, 0, 0], abs=1e-4)
    assert msg.quality == 100 and math.isnan(msg.vx) and math.isnan(msg.velocity_covariance[0])


@pytest.mark.parametrize(("sigma", "quality"), [(0.005, 100), (0.01, 100), (0.5, 1), (2.0, 1), (math.nan, 0)])
def test_quality_mapping(sigma, quality):
    assert codec.quality_percent(sigma) == quality


def test_fused_pose_round_trip():
    pose = pose_enu([-1, 0.5, 2], [3, 4, 5], sigma=0.03, capture=99)
    msg = roundtrip(codec.encode_fused(D, pose, entity_index=4, frame_index=0, fingerprint=5))
    assert (msg.entity_index, msg.frame_index, msg.level, msg.n_observations, msg.time_usec) == (4, 0, 1, 3, 99)
    assert (msg.x, msg.y, msg.z, msg.sigma) == pytest.approx((-1, 0.5, 2, 0.03))

"""The autopilot's messages as they leave the node: VISION_POSITION_ESTIMATE and ODOMETRY fields in
NED/FRD, the covariance triangle, ODOMETRY quality. (Observation and TUNNEL round trips: test_codec.py.)"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.core.graph import EntityPose
from atlas_onboard.mavlink import codec, dialect

D = dialect.load()


def roundtrip(msg):
    tx = D.MAVLink(None, srcSystem=9, srcComponent=197)
    rx = D.MAVLink(None)
    rx.robust_parsing = True
    out = rx.parse_buffer(msg.pack(tx))
    assert out is not None and len(out) == 1
    return out[0]


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

"""LANDING_TARGET on the wire: each autopilot's form, packed and parsed back by plain pymavlink."""

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink

from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink.landing import ardupilot_landing_target_fields, px4_landing_target_fields


def wire(fields):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    data = mavlink.MAVLink_landing_target_message(**fields).pack(mav)
    return mavlink.MAVLink(None).parse_char(data)


def test_px4_form():
    q = (math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))
    m = wire(px4_landing_target_fields(1_700_000_000_123_456, 3.0, 1.0, -0.25, q))
    # PX4 v1.16 takes a position only with position_valid 1 in MAV_FRAME_LOCAL_NED (1).
    assert (m.position_valid, m.frame, m.time_usec) == (1, mavlink.MAV_FRAME_LOCAL_NED, 1_700_000_000_123_456)
    assert (m.x, m.y, m.z) == pytest.approx((3.0, 1.0, -0.25)) and m.q == pytest.approx(q)
    assert m.type == mavlink.LANDING_TARGET_TYPE_VISION_FIDUCIAL


def test_ardupilot_form():
    m = wire(ardupilot_landing_target_fields(5_000_000, 1.0, 0.0, 3.0, math.sqrt(10), 0.0, math.atan(-1 / 3)))
    # ArduPilot PLND_TYPE 1: MAV_FRAME_BODY_FRD (12) with distance > 0, and the angles of the same vector.
    assert (m.position_valid, m.frame) == (1, mavlink.MAV_FRAME_BODY_FRD)
    assert (m.x, m.y, m.z, m.distance) == pytest.approx((1.0, 0.0, 3.0, math.sqrt(10)))
    los = (-math.tan(m.angle_y), math.tan(m.angle_x), 1.0)
    assert [v / math.hypot(*los) * m.distance for v in los] == pytest.approx([1.0, 0.0, 3.0], abs=1e-5)


def test_bad_values_are_refused_in_one_line():
    with pytest.raises(AtlasError, match="distance > 0"):
        ardupilot_landing_target_fields(1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    with pytest.raises(AtlasError, match="finite"):
        px4_landing_target_fields(1, math.nan, 0.0, 0.0, (1.0, 0.0, 0.0, 0.0))

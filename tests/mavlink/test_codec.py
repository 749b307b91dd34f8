"""The wire format byte for byte: ATLAS_OBSERVATION, its TUNNEL form and ATLAS_FUSED_POSE round trips,
the documented offsets, and every way a received observation is refused (fuzzed fields included)."""

import math
import struct
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink import codec, dialect, framing

pytestmark = pytest.mark.usefixtures("framing_mode")  # every test with the fast path and without

D = dialect.load()
FP = 0xDEADBEEF
MD = MarkerData(7, 33, 0.0125, (0.1, -0.2, 1.5), (0.9, 0.1, -0.3, 0.2), 1_700_000_000_123_456, 0.42, 0.8, 9, 65535)


def wire(msg, sysid=9):
    tx = D.MAVLink(None, srcSystem=sysid, srcComponent=197)
    return msg.pack(tx)


def parse(buf):
    """The messages of ``buf`` as a link's parser gives them (the fast path or pymavlink's: both ways)."""
    rx = framing.parser(D, None, 255, 0, frozenset())
    return rx.parse_buffer(buf) or []


def f32(v):
    return struct.unpack("<f", struct.pack("<f", v))[0]


def assert_md_equal(a, b):
    assert (a.sensor_id, a.marker_id, a.capture_time_us, a.origin, a.seq, a.frame_remaining) == (
        b.sensor_id, b.marker_id, b.capture_time_us, b.origin, b.seq, b.frame_remaining,
    )  # fmt: skip
    got = (*a.p_sensor_marker_m, *a.q_sensor_marker_wxyz, a.sigma_m, a.reprojection_error_px, a.ambiguity_ratio)
    want = (*b.p_sensor_marker_m, *b.q_sensor_marker_wxyz, b.sigma_m, b.reprojection_error_px, b.ambiguity_ratio)
    assert got == tuple(f32(v) for v in want)  # exact: float32 on the wire
    alt_got = (*a.p_sensor_marker_alt_m, *a.q_sensor_marker_alt_wxyz)
    alt_want = (*b.p_sensor_marker_alt_m, *b.q_sensor_marker_alt_wxyz)
    assert [math.isnan(v) for v in alt_got] == [math.isnan(v) for v in alt_want]
    assert [v for v in alt_got if not math.isnan(v)] == [f32(v) for v in alt_want if not math.isnan(v)]


MD_ALT = MarkerData(
    7, 33, 0.0125, (0.1, -0.2, 1.5), (0.9, 0.1, -0.3, 0.2), 1_700_000_000_123_456, 0.42, 0.8, 9, 65535,
    p_sensor_marker_alt_m=(0.11, -0.19, 1.49), q_sensor_marker_alt_wxyz=(0.2, 0.9, 0.3, -0.1),
)  # fmt: skip


@pytest.mark.parametrize("md", [MD, MD_ALT], ids=["without_alt", "with_alt"])
@pytest.mark.parametrize("tunnel", [False, True], ids=["observation", "tunnel"])
def test_round_trip_with_and_without_the_other_solution(md, tunnel):
    if tunnel:
        (msg,) = parse(wire(codec.encode_tunnel(D, md, FP)))
        got = codec.decode_tunnel(msg.payload_type, msg.payload_length, msg.payload, 9, FP, check=True)
    else:
        (msg,) = parse(wire(codec.encode_observation(D, md, FP)))
        got = codec.decode_observation(msg, origin=9, fingerprint=FP, check=True)
    assert_md_equal(got, md)
    assert got.alt_state() is md.alt_state()


def test_the_other_solution_sits_at_its_documented_offsets():
    payload = codec.tunnel_payload(MD_ALT, FP)
    assert struct.unpack_from("<3f", payload, 52) == tuple(f32(v) for v in MD_ALT.p_sensor_marker_alt_m)
    assert struct.unpack_from("<4f", payload, 64) == tuple(f32(v) for v in MD_ALT.q_sensor_marker_alt_wxyz)


def test_observation_round_trip_exact():
    (msg,) = parse(wire(codec.encode_observation(D, MD, FP)))
    assert msg.get_type() == "ATLAS_OBSERVATION" and msg.get_msgId() == 43100 and msg.get_srcSystem() == 9
    assert_md_equal(codec.decode_observation(msg, origin=9, fingerprint=FP, check=True), MD)


def test_observation_payload_offsets_match_the_document():
    buf = wire(codec.encode_observation(D, MD, FP))
    assert buf[0] == 0xFD and buf[7:10] == bytes([43100 & 0xFF, (43100 >> 8) & 0xFF, 0])  # MAVLink 2, id 43100
    payload = buf[10 : 10 + buf[1]]
    assert len(payload) == 87  # the last byte (format_version 1) is not zero, so nothing is truncated
    assert struct.unpack_from("<Q", payload, 0)[0] == MD.capture_time_us
    assert struct.unpack_from("<I", payload, 8)[0] == FP
    assert struct.unpack_from("<3f", payload, 12) == tuple(f32(v) for v in MD.p_sensor_marker_m)
    assert struct.unpack_from("<4f", payload, 24) == tuple(f32(v) for v in MD.q_sensor_marker_wxyz)
    assert struct.unpack_from("<3f", payload, 40) == (f32(0.0125), f32(0.42), f32(0.8))
    assert all(math.isnan(v) for v in struct.unpack_from("<7f", payload, 52))  # no alternative solution
    assert struct.unpack_from("<HHHB", payload, 80) == (7, 33, 65535, 1)
    # The TUNNEL payload is the same 87 bytes, then frame_remaining (here 0, cut from the message).
    assert codec.tunnel_payload(MD, FP) == bytes(payload) + b"\x00"


@pytest.mark.parametrize("remaining", [1, 3, 255])
def test_frame_remaining_travels_in_the_extension_and_in_tunnel(remaining):
    md = replace(MD, frame_remaining=remaining)
    buf = wire(codec.encode_observation(D, md, FP))
    payload = buf[10 : 10 + buf[1]]
    assert len(payload) == 88 and payload[87] == remaining
    (msg,) = parse(buf)
    assert codec.decode_observation(msg, 9, FP).frame_remaining == remaining
    tunnel = codec.tunnel_payload(md, FP)
    assert len(tunnel) == 88 and tunnel[87] == remaining
    got = codec.decode_tunnel(43100, 88, list(tunnel) + [0] * 40, 9, FP)
    assert got.frame_remaining == remaining
    # A sender without the extension: 87 bytes, read as the last of its frame.
    assert codec.decode_tunnel(43100, 87, list(tunnel[:87]) + [0] * 41, 9, FP).frame_remaining == 0
    # Out of the byte's range it is clamped, never an encoding error.
    assert codec.observation_fields(replace(MD, frame_remaining=1000), FP)["frame_remaining"] == 255


def test_tunnel_round_trip():
    msg_obj = codec.encode_tunnel(D, MD, FP)
    (msg,) = parse(wire(msg_obj))
    assert msg.get_type() == "TUNNEL" and msg.payload_type == 43100 > 32767 and msg.payload_length == 88
    assert (msg.target_system, msg.target_component) == (0, 0)
    got = codec.decode_tunnel(msg.payload_type, msg.payload_length, msg.payload, 9, FP, check=True)
    assert_md_equal(got, MD)


@pytest.mark.parametrize(
    ("ptype", "length", "reason"),
    [
        (1234, 88, "tunnel_unknown_type"),
        (43100, 86, "tunnel_bad_length"),
        (43100, 89, "tunnel_bad_length"),
        (43100, 128, "tunnel_bad_length"),
    ],
)
def test_tunnel_rejections(ptype, length, reason):
    with pytest.raises(codec.RejectionError) as info:
        codec.decode_tunnel(ptype, length, [0] * 128, 9, 1)
    assert info.value.reason == reason


def test_tunnel_with_a_short_payload_list_is_refused():
    with pytest.raises(codec.RejectionError, match="tunnel_bad_length"):
        codec.decode_tunnel(43100, 88, [0] * 40, 9, 1)


def test_wrong_fingerprint_and_version_are_refused():
    (msg,) = parse(wire(codec.encode_observation(D, MD, 1)))
    with pytest.raises(codec.RejectionError, match="wrong_fingerprint"):
        codec.decode_observation(msg, 9, 2)
    fields = codec.observation_fields(MD, 1)
    fields["format_version"] = 2
    (msg,) = parse(wire(D.MAVLink_atlas_observation_message(**fields)))
    with pytest.raises(codec.RejectionError, match="bad_version"):
        codec.decode_observation(msg, 9, 1)


def fuzzed(**override):
    fields = codec.observation_fields(MD, FP)
    fields.update(override)
    (msg,) = parse(wire(D.MAVLink_atlas_observation_message(**fields)))
    return msg


@pytest.mark.parametrize(
    ("override", "reason"),
    [
        *[({f: v}, "non_finite") for f in ("x", "y", "z", "sigma") for v in (math.nan, math.inf, -math.inf)],
        *[({f: 3e38}, "out_of_range") for f in ("x", "y", "z")],  # huge but finite float32
        ({"sigma": 3e38}, "bad_sigma"),
        ({"sigma": -0.1}, "bad_sigma"),
        ({"sigma": 0.0}, "bad_sigma"),
        ({"q": [0.0, 0.0, 0.0, 0.0]}, "zero_quaternion"),
        ({"q": [math.nan, 0.0, 0.0, 1.0]}, "non_finite"),
        ({"q": [1.0, math.inf, 0.0, 0.0]}, "non_finite"),
        ({"format_version": 0}, "bad_version"),
        ({"format_version": 255}, "bad_version"),
        ({"fingerprint": FP ^ 1}, "wrong_fingerprint"),
    ],
)
def test_every_bad_field_is_a_rejection_with_its_reason(override, reason):
    with pytest.raises(codec.RejectionError) as info:
        codec.decode_observation(fuzzed(**override), 9, FP, check=True)
    assert info.value.reason == reason


def test_without_check_the_record_reaches_the_listener_for_its_checks():
    md = codec.decode_observation(fuzzed(sigma=-0.1), 9, FP)
    assert md.sigma_m == pytest.approx(-0.1) and md.rejection() is not None


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=0, max_size=300))
def test_random_bytes_never_raise_and_never_yield_an_observation(data):
    rx = D.MAVLink(None)
    rx.robust_parsing = True
    out = rx.parse_buffer(data) or []
    for msg in out:  # random bytes that happen to frame must still fail the CRC
        assert msg.get_type() == "BAD_DATA" or msg.get_type().startswith("UNKNOWN")


def test_truncated_frames_yield_nothing():
    frame = wire(codec.encode_observation(D, MD, FP))
    for cut in range(1, len(frame)):
        rx = D.MAVLink(None)
        rx.robust_parsing = True
        assert [m for m in rx.parse_buffer(frame[:cut]) or [] if m.get_type() == "ATLAS_OBSERVATION"] == []


def test_fused_pose_round_trip_with_name():
    pose = EntityPose("drone_alpha_long_name", np.array([-1, 0.5, 2.0]), np.array([0, 0, 0.6, 0.8]), 2, 3, 4, 0.03, 99)
    (msg,) = parse(wire(codec.encode_fused(D, pose, entity_index=4, frame_index=0, fingerprint=5)))
    assert (msg.entity_index, msg.frame_index, msg.level, msg.n_observations, msg.time_usec) == (4, 0, 2, 4, 99)
    assert (msg.x, msg.y, msg.z, msg.sigma) == (f32(-1), f32(0.5), f32(2), f32(0.03))
    assert msg.q == [f32(0.8), 0.0, 0.0, f32(0.6)]  # w first
    assert msg.entity_name == "drone_alpha_long"  # 16 bytes
    assert msg.fingerprint == 5 and msg.format_version == 1


def test_fused_pose_from_an_older_sender_without_the_name_extension():
    pose = EntityPose("d", np.zeros(3), np.array([0, 0, 0, 1.0]), 1, 1, 1, 0.03, 1)
    buf = bytearray(wire(codec.encode_fused(D, pose, 1, 0, 5)))
    assert buf[1] == 50  # 49 bytes of version-1 fields, then the name "d" (trailing zeros are cut)
    # The same message as a sender without the extension frames it: 49 bytes, CRC over those.
    fields = codec.fused_fields(pose, 1, 0, 5)
    fields["entity_name"] = b""
    (msg,) = parse(wire(D.MAVLink_atlas_fused_pose_message(**fields)))
    assert msg.entity_name == "" and msg.entity_index == 1 and msg.format_version == 1


finite32 = st.floats(-1e6, 1e6, width=32)


@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 0xFFFF),
    st.integers(0, 0xFFFF),
    st.floats(2**-20, 100.0, width=32),
    st.tuples(finite32, finite32, finite32),
    st.tuples(finite32, finite32, finite32, finite32),
    st.integers(0, 2**64 - 1),
    st.integers(0, 0xFFFF),
    st.booleans(),
    st.none() | st.tuples(st.tuples(finite32, finite32, finite32), st.tuples(finite32, finite32, finite32, finite32)),
)
def test_round_trip_is_exact_for_every_representable_record(sensor, marker, sigma, p, q, t_us, seq, tunnel, alt):
    md = MarkerData(sensor, marker, sigma, p, q, t_us, 0.5, math.nan, 77, seq)
    if alt is not None:
        md = replace(md, p_sensor_marker_alt_m=alt[0], q_sensor_marker_alt_wxyz=alt[1])
    if tunnel:
        (msg,) = parse(wire(codec.encode_tunnel(D, md, FP), sysid=77))
        got = codec.decode_tunnel(msg.payload_type, msg.payload_length, msg.payload, msg.get_srcSystem(), FP)
    else:
        (msg,) = parse(wire(codec.encode_observation(D, md, FP), sysid=77))
        got = codec.decode_observation(msg, msg.get_srcSystem(), FP)
    assert (got.sensor_id, got.marker_id, got.capture_time_us, got.seq, got.origin) == (sensor, marker, t_us, seq, 77)
    assert got.p_sensor_marker_m == p and got.q_sensor_marker_wxyz == q and got.sigma_m == sigma
    assert got.reprojection_error_px == 0.5 and math.isnan(got.ambiguity_ratio)
    if alt is None:
        assert all(math.isnan(v) for v in (*got.p_sensor_marker_alt_m, *got.q_sensor_marker_alt_wxyz))
    else:
        assert (got.p_sensor_marker_alt_m, got.q_sensor_marker_alt_wxyz) == alt


def _detection_covariance():
    """A real single-marker covariance (a 20 cm tag 2.8 m below a ceiling camera): its lateral offset
    and tilt correlate at 0.985, the case a compact code of the correlations gets wrong."""
    from atlas_onboard.core.markerdata import matrix_to_upper
    from atlas_onboard.detector import pose

    K = np.array([[480.0, 0, 480], [0, 480.0, 270], [0, 0, 1]])
    R = np.diag([1.0, -1.0, -1.0])  # face up, seen from above
    C = pose.pose_covariance(pose.CornerFit(R, np.array([0.6, -0.3, 2.8]), pose.object_corners(0.2), K), 0.1, 0.05)
    return C, matrix_to_upper(C)


def test_covariance_travels_as_21_float32_and_keeps_its_thin_directions():
    import scipy.linalg

    C, upper = _detection_covariance()
    md = replace(MD, covariance=upper)
    buf = wire(codec.encode_observation(D, md, FP))
    payload = buf[10 : 10 + buf[1]]
    assert len(payload) == 172
    assert struct.unpack_from("<21f", payload, 88) == tuple(f32(v) for v in upper)  # the documented offset
    (msg,) = parse(buf)
    got = codec.decode_observation(msg, 9, FP, check=True)
    assert got.covariance == tuple(f32(v) for v in upper)
    # Every direction's variance kept: the generalized eigenvalues of C against what arrived are 1.
    w = scipy.linalg.eigh(C, got.covariance_matrix(), eigvals_only=True)
    assert np.all(np.abs(w - 1.0) < 1e-4)


@pytest.mark.parametrize("how", ["none", "nan_first"])
def test_no_covariance_is_empty_and_costs_no_bytes(how):
    md = MD if how == "none" else replace(MD, covariance=(math.nan,) + (0.0,) * 20)
    fields = codec.observation_fields(md, FP) if how == "none" else None
    if how == "none":
        assert fields["covariance"] == [0.0] * 21
        buf = wire(codec.encode_observation(D, md, FP))
        assert buf[1] == 87  # all zero: cut from the payload, as from a sender without the extension
        (msg,) = parse(buf)
    else:
        msg = D.MAVLink_atlas_observation_message(
            **{**codec.observation_fields(MD, FP), "covariance": list(md.covariance)}
        )
        (msg,) = parse(wire(msg))
    assert codec.decode_observation(msg, 9, FP, check=True).covariance == ()


def test_a_covariance_that_is_not_positive_definite_is_refused_with_its_reason():
    _, upper = _detection_covariance()
    bad = list(upper)
    bad[0] = -bad[0]  # a negative variance
    msg = D.MAVLink_atlas_observation_message(**{**codec.observation_fields(MD, FP), "covariance": bad})
    (msg,) = parse(wire(msg))
    with pytest.raises(codec.RejectionError) as e:
        codec.decode_observation(msg, 9, FP, check=True)
    assert e.value.reason == "bad_covariance"
    # The TUNNEL form has no room for it: the receiver models the covariance from sigma.
    tunnel = codec.tunnel_payload(replace(MD, covariance=upper), FP)
    assert codec.decode_tunnel(43100, len(tunnel), list(tunnel) + [0] * (128 - len(tunnel)), 9, FP).covariance == ()

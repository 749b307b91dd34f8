"""The framing fast path (atlas_onboard/mavlink/framing.py): the same messages, bad data and parser
state as pymavlink's own parser on any input (differential tests), faster; deferred decoding; the off
switch."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink import codec, dialect, framing

# --- the faster decode (parser_class): the same messages as pymavlink's, faster ----------------------


def _frame(d, msgtype, payload: bytes, seq=7, sysid=42, compid=191, incompat=0) -> bytearray:
    """A MAVLink 2 frame as a sender writes it (trailing zeros of the payload dropped)."""
    body = payload.rstrip(b"\x00") or payload[:1]
    mid = msgtype.id
    head = bytes([0xFD, len(body), incompat, 0, seq, sysid, compid, mid & 0xFF, (mid >> 8) & 0xFF, mid >> 16])
    crc = d.x25crc(bytearray(head[1:] + body + bytes([msgtype.crc_extra]))).crc
    return bytearray(head + body + bytes([crc & 0xFF, crc >> 8]))


def _same(a, b) -> None:
    """Every attribute: the fields, the raw strings, the buffers, the checksum, the header."""
    assert type(a) is type(b)
    assert repr({k: v for k, v in vars(a).items() if k != "_header"}) == repr(
        {k: v for k, v in vars(b).items() if k != "_header"}
    )
    assert vars(a._header) == vars(b._header)


@pytest.fixture
def parsers(monkeypatch):
    """pymavlink's parser and ours, and a count of the frames ours handed to pymavlink's decode."""
    d = dialect.load()
    calls = []
    generic = d.MAVLink.decode
    monkeypatch.setattr(d.MAVLink, "decode", lambda self, buf: calls.append(1) or generic(self, buf))
    monkeypatch.setattr(framing, "_cache", {})
    ours = framing.parser_class(d)(None)
    theirs = d.MAVLink(None)
    for mav in (ours, theirs):
        mav.robust_parsing = True
    yield d, ours, theirs, calls
    monkeypatch.undo()
    framing._cache.pop("parser", None)


def test_parser_decodes_every_message_of_the_dialect_as_pymavlink_does(parsers):
    d, ours, theirs, calls = parsers
    rng = np.random.default_rng(3)
    for msgtype in d.mavlink_map.values():
        size = msgtype.unpacker.size
        for payload in (rng.integers(0, 256, size, dtype=np.uint8).tobytes(), bytes(size), bytes(size - 1) + b"\x05"):
            frame = _frame(d, msgtype, payload)
            mine = ours.parse_buffer(bytes(frame))
            assert len(mine) == 1 and mine[0].get_type() == msgtype.msgname, msgtype.msgname
            _same(mine[0], theirs.parse_buffer(bytes(frame))[0])
    # pymavlink's decode ran for its own parser only: valid unsigned MAVLink 2 frames never need it.
    assert len(calls) == 3 * len(d.mavlink_map)


@given(payload=st.binary(min_size=0, max_size=300), which=st.sampled_from(["atlas_observation", "atlas_fused_pose"]))
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_parser_matches_pymavlink_on_any_atlas_payload(parsers, payload, which):
    d, ours, theirs, _ = parsers
    msgtype = getattr(d, f"MAVLink_{which}_message")
    payload = (payload + bytes(msgtype.unpacker.size))[: msgtype.unpacker.size]
    frame = bytes(_frame(d, msgtype, payload))
    _same(ours.parse_buffer(frame)[0], theirs.parse_buffer(frame)[0])


def test_parser_leaves_bad_and_v1_frames_to_pymavlink_and_frames_signed_ones_alike(parsers):
    d, ours, theirs, calls = parsers
    msgtype = d.MAVLink_atlas_observation_message
    good = _frame(d, msgtype, bytes(range(1, 173)))
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    unknown_flag = _frame(d, msgtype, bytes(range(1, 173)), incompat=0x02)
    for frame in (bad_crc, unknown_flag):
        calls.clear()
        mine, theirs_ = ours.parse_buffer(bytes(frame)), theirs.parse_buffer(bytes(frame))
        assert [m.get_type() for m in mine] == [m.get_type() for m in theirs_] == ["BAD_DATA"]
        assert mine[0].reason == theirs_[0].reason
    calls.clear()
    with pytest.raises(d.MAVError) as mine_err:  # a wrong length field (decode called directly)
        ours.decode(good + b"\x00")
    with pytest.raises(d.MAVError) as theirs_err:
        theirs.decode(good + b"\x00")
    assert str(mine_err.value) == str(theirs_err.value) and calls == [1, 1]
    # MAVLink 1: pymavlink's decode. A signed frame: framed here, as pymavlink's decode frames it.
    v1 = d.MAVLink(None, srcSystem=3)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    hb = d.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)
    calls.clear()
    frame_v1 = hb.pack(v1, force_mavlink1=True)
    _same(ours.parse_buffer(frame_v1)[0], theirs.parse_buffer(frame_v1)[0])
    assert calls == [1, 1]
    key = bytes(range(32))
    sender = d.MAVLink(None, srcSystem=9)
    sender.signing.secret_key, sender.signing.sign_outgoing, sender.signing.timestamp = key, True, 1
    for mav in (ours, theirs):
        mav.signing.secret_key = key
    signed = hb.pack(sender)
    calls.clear()
    mine, theirs_ = ours.parse_buffer(signed)[0], theirs.parse_buffer(signed)[0]
    assert mine._signed and theirs_._signed and calls == [1]
    _same(mine, theirs_)


# --- whole frames at a time, and deferred decoding ----------------------------------------------------


def _pieces(d, rng, kinds):
    """The bytes of a stream made of ``kinds``: valid frames of random types and payloads, and what a
    link can also carry (a bad checksum, an unknown incompat flag, a MAVLink 1 frame, a frame cut
    short, garbage)."""
    types = sorted(d.mavlink_map.values(), key=lambda t: t.id)
    out = []
    for kind in kinds:
        msgtype = d.MAVLink_atlas_observation_message if kind == "obs" else types[int(rng.integers(len(types)))]
        payload = rng.integers(0, 256, msgtype.unpacker.size, dtype=np.uint8).tobytes()
        if rng.random() < 0.5:  # trailing zeros, dropped on the wire
            payload = payload[: int(rng.integers(1, len(payload) + 1))].ljust(msgtype.unpacker.size, b"\x00")
        frame = _frame(d, msgtype, payload, seq=int(rng.integers(256)), sysid=int(rng.integers(1, 256)))
        if kind == "bad_crc":
            frame[-2] ^= 0x5A
        elif kind == "flag":
            frame = _frame(d, msgtype, payload, incompat=0x04)
        elif kind == "v1":
            frame = bytearray(d.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(d.MAVLink(None), force_mavlink1=True))
        elif kind == "cut":
            frame = frame[: int(rng.integers(1, len(frame)))]
        elif kind == "garbage":
            frame = bytearray(rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8).tobytes())
        out.append(bytes(frame))
    return out


def _fields(msg) -> list:
    """What a receiver sees of a message (a BAD_DATA's reason and bytes; a message's every field)."""
    if msg.get_type() == "BAD_DATA":
        return ["BAD_DATA", msg.reason, bytes(msg.data)]
    return [msg.get_type(), msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq(), repr(msg.to_dict())]


def _parse_both(ours, theirs, pieces, rng, stream):
    """What our parser and pymavlink's give for ``pieces`` read one per read, or (``stream``) for their
    bytes cut at up to five random places."""
    if stream:
        data = b"".join(pieces)
        cuts = sorted(int(c) for c in rng.integers(0, len(data) + 1, int(rng.integers(0, 6))))
        pieces = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]
    got, want = [], []
    for piece in pieces:
        got += ours.parse_buffer(piece) or []
        want += theirs.parse_buffer(piece) or []
    return got, want


@given(
    kinds=st.lists(st.sampled_from(["frame", "obs", "frame", "bad_crc", "flag", "v1", "cut", "garbage"]), max_size=12),
    seed=st.integers(0, 2**32 - 1),
    stream=st.booleans(),
    deferred=st.booleans(),
)
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_whole_frames_parse_as_pymavlink_parses_any_stream(parsers, kinds, seed, stream, deferred):
    """Any mix of frames and bad data, read as datagrams (one piece per read) or as a stream cut at
    random places: the same messages, bad data and counters as pymavlink's byte-at-a-time parser, with
    or without deferred decoding (a deferred frame's fields are those of the message it decodes to)."""
    d, ours, theirs, _ = parsers
    rng = np.random.default_rng(seed)
    ours.deferred_ids = frozenset(t.id for t in d.mavlink_map.values()) if deferred else frozenset()
    pieces = _pieces(d, rng, kinds)
    got, want = _parse_both(ours, theirs, pieces, rng, stream)
    for mine in got:
        if isinstance(mine, framing.Deferred):
            scalars = {name: getattr(mine, name) for name in framing._scalar_readers(mine._msgtype)}
            assert mine._msg is None  # read from the payload, not decoded
            msg = mine.decoded()
            assert repr(scalars) == repr({name: getattr(msg, name) for name in scalars})  # NaN included
    assert [_fields(m) for m in got] == [_fields(m) for m in want]
    assert deferred or not any(isinstance(m, framing.Deferred) for m in got)
    for name in ("total_bytes_received", "total_packets_received", "total_receive_errors", "expected_length"):
        assert getattr(ours, name) == getattr(theirs, name), name
    assert ours.buf[ours.buf_index :] == theirs.buf[theirs.buf_index :]


def test_a_deferred_frame_reads_its_fields_without_decoding_and_decodes_once(parsers):
    d, ours, theirs, calls = parsers
    ours.deferred_ids = frozenset({d.MAVLink_atlas_observation_message.id})
    sender = d.MAVLink(None, srcSystem=33, srcComponent=197)
    md = MarkerData(3, 9, 0.01, (0.1, -0.2, 2.0), (1.0, 0.0, 0.0, 0.0), 1_700_000_000_000_000, seq=7)
    frames = codec.encode_observation(d, md, 0xABCD1234).pack(sender)
    frames += d.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(sender)
    obs, hb = ours.parse_buffer(frames)
    assert isinstance(obs, framing.Deferred) and not isinstance(hb, framing.Deferred)
    assert (obs.get_type(), obs.get_srcSystem(), obs.get_srcComponent(), obs.get_msgId()) == (
        "ATLAS_OBSERVATION", 33, 197, 43100,
    )  # fmt: skip
    assert (obs.fingerprint, obs.seq, obs.sensor_id, obs.marker_id, obs.format_version) == (
        0xABCD1234, 7, 3, 9, codec.FORMAT_VERSION,
    )  # fmt: skip
    assert obs._msg is None and calls == []
    assert obs.q == pytest.approx([1.0, 0.0, 0.0, 0.0])  # an array: decodes
    assert obs.decoded() is obs.decoded() and obs._msg is not None
    _same(obs.decoded(), theirs.parse_buffer(frames)[0])


def test_the_off_switch_gives_pymavlink_s_own_parser(monkeypatch):
    """With the fast path off, a link's parser is the generated class itself: no deferred frames."""
    d = dialect.load()
    monkeypatch.setattr(framing, "FAST", False)
    mav = framing.parser(d, None, 1, 197, frozenset({d.MAVLink_atlas_observation_message.id}))
    assert type(mav) is d.MAVLink and mav.robust_parsing
    sender = d.MAVLink(None, srcSystem=3, srcComponent=197)
    md = MarkerData(3, 9, 0.01, (0.1, -0.2, 2.0), (1.0, 0.0, 0.0, 0.0), 1_700_000_000_000_000, seq=7)
    (msg,) = mav.parse_buffer(codec.encode_observation(d, md, 1).pack(sender))
    assert not isinstance(msg, framing.Deferred) and msg.marker_id == 9
    monkeypatch.setattr(framing, "FAST", True)
    fast = framing.parser(d, None, 1, 197, frozenset({d.MAVLink_atlas_observation_message.id}))
    assert type(fast) is framing.parser_class(d) and isinstance(
        fast.parse_buffer(msg.get_msgbuf())[0], framing.Deferred
    )


KEY = bytes(range(32))


def _signed_pieces(d, rng, kinds):
    """Frames as signing peers send them: signed with our key (``signed``), with another key
    (``other_key``), a replay of an earlier signed frame (``replay``), unsigned (``unsigned``), and
    a signed frame cut short (``cut``)."""
    good = d.MAVLink(None, srcSystem=9, srcComponent=197)
    other = d.MAVLink(None, srcSystem=9, srcComponent=197)
    for mav, key in ((good, KEY), (other, bytes(32))):
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = key, True, 10**9
        mav.signing.link_id = 1
    plain = d.MAVLink(None, srcSystem=9, srcComponent=197)
    sent: list[bytes] = []
    out = []
    for kind in kinds:
        md = MarkerData(3, int(rng.integers(0, 50)), 0.01, (0.1, -0.2, 2.0), (1.0, 0.0, 0.0, 0.0), 1_700_000_000, seq=7)
        msg = (
            codec.encode_observation(d, md, 1) if rng.random() < 0.5 else d.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)
        )
        if kind == "replay" and sent:
            frame = sent[int(rng.integers(len(sent)))]
        elif kind == "other_key":
            frame = msg.pack(other)
        elif kind == "unsigned":
            frame = msg.pack(plain)
        else:
            frame = msg.pack(good)
            sent.append(frame)
            if kind == "cut":
                frame = frame[: int(rng.integers(1, len(frame)))]
        out.append(bytes(frame))
    return out


@given(
    kinds=st.lists(st.sampled_from(["signed", "signed", "other_key", "replay", "unsigned", "cut"]), max_size=10),
    seed=st.integers(0, 2**32 - 1),
    stream=st.booleans(),
    deferred=st.booleans(),
    keyed=st.sampled_from(["no_key", "require", "allow_unsigned"]),
)
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_signed_frames_parse_as_pymavlink_parses_them(parsers, kinds, seed, stream, deferred, keyed):
    """Signed, wrongly signed, replayed and unsigned frames, with a key or without, unsigned ones
    allowed or not: the same messages, BAD_DATA, signing counts and stream state as pymavlink's."""
    d, ours, theirs, _ = parsers
    rng = np.random.default_rng(seed)
    ours.deferred_ids = frozenset(t.id for t in d.mavlink_map.values()) if deferred else frozenset()
    if keyed != "no_key":
        for mav in (ours, theirs):
            mav.signing.secret_key, mav.signing.timestamp = KEY, 10**9
            if keyed == "allow_unsigned":
                mav.signing.allow_unsigned_callback = lambda _mav, msg_id: msg_id == 0  # HEARTBEAT only
    pieces = _signed_pieces(d, rng, kinds)
    got, want = _parse_both(ours, theirs, pieces, rng, stream)
    got = [m.decoded() if isinstance(m, framing.Deferred) else m for m in got]
    assert [_fields(m) for m in got] == [_fields(m) for m in want]
    assert [getattr(m, "_signed", None) for m in got] == [getattr(m, "_signed", None) for m in want]
    counts = ("sig_count", "goodsig_count", "badsig_count", "unsigned_count", "reject_count", "timestamp")
    assert [getattr(ours.signing, k) for k in counts] == [getattr(theirs.signing, k) for k in counts]
    assert ours.signing.stream_timestamps == theirs.signing.stream_timestamps
    for name in ("total_bytes_received", "total_packets_received", "total_receive_errors", "expected_length"):
        assert getattr(ours, name) == getattr(theirs, name), name

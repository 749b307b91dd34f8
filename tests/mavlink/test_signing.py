"""Signing timestamps: a frame stamped far ahead is refused and adopts nothing, one a little ahead is
adopted only up to the bound, the replay table outlives a reopened connection, and a state file that
holds an adopted future timestamp is repaired at load."""

import json
import os
import time

import pytest

from atlas_onboard.mavlink import codec
from atlas_onboard.mavlink.signing import MAX_AHEAD_S, SIGNING_TICKS_PER_S, signing_timestamp
from tests.mavlink.loopback import FP, MD, RawSender, drain, free_port, kinds, make_link, poll_until, write_key

pytestmark = pytest.mark.deadlines  # sockets and their deadlines

TICKS_2_48 = (1 << 48) - 1


def _rx(tmp_path, closing, **kw):
    key = write_key(tmp_path, os.urandom(32))
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, key, **kw)
    closing(rx)
    rx.open()
    return rx, port, key.read_bytes()


def test_a_frame_stamped_near_2_48_is_refused_and_moves_no_timestamp(tmp_path, closing):
    rx, port, key = _rx(tmp_path, closing)
    before = rx.mav.signing.timestamp
    evil = RawSender(port, 250, key, timestamp=TICKS_2_48 - 10)
    closing(evil)
    evil.raw(evil.observation(seq=1))
    assert drain(rx, 0.3) == []
    assert rx.counters["signature_ahead"] == 1
    now = signing_timestamp(time.time())
    assert before <= rx.mav.signing.timestamp <= now + 1000
    # the same stream, stamped by a right clock, still passes: the future frame left no trace
    good = RawSender(port, 250, key)
    closing(good)
    good.raw(good.observation(seq=2))
    assert kinds(poll_until(rx, lambda m: len(m) >= 1)) == ["ATLAS_OBSERVATION"]


def test_a_frame_a_little_ahead_passes_but_raises_the_own_timestamp_only_to_the_bound(tmp_path, closing):
    rx, port, key = _rx(tmp_path, closing)
    ahead = RawSender(port, 250, key, timestamp=signing_timestamp(time.time()) + 40 * SIGNING_TICKS_PER_S)
    closing(ahead)
    ahead.raw(ahead.observation(seq=1))
    assert kinds(poll_until(rx, lambda m: len(m) >= 1)) == ["ATLAS_OBSERVATION"]
    bound = signing_timestamp(time.time()) + MAX_AHEAD_S * SIGNING_TICKS_PER_S
    assert rx.mav.signing.timestamp <= bound
    assert rx.mav.signing.timestamp >= bound - 2 * SIGNING_TICKS_PER_S  # raised, to the bound
    assert rx.counters["signing_clock_behind"] == 1


def test_the_replay_table_outlives_a_reopened_connection(tmp_path, closing):
    rx, port, key = _rx(tmp_path, closing)
    peer = RawSender(port, 250, key)
    closing(peer)
    frame = peer.observation(seq=1)
    peer.raw(frame)
    assert len(poll_until(rx, lambda m: len(m) >= 1)) == 1
    rx._drop()  # the connection fails; the link reopens it
    poll_until(rx, lambda _m: rx.is_open, 2.0)
    assert rx.is_open
    peer.raw(frame)
    assert drain(rx, 0.3) == []
    assert rx.counters["signature_replayed"] == 1


def test_a_state_file_holding_a_future_timestamp_is_repaired_at_load(tmp_path, closing):
    key = write_key(tmp_path, os.urandom(32))
    state = tmp_path / "state"
    url = f"udpout:127.0.0.1:{free_port()}"
    first = make_link(url, 250, key, state_dir=state)
    first.open()
    first.send(codec.encode_observation(first.dialect, MD, FP))
    first.close()
    (path,) = state.glob("signing-*.json")
    path.write_text(json.dumps({"timestamp": TICKS_2_48}))  # what an older version adopted and saved
    second = make_link(url, 250, key, state_dir=state)
    closing(second)
    second.open()
    now = signing_timestamp(time.time())
    assert now <= second.mav.signing.timestamp <= now + 25 * SIGNING_TICKS_PER_S  # bound plus the save period
    assert second.counters["signing_state_repaired"] == 1
    second.close()
    assert json.loads(path.read_text())["timestamp"] <= now + 25 * SIGNING_TICKS_PER_S

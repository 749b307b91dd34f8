"""Each peer's clock measured from its stamps: a stamp further in the future than the peer's offset
and jitter allow is refused; a peer whose clock really runs ahead is learnt, not refused for ever;
rare forged stamps cannot move the measure."""

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.core.peerclock import FUTURE_MARGIN_S, MIN_SAMPLES, UNMEASURED_LEAD_S, PeerClocks

S = 1_000_000  # microseconds per second


def _stream(clocks, origin, offset_s, latency_s, jitter_s, n, t0_s=100.0, rate_hz=30.0, rng=None):
    """``n`` observations of ``origin``, whose clock reads ``offset_s`` ahead of ours, arriving
    ``latency_s`` (+ up to ``jitter_s``) after capture; returns how many were refused."""
    rng = rng or random.Random(0)
    refused = 0
    for i in range(n):
        capture_true = t0_s + i / rate_hz
        arrival = capture_true + latency_s + rng.uniform(0.0, jitter_s)
        refused += clocks.future(origin, round((capture_true + offset_s) * S), round(arrival * S))
    return refused


@settings(max_examples=40, deadline=None)
@given(offset_ms=st.integers(-500, 500), latency_ms=st.integers(0, 80), jitter_ms=st.integers(0, 30))
def test_an_honest_peer_is_never_refused_once_measured_and_a_stamp_09_s_ahead_always_is(
    offset_ms, latency_ms, jitter_ms
):
    clocks = PeerClocks()
    rng = random.Random(offset_ms * 1000 + latency_ms)
    _stream(clocks, 7, offset_ms / 1e3, latency_ms / 1e3, jitter_ms / 1e3, MIN_SAMPLES, rng=rng)
    assert _stream(clocks, 7, offset_ms / 1e3, latency_ms / 1e3, jitter_ms / 1e3, 300, t0_s=101.0, rng=rng) == 0
    # The same peer's true observation stamped 0.9 s ahead of its own clock, every 0.9 s among them.
    for k in range(5):
        capture = 120.0 + 0.9 * k
        arrival = capture + latency_ms / 1e3
        assert clocks.future(7, round((capture + offset_ms / 1e3 + 0.9) * S), round(arrival * S))
        _stream(clocks, 7, offset_ms / 1e3, latency_ms / 1e3, jitter_ms / 1e3, 27, t0_s=capture + 0.01, rng=rng)


def test_a_lead_within_the_margin_is_taken_and_beyond_it_refused():
    clocks = PeerClocks()
    _stream(clocks, 3, 0.0, 0.005, 0.0, 64)  # exactly 5 ms of latency: no jitter measured
    now = 200 * S
    assert not clocks.future(3, now + round(0.005 * S) - round((FUTURE_MARGIN_S - 0.001) * S), now)
    assert clocks.future(3, now + round((FUTURE_MARGIN_S + 0.001) * S), now)


def test_before_its_clock_is_measured_a_peer_may_lead_by_the_unmeasured_allowance_only():
    clocks = PeerClocks()
    now = 50 * S
    assert not clocks.future(9, now + round((UNMEASURED_LEAD_S - 0.01) * S), now)
    assert clocks.future(9, now + round((UNMEASURED_LEAD_S + 0.01) * S), now + 1)


def test_each_origin_has_its_own_clock():
    clocks = PeerClocks()
    _stream(clocks, 1, 0.3, 0.002, 0.002, 64)  # a clock 300 ms ahead: learnt
    _stream(clocks, 2, 0.0, 0.002, 0.002, 64)
    now = 300 * S
    assert not clocks.future(1, now + round(0.29 * S), now)
    assert clocks.future(2, now + round(0.29 * S), now)

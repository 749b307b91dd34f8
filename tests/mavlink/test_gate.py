"""The peer gate with times passed in: duplicates dropped once admitted, per-(link, peer) token buckets,
bounded memory, rate-limited clock-skew reports."""

from dataclasses import replace

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink.gate import PeerGate, TokenBucket

NS = 1_000_000_000
BASE = MarkerData(10, 5, 0.01, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), 1_700_000_000_000_000, origin=250, seq=1)


def obs(origin=250, seq=1, sensor=10, marker=5, t_us=BASE.capture_time_us):
    return replace(BASE, origin=origin, seq=seq, sensor_id=sensor, marker_id=marker, capture_time_us=t_us)


def test_duplicate_from_another_link_is_dropped_once_admitted():
    gate = PeerGate(own_system_id=1)
    assert gate.admit(obs(), link_index=0, rate_hz=100, arrival_ns=0) is None
    assert gate.admit(obs(), link_index=1, rate_hz=100, arrival_ns=1000) == "duplicate"  # second link
    assert gate.admit(obs(), link_index=0, rate_hz=100, arrival_ns=2000) == "duplicate"  # mesh echo
    # Any field of the identity that differs makes another observation.
    for other in (obs(origin=251), obs(seq=2), obs(sensor=11), obs(marker=6), obs(t_us=BASE.capture_time_us + 1)):
        assert gate.admit(other, 0, 100, 3000) is None


def test_own_echo():
    gate = PeerGate(own_system_id=250)
    assert gate.admit(obs(origin=250), 0, 100, 0) == "own_echo"


def test_window_is_bounded_and_forgets_the_oldest():
    gate = PeerGate(own_system_id=1, dedupe_window=100)
    for k in range(1000):
        assert gate.admit(obs(seq=k), 0, 1e9, k) is None
    assert gate.sizes() == (100, 1)
    assert gate.admit(obs(seq=999), 0, 1e9, 2000) == "duplicate"  # still in the window
    assert gate.admit(obs(seq=0), 0, 1e9, 2001) is None  # fell out of it


def test_a_flooding_peer_spends_only_its_own_tokens():
    gate = PeerGate(own_system_id=1)
    # Peer 250 sends 500 observations within 10 ms at a 50 Hz limit: one second's burst (50) passes.
    flood = [gate.admit(obs(origin=250, seq=k), 0, 50.0, k * 20_000) for k in range(500)]
    assert flood.count(None) == 50 and flood.count("rate_limited") == 450
    # Peer 251, on the same link at the same time, is not affected.
    assert [gate.admit(obs(origin=251, seq=k), 0, 50.0, 10_000_000 + k) for k in range(5)] == [None] * 5
    # Nor is peer 250 itself on another link (a spoofed id on link 0 cannot drain link 1).
    assert gate.admit(obs(origin=250, seq=10_000), 1, 50.0, 10_000_000) is None
    # After 0.1 s at 50 Hz, peer 250 on link 0 has 5 tokens again.
    later = [gate.admit(obs(origin=250, seq=20_000 + k), 0, 50.0, 110_000_000) for k in range(10)]
    assert later.count(None) == 5


def test_memory_stays_bounded_under_every_system_id():
    gate = PeerGate(own_system_id=1, dedupe_window=512)
    for k in range(20_000):
        gate.admit(obs(origin=k % 256, seq=k), k % 3, 10.0, k)
    seen, buckets = gate.sizes()
    assert seen == 512 and buckets <= 3 * 256


def test_token_bucket_numbers():
    b = TokenBucket(10.0, now_ns=0)
    assert sum(b.take(0) for _ in range(20)) == 10  # burst of one second's worth
    assert sum(b.take(NS // 2) for _ in range(20)) == 5  # half a second refills five
    assert sum(b.take(NS // 4) for _ in range(20)) == 0  # a clock going back refills nothing


def test_skew_is_counted_every_time_and_reported_once_per_interval():
    gate = PeerGate(own_system_id=1, skew_warn_s=0.1, skew_warn_every_s=10.0)
    md = obs()
    wall_ns = md.capture_time_us * 1000
    assert gate.check_skew(md, wall_ns + 50_000_000, 0) is None  # 50 ms: fine
    report = gate.check_skew(md, wall_ns + 2 * NS, 0)
    assert report is not None and report.origin == 250 and abs(report.skew_s - 2.0) < 1e-9
    assert gate.check_skew(md, wall_ns - 3 * NS, 5 * NS) is None  # counted, not reported again yet
    assert gate.check_skew(md, wall_ns - 3 * NS, 11 * NS).skew_s == -3.0  # the interval has passed
    assert gate.check_skew(obs(origin=251), wall_ns + NS, 11 * NS) is not None  # other peers separately
    assert gate.skew_warnings == 4


def test_a_stamp_more_than_a_second_from_our_clock_is_refused():
    gate = PeerGate(own_system_id=1)
    wall_ns = 1_700_000_000_000_000_000
    t_us = wall_ns // 1000
    for offset_us, refused in ((0, False), (-999_999, False), (999_999, False), (-1_000_001, True),
                               (1_000_001, True), (-t_us, True), (10**15, True)):  # fmt: skip
        assert gate.stamp_refused(obs(1, 1, t_us=t_us + offset_us), wall_ns) is refused, offset_us


def test_origin_binding_by_the_world_files_nodes():
    from atlas_onboard.core.rejection import Rejection
    from atlas_onboard.mavlink.gate import OriginBinding

    # sensors: 1 on d1 (this node's entity), 2 on d2 (system 2), 10 on world (system 250), 30 on an
    # entity that no node runs
    binding = OriginBinding({1: "d1", 2: "d2", 10: "world", 30: "orphan"}, {"d1": 1, "d2": 2, "world": 250}, "d1")
    assert binding.observation(2, 2) is None and binding.observation(10, 250) is None
    assert binding.observation(2, 250) is Rejection.NOT_OWNER
    assert binding.observation(10, 2) is Rejection.NOT_OWNER
    for origin in (1, 2, 250, 77):  # the own entity's sensor: from no one, not even "ourselves"
        assert binding.observation(1, origin) is Rejection.OWN_SENSOR
    assert binding.observation(30, 2) is Rejection.UNBOUND_SENSOR
    assert binding.observation(999, 2) is Rejection.UNKNOWN_SENSOR
    assert binding.unbound == ("orphan",)
    assert binding.fused("d2", 2) is None and binding.fused("d1", 2) is Rejection.NOT_OWNER
    assert binding.fused("d2", 77) is Rejection.UNKNOWN_ORIGIN
    assert binding.is_node(250) and not binding.is_node(77)


def test_report_limiter_one_per_reason_per_period_with_the_count():
    from atlas_onboard.mavlink.gate import ReportLimiter

    limiter = ReportLimiter(every_s=10.0, max_keys=3)
    assert limiter.allow("a", 0) == 0
    assert [limiter.allow("a", k * NS) for k in range(1, 10)] == [None] * 9
    assert limiter.allow("b", 5 * NS) == 0  # another reason is not held back
    assert limiter.allow("a", 10 * NS) == 9  # the next one says how many were suppressed
    assert limiter.allow("a", 11 * NS) is None and limiter.suppressed_total == 10
    for key in ("c", "d", "e", "f"):  # bounded: an attacker's many reasons cannot grow it
        limiter.allow(key, 12 * NS)
    assert len(limiter._last_ns) <= 3

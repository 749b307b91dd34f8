"""Publishing decisions: never stale, never twice, rate-capped, reset counter on loss and jumps."""

import numpy as np

from atlas_onboard.core.graph import TransformGraph
from atlas_onboard.publisher import Publisher

MS = 1_000_000


def graph_with(p, capture_us, now_ns, g=None):
    g = g or TransformGraph(["world", "d"], 250 * MS)
    g.update_edge((1, 1), "world", "d", np.asarray(p, float), np.array([0, 0, 0, 1.0]), 0.01, now_ns, capture_us)
    return g


def test_sends_once_per_new_observation_and_stops_when_edges_expire():
    pub = Publisher("d", rate_hz=30)
    g = graph_with([1, 2, 3], capture_us=1000, now_ns=0)
    out, status = pub.autopilot(g.evaluate(0), 0)
    assert status == "pose found" and out is not None and out.reset_counter == 0
    np.testing.assert_allclose(out.pose.p_world_m, [1, 2, 3])
    out, status = pub.autopilot(g.evaluate(40 * MS), 40 * MS)  # same observation: nothing new
    assert out is None and status is None
    out, status = pub.autopilot(g.evaluate(250 * MS + 1), 250 * MS + 1)  # edge expired
    assert out is None and status == "pose lost"
    out, status = pub.autopilot(g.evaluate(300 * MS), 300 * MS)
    assert out is None and status is None
    assert pub.sent == 1


def test_rate_cap_is_a_token_bucket():
    pub = Publisher("d", rate_hz=10)  # burst 2: two back to back, then one per 100 ms
    g = graph_with([0, 0, 0], 1, 0)
    assert pub.autopilot(g.evaluate(0), 0)[0] is not None
    graph_with([0, 0, 0.01], 2, 1 * MS, g)
    assert pub.autopilot(g.evaluate(1 * MS), 1 * MS)[0] is not None  # the burst allows a second
    assert pub.next_autopilot_ns() is None  # the bucket is empty, but nothing is held back
    graph_with([0, 0, 0.02], 3, 2 * MS, g)
    assert pub.autopilot(g.evaluate(2 * MS), 2 * MS)[0] is None  # the third waits for a token
    assert pub.suppressed_rate == 1
    release = pub.next_autopilot_ns()
    assert 95 * MS < release <= 101 * MS  # one token refills in 100 ms
    out, _ = pub.autopilot(g.evaluate(release), release)
    assert out is not None and out.pose.capture_time_us == 3
    assert pub.next_autopilot_ns() is None  # the held pose went: nothing more to wait for
    sent = 0
    for k in range(100):  # a steady 100 Hz of new observations for 1 s: about 10 go out
        t = 200 * MS + k * 10 * MS
        graph_with([0, 0, 0.03], 10 + k, t, g)
        sent += pub.autopilot(g.evaluate(t), t)[0] is not None
    assert 10 <= sent <= 12


def test_reset_counter_on_found_again_and_on_jump():
    pub = Publisher("d", rate_hz=1000, reset_jump_m=0.5)
    g = graph_with([0, 0, 0], 1, 0)
    assert pub.autopilot(g.evaluate(0), 0)[0].reset_counter == 0
    pub.autopilot(g.evaluate(300 * MS), 300 * MS)  # lost
    graph_with([0.1, 0, 0], 2, 400 * MS, g)
    out, status = pub.autopilot(g.evaluate(400 * MS), 400 * MS)
    assert status == "pose found" and out.reset_counter == 1
    graph_with([0.2, 0, 0], 3, 410 * MS, g)  # small move: same counter
    assert pub.autopilot(g.evaluate(410 * MS), 410 * MS)[0].reset_counter == 1
    graph_with([1.0, 0, 0], 4, 420 * MS, g)  # 0.8 m jump
    assert pub.autopilot(g.evaluate(420 * MS), 420 * MS)[0].reset_counter == 2


def test_reset_counter_wraps_like_the_uint8_field_and_a_loss_before_any_pose_is_no_reset():
    pub = Publisher("d", rate_hz=1000, reset_jump_m=0.5)
    g = TransformGraph(["world", "d"], 250 * MS)
    assert pub.autopilot(g.evaluate(0), 0) == (None, None)  # nothing yet: no loss to report
    graph_with([0, 0, 0], 1, 10 * MS, g)
    assert pub.autopilot(g.evaluate(10 * MS), 10 * MS)[0].reset_counter == 0
    pub.reset_counter = 255
    graph_with([5, 5, 5], 2, 20 * MS, g)
    assert pub.autopilot(g.evaluate(20 * MS), 20 * MS)[0].reset_counter == 0


def test_non_finite_pose_is_never_sent():
    pub = Publisher("d")
    g = graph_with([np.nan, 0, 0], 1, 0)
    out, status = pub.autopilot(g.evaluate(0), 0)
    assert out is None and status is None and pub.sent == 0


def test_fused_rate():
    pub = Publisher("d", fused_rate_hz=5)
    due = [pub.fused_due(t * 50 * MS) for t in range(10)]  # every 50 ms for 0.5 s
    assert due == [True, False, False, False, True, False, False, False, True, False]

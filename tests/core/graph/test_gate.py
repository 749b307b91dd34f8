"""The gate against peers that lie: a covariance that would widen the gate of a heavily weighed
candidate, forged views that would move an entity faster than it can fly (the speed bound, applied to
each candidate before any consensus), and the bound's clock (a refused candidate does not restart it,
a loss widens it at the vehicle's top speed)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.core.graph import TransformGraph
from atlas_onboard.core.graph.gate import SPEED_CANDIDATE_SIGMA_CAP_M, SPEED_GATE_SIGMA
from tests.helpers import pose

MS = 1_000_000
TIMEOUT_NS = 250 * MS
HUGE = np.diag([400.0, 400.0, 400.0, 1.0, 1.0, 1.0])  # 20 m per axis, a radian of attitude


def _edge(g, key, a, b, T, sigma, now_ns, capture_us, cov=None):
    g.update_edge(key, a, b, T.translation, T.rotation.as_quat(), sigma, now_ns, capture_us, cov_a_b=cov)


@pytest.mark.parametrize("max_speed", [0.0, 5.0])
def test_a_peer_with_a_tiny_sigma_and_a_huge_covariance_cannot_move_a_drone_with_its_own_view(max_speed):
    """The own camera (sensor 1) sees a floor tag; a world camera (sensor 10) claims the drone 20 m
    east with sigma 0.1 mm and a covariance of 20 m. The gate judges it with the sigma it would weigh
    by (with the speed bound off too), so it is out; the pose is the camera's, exactly."""
    g = TransformGraph(["world", "d"], TIMEOUT_NS, outlier_gate_sigma=5.0, anchor_sensors={1}, max_speed_m_s=max_speed)
    truth = pose([1.0, 2.0, 1.5], [0, 0, 30])
    lie = pose([21.0, 2.0, 1.5], [0, 0, 30])
    for t in range(0, 200, 33):
        _edge(g, (1, 0), "d", "world", truth.inv(), 0.01, t * MS, t * 1000)
        _edge(g, (10, 5), "world", "d", lie, 1e-4, t * MS, t * 1000, HUGE)
        r = g.evaluate(t * MS)
        np.testing.assert_allclose(r.poses["d"].p_world_m, truth.translation, atol=1e-9)
    assert g.gated_total + g.too_fast_total == 7


def _relay(max_speed=5.0, k=5.0):
    """A relay follower's graph: world -> lead only through the leader's camera (sensor 1, a peer),
    lead -> f through the follower's own camera (sensor 2) on the leader's marker."""
    return TransformGraph(
        ["world", "lead", "f"], TIMEOUT_NS, outlier_gate_sigma=k, anchor_sensors={2}, max_speed_m_s=max_speed
    )


LEAD = pose([2.0, 0.0, 1.2], [0, 0, 0])
F_IN_LEAD = pose([-1.2, 0.0, 0.0], [0, 0, 0])


def _lead_at(x):
    return pose([2.0 + x, 0.0, 1.2], [0, 0, 0])


def test_a_relay_drone_is_not_moved_by_a_forged_leader_view_with_a_huge_covariance():
    g = _relay()
    for t in range(0, 400, 66):
        _edge(g, (1, 0), "lead", "world", LEAD.inv(), 0.002, t * MS, t * 1000)
        if t >= 132:
            _edge(g, (1, 3), "lead", "world", _lead_at(20.0).inv(), 1e-4, t * MS, t * 1000, HUGE)
        _edge(g, (2, 50), "f", "lead", F_IN_LEAD.inv(), 0.003, t * MS, t * 1000)
        r = g.evaluate(t * MS)
        np.testing.assert_allclose(r.poses["f"].p_world_m, (LEAD * F_IN_LEAD).translation, atol=1e-6)
        assert r.poses["f"].own_view is False  # a relay drone's pose rests on the leader's: peers' work


def test_three_forged_leader_views_do_not_outvote_the_real_one():
    """Three forged views of the leader 1 m off, each precise and consistent, every frame; the real
    one with them. Without the bound the median of four is theirs; with it each is refused on its own,
    counted, and the follower stays where the real view puts it."""
    for max_speed, moved in ((0.0, True), (5.0, False)):
        g = _relay(max_speed)
        for t in range(0, 600, 66):
            _edge(g, (1, 0), "lead", "world", LEAD.inv(), 0.002, t * MS, t * 1000)
            if t >= 132:
                for m in (1, 2, 3):
                    _edge(g, (1, m), "lead", "world", _lead_at(1.0).inv(), 0.002, t * MS, t * 1000 + 1)
            _edge(g, (2, 50), "f", "lead", F_IN_LEAD.inv(), 0.003, t * MS, t * 1000)
            r = g.evaluate(t * MS)
        err = np.linalg.norm(r.poses["f"].p_world_m - (LEAD * F_IN_LEAD).translation)
        if moved:
            assert err > 0.5, err
        else:
            assert err < 1e-6, err
            assert g.too_fast_total == 3 * len(range(132, 600, 66))


def test_a_refused_candidate_does_not_restart_the_bounds_clock_and_a_loss_only_widens_it():
    """The real leader view arrives last at 66 ms; a forged one 3 m off comes every 33 ms from then on
    (the consensus gate off: the speed bound alone). It is refused while the leader could not have
    flown 3 m since its estimate, past the edge timeout too (a loss: real views late on a loaded computer
    must not hand the re-acquisition to forged ones); it is taken at the first frame the bound (its
    sigmas plus the top speed times the time since) covers. Were the clock restarted by each refusal,
    it would never be taken."""
    g = _relay(k=0.0)
    _edge(g, (1, 0), "lead", "world", LEAD.inv(), 0.002, 0, 0)
    g.evaluate(0)
    _edge(g, (1, 0), "lead", "world", LEAD.inv(), 0.002, 66 * MS, 66_000)
    g.evaluate(66 * MS)
    frames = list(range(99, 1000, 33))
    sigmas = SPEED_GATE_SIGMA * np.hypot(0.002, 0.002)
    due = next(t for t in frames if sigmas + 5.0 * (t - 66) / 1000 >= 3.0)
    assert due > 66 + 250 + 33  # well past the edge timeout
    for t in frames:
        _edge(g, (1, 1), "lead", "world", _lead_at(3.0).inv(), 0.002, t * MS, t * 1000)
        x = g.evaluate(t * MS).poses["lead"].p_world_m[0]
        assert abs(x - (5.0 if t >= due else 2.0)) < 1e-6, (t, due, x)


def test_forged_views_do_not_take_over_when_the_real_ones_are_late_past_the_edge_timeout():
    """Three forged leader views 2 m off every frame; the real view every frame too, except for 330 ms
    in which it is late (a loaded computer, a lossy link): past the edge timeout, nothing is accepted.
    The leader could not have flown 2 m in that time, so the forged views are still refused and the
    real one, when it comes back, is taken; the follower stays where the real views put it."""
    g = _relay()
    for t in range(0, 1200, 66):
        real = not 264 < t < 594
        if real:
            _edge(g, (1, 0), "lead", "world", LEAD.inv(), 0.002, t * MS, t * 1000)
        if t >= 132:
            for m in (1, 2, 3):
                _edge(g, (1, m), "lead", "world", _lead_at(2.0).inv(), 0.002, t * MS, t * 1000 + 1)
        _edge(g, (2, 50), "f", "lead", F_IN_LEAD.inv(), 0.003, t * MS, t * 1000)
        r = g.evaluate(t * MS)
        if "f" in r.poses:
            err = np.linalg.norm(r.poses["f"].p_world_m - (LEAD * F_IN_LEAD).translation)
            assert err < 1e-6, (t, err)
    assert "f" in r.poses and g.too_fast_total > 0


def test_the_bound_grows_with_the_time_since_the_estimate_for_a_real_move():
    """A leader really flying at 2.5 m/s, seen every 66 ms, then unseen for 150 ms (less than the edge
    timeout): every view is taken, the one after the gap too (0.375 m away); the same jump again
    50 ms later is refused (the consensus gate off: the speed bound alone)."""
    g = _relay(k=0.0)
    x = 0.0
    for t in range(0, 400, 66):
        x = 2.5 * t / 1000
        _edge(g, (1, 0), "lead", "world", _lead_at(x).inv(), 0.002, t * MS, t * 1000)
        r = g.evaluate(t * MS)
        assert abs(r.poses["lead"].p_world_m[0] - 2.0 - x) < 1e-6
    last = 396
    t = last + 150
    _edge(g, (1, 0), "lead", "world", _lead_at(x + 0.375).inv(), 0.002, t * MS, t * 1000)
    assert abs(g.evaluate(t * MS).poses["lead"].p_world_m[0] - 2.0 - x - 0.375) < 1e-6
    assert g.too_fast_total == 0
    t2 = t + 50
    _edge(g, (1, 0), "lead", "world", _lead_at(x + 0.75).inv(), 0.002, t2 * MS, t2 * 1000)
    assert abs(g.evaluate(t2 * MS).poses["lead"].p_world_m[0] - 2.0 - x - 0.375) < 1e-6
    assert g.too_fast_total == 1


def test_an_old_stamp_buys_no_distance():
    """A forged view stamped 0.9 s before the estimate: the time since the estimate is counted from
    the stamps only forwards, so its claim of an old capture does not widen the bound to 4.5 m (the
    consensus gate off: the speed bound alone)."""
    g = _relay(k=0.0)
    _edge(g, (1, 0), "lead", "world", LEAD.inv(), 0.002, 1000 * MS, 1_000_000)
    g.evaluate(1000 * MS)
    _edge(g, (1, 0), "lead", "world", LEAD.inv(), 0.002, 1033 * MS, 1_033_000)
    _edge(g, (1, 1), "lead", "world", _lead_at(2.0).inv(), 0.002, 1033 * MS, 100_000)
    r = g.evaluate(1033 * MS)
    assert abs(r.poses["lead"].p_world_m[0] - 2.0) < 1e-6 and g.too_fast_total == 1


@settings(max_examples=60, deadline=None)
@given(
    dt_ms=st.integers(1, 240),
    speed=st.floats(0.5, 10.0),
    frac=st.floats(0.0, 2.0),
)
def test_the_bound_is_the_speed_times_the_time_since_plus_the_estimates_sigmas(dt_ms, speed, frac):
    """A candidate ``frac`` of the bound away is kept iff frac <= 1 (up to rounding at the edge), with
    the candidate's own sigma counted up to its cap."""
    g = TransformGraph(["world", "lead"], TIMEOUT_NS, outlier_gate_sigma=5.0, max_speed_m_s=speed)
    s0, s1 = 0.002, 0.5  # the candidate's sigma is capped
    cov0 = np.diag([s0**2] * 3 + [1e-6] * 3)
    g.update_edge((1, 0), "world", "lead", np.zeros(3), [0, 0, 0, 1.0], s0, 0, 0, cov_a_b=cov0)
    g.evaluate(0)
    bound = 5.0 * np.hypot(s0, SPEED_CANDIDATE_SIGMA_CAP_M) + speed * dt_ms / 1000
    if abs(frac - 1.0) < 1e-6:
        return
    cov1 = np.diag([s1**2] * 3 + [1e-6] * 3)
    p = np.array([frac * bound, 0.0, 0.0])
    g.update_edge((1, 0), "world", "lead", p, [0, 0, 0, 1.0], s1, dt_ms * MS, dt_ms * 1000, cov_a_b=cov1)
    r = g.evaluate(dt_ms * MS)
    assert (g.too_fast_total == 0) == (frac < 1.0)
    assert np.allclose(r.poses["lead"].p_world_m, p if frac < 1.0 else 0.0)


def test_the_own_cameras_direct_views_are_not_held_to_the_bound():
    # (The consensus gate off: it has its own rule for a lone jump.)
    g = TransformGraph(["world", "d"], TIMEOUT_NS, outlier_gate_sigma=0.0, anchor_sensors={1}, max_speed_m_s=5.0)
    _edge(g, (1, 0), "d", "world", pose([1.0, 0, 1]).inv(), 0.002, 0, 0)
    g.evaluate(0)
    _edge(g, (1, 0), "d", "world", pose([3.0, 0, 1]).inv(), 0.002, 33 * MS, 33_000)
    r = g.evaluate(33 * MS)
    assert abs(r.poses["d"].p_world_m[0] - 3.0) < 1e-9 and r.poses["d"].own_view is True
    assert g.too_fast_total == 0

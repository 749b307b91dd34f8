"""A parent taken at its child's capture time: a follower seen only through its moving leader."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.graph import TransformGraph
from atlas_onboard.core.graph.timing import (
    ACCEL_SIGMA_M_S2,
    ANGULAR_ACCEL_SIGMA_RAD_S2,
    Waiting,
    WaitingViews,
    line_weights,
)
from tests.core.graph.builders import MS
from tests.helpers import pose

NAMES = ["world", "leader", "follower"]
T_LF = pose([-2.0, 0.15, -0.2], [2, -3, 8])  # the follower 2 m behind its leader, in the leader's frame
FRAME_US = 33_333  # the leader's camera at 30 Hz


def leader_at(t_s, p0, v, a, R0, w, alpha):
    """The leader's pose at t_s: position p0 + v t + a t^2 / 2, attitude R0 Exp(w t + alpha t^2 / 2)."""
    return RigidTransform.from_components(
        p0 + v * t_s + 0.5 * a * t_s**2, R0 * Rotation.from_rotvec(w * t_s + 0.5 * alpha * t_s**2)
    )


def put(g, key, a, b, T, cov, capture_us, now_ns):
    g.update_edge(key, a, b, T.translation, T.rotation.as_quat(), 0.01, now_ns, capture_us, cov_a_b=cov)


def noisy(T, cov, rng):
    """T perturbed as the covariance convention says: p + dp, R Exp(dtheta)."""
    e = rng.multivariate_normal(np.zeros(6), cov)
    return RigidTransform.from_components(T.translation + e[:3], T.rotation * Rotation.from_rotvec(e[3:]))


def pose_error(est, truth):
    """[dp, dtheta] of an estimate against the truth in the covariance convention."""
    p = np.asarray(est.p_world_m) - truth.translation
    dth = (truth.rotation.inv() * Rotation.from_quat(est.q_world_xyzw)).as_rotvec()
    return np.concatenate([p, dth])


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-0.3, 0.0), min_size=2, max_size=6, unique=True),
    st.floats(-0.3, 0.1),
)
def test_line_weights_reproduce_a_line_exactly(times, t):
    t_s = np.array(sorted(times))
    if np.ptp(t_s) < 1e-3:
        return
    w = line_weights(t_s, t)
    assert w.sum() == pytest.approx(1.0, abs=1e-9)
    assert w @ t_s == pytest.approx(t, abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-0.3, 0.0), st.floats(0.01, 100.0)), min_size=2, max_size=6, unique_by=lambda x: x[0]),
    st.floats(-0.3, 0.1),
)
def test_weighed_line_weights_reproduce_a_line_exactly(samples, t):
    t_s, omega = (np.array(x) for x in zip(*sorted(samples), strict=True))
    if np.ptp(t_s) < 1e-3:
        return
    w = line_weights(t_s, t, omega)
    assert w.sum() == pytest.approx(1.0, abs=1e-9)
    assert w @ t_s == pytest.approx(t, abs=1e-9)


@pytest.mark.parametrize("offset_us", [-12_000, -25_000, 40_000])
def test_follower_through_a_moving_leader_is_composed_at_its_own_capture_time(offset_us):
    """The leader flies at 0.8 m/s and turns at 35 deg/s, seen at 30 Hz; the follower's image is taken
    ``offset_us`` from the leader's newest (before it: interpolated; more than a frame after it:
    extrapolated). Composed
    with the leader's pose at the follower's instant the follower is exact; composed with the leader's
    newest pose (the leader where it was) it is off by centimetres."""
    p0, v, R0, w = (
        np.array([1.0, 0.5, 1.2]),
        np.array([0.7, 0.35, 0.05]),
        Rotation.from_euler("z", 20, degrees=True),
        np.array([0.02, -0.03, 0.6]),
    )
    zero = np.zeros(3)
    cov = np.diag([1e-6] * 3 + [1e-6] * 3)
    errors = {}
    for align in (True, False):
        g = TransformGraph(NAMES, 250 * MS, align=align)
        for k in range(4):
            t_us = k * FRAME_US
            put(g, (1, 1), "world", "leader", leader_at(t_us / 1e6, p0, v, zero, R0, w, zero), cov, t_us, t_us * 1000)
            g.evaluate(t_us * 1000)
        t_b = 3 * FRAME_US + offset_us
        truth = leader_at(t_b / 1e6, p0, v, zero, R0, w, zero) * T_LF
        now = (3 * FRAME_US + 40_000) * 1000
        put(g, (2, 9), "leader", "follower", T_LF, cov, t_b, now)
        f = g.evaluate(now).poses["follower"]
        assert f.capture_time_us == (t_b if align else max(t_b, 3 * FRAME_US))
        errors[align] = float(np.linalg.norm(f.p_world_m - truth.translation))
    assert errors[True] < 1e-6
    assert errors[False] > 0.01


def test_a_leader_pose_its_own_covariance_calls_poor_counts_less_in_the_follower():
    """The leader flies a straight line seen at 30 Hz, its poses exact with a 1 mm, 1 mrad covariance,
    but its newest one is off by 20 mm and 2 mrad, as its own covariance (20 mm, 2 mrad) allows. The
    follower's image lies between the leader's last two poses: the leader's line there rests on the
    well measured poses, the poor one counts by its variance, and the follower stays within 2 mm of
    the truth (an equally weighed line through the poses carries 45 % of the newest's error: 9 mm)."""
    p0, v, R0, w = (
        np.array([0.3, -0.4, 1.3]),
        np.array([0.5, 0.2, 0.0]),
        Rotation.from_euler("z", -30, degrees=True),
        np.array([0.0, 0.0, 0.3]),
    )
    zero = np.zeros(3)
    good = np.diag([1e-6] * 3 + [1e-6] * 3)
    poor = np.diag([4e-4] * 3 + [4e-6] * 3)
    miss = RigidTransform.from_components([0.02, 0.0, 0.0], Rotation.from_rotvec([0.0, 0.002, 0.0]))
    g = TransformGraph(NAMES, 250 * MS, align=True)
    for k in range(6):
        t_us = k * FRAME_US
        T = leader_at(t_us / 1e6, p0, v, zero, R0, w, zero)
        T, cov = (T * miss, poor) if k == 5 else (T, good)
        put(g, (1, 1), "world", "leader", T, cov, t_us, t_us * 1000)
        g.evaluate(t_us * 1000)
    t_b = 4 * FRAME_US + FRAME_US // 2
    truth = leader_at(t_b / 1e6, p0, v, zero, R0, w, zero) * T_LF
    now = (5 * FRAME_US + 30_000) * 1000
    put(g, (2, 9), "leader", "follower", T_LF, good, t_b, now)
    f = g.evaluate(now).poses["follower"]
    assert f.capture_time_us == t_b
    assert float(np.linalg.norm(f.p_world_m - truth.translation)) < 0.002


def test_composed_pose_nees_is_about_6_with_leader_poses_of_unlike_covariances():
    """Monte Carlo: as below, but every other leader pose has nine times the variance (a frame with
    fewer tags); each pose's error drawn from its own covariance. The follower's 6x6 still describes its
    error (NEES6 about 6), whatever weight each pose gets."""
    rng = np.random.default_rng(11)
    C_good = np.diag([1.5e-3, 1.2e-3, 2.0e-3, 2e-3, 2.5e-3, 4e-3]) ** 2
    C_edge = np.diag([1.5e-3, 1.5e-3, 5e-3, 6e-3, 6e-3, 3e-3]) ** 2
    p0, v, R0, w = np.array([0.0, 0.0, 1.2]), np.array([0.6, -0.2, 0.0]), Rotation.identity(), np.array([0.0, 0.0, 0.4])
    nees = []
    for _ in range(600):
        a = rng.normal(0.0, ACCEL_SIGMA_M_S2, 3)
        alpha = rng.normal(0.0, ANGULAR_ACCEL_SIGMA_RAD_S2, 3)
        g = TransformGraph(NAMES, 250 * MS, align=True)
        for k in range(5):
            t_us = k * FRAME_US
            C = C_good * (9.0 if k % 2 else 1.0)
            T = noisy(leader_at(t_us / 1e6, p0, v, a, R0, w, alpha), C, rng)
            put(g, (1, 1), "world", "leader", T, C, t_us, t_us * 1000)
            g.evaluate(t_us * 1000)
        t_b = 3 * FRAME_US + 12_000
        truth = leader_at(t_b / 1e6, p0, v, a, R0, w, alpha) * T_LF
        now = (4 * FRAME_US + 30_000) * 1000
        put(g, (2, 9), "leader", "follower", noisy(T_LF, C_edge, rng), C_edge, t_b, now)
        f = g.evaluate(now).poses["follower"]
        e = pose_error(f, truth)
        nees.append(float(e @ np.linalg.solve(f.covariance, e)))
    assert 5.4 <= np.mean(nees) <= 6.6


def test_a_follower_image_just_after_the_leaders_newest_waits_for_the_leaders_next_one():
    """The follower's image is 15 ms past the leader's newest, whose next is due 18 ms later: rather
    than extrapolate, the follower waits (no pose yet at the start, its last pose kept later, not
    re-stamped), and is exact once the leader's next pose brackets its time."""
    p0, v, R0, w = (
        np.array([1.0, 0.5, 1.2]),
        np.array([0.7, 0.35, 0.05]),
        Rotation.identity(),
        np.array([0.0, 0.0, 0.6]),
    )
    zero = np.zeros(3)
    cov = np.diag([1e-6] * 6)
    g = TransformGraph(NAMES, 250 * MS, align=True)
    for k in range(4):
        t_us = k * FRAME_US
        put(g, (1, 1), "world", "leader", leader_at(t_us / 1e6, p0, v, zero, R0, w, zero), cov, t_us, t_us * 1000)
        g.evaluate(t_us * 1000)
    t_b = 3 * FRAME_US + 15_000
    put(g, (2, 9), "leader", "follower", T_LF, cov, t_b, (t_b + 10_000) * 1000)
    assert "follower" not in g.evaluate((t_b + 10_000) * 1000).poses
    t_us = 4 * FRAME_US
    put(
        g, (1, 1), "world", "leader", leader_at(t_us / 1e6, p0, v, zero, R0, w, zero), cov, t_us, (t_us + 10_000) * 1000
    )
    f = g.evaluate((t_us + 10_000) * 1000).poses["follower"]
    truth = leader_at(t_b / 1e6, p0, v, zero, R0, w, zero) * T_LF
    assert f.capture_time_us == t_b
    assert np.linalg.norm(f.p_world_m - truth.translation) < 1e-6


def test_a_parent_whose_motion_is_unknown_is_taken_where_it_was_aged_by_the_time_between():
    """The leader has one pose (its motion unknown): the follower's image 40 ms later is placed through
    it with the leader's position variance grown by (age_sigma_m_per_s * 40 ms)^2 per axis, as an
    edge of that age would be; with no ageing (the paper), exactly the leader's newest pose."""
    cov = np.diag([1e-6] * 6)
    leader = pose([1.0, 0.5, 1.2], [0, 0, 30])
    out = {}
    for age in (0.0, 1.0):
        g = TransformGraph(NAMES, 250 * MS, align=True, age_sigma_m_per_s=age)
        put(g, (1, 1), "world", "leader", leader, cov, 0, 0)
        g.evaluate(0)
        put(g, (2, 9), "leader", "follower", T_LF, cov, 40_000, 41_000_000)
        out[age] = g.evaluate(41_000_000).poses["follower"]
    truth = leader * T_LF
    for f in out.values():
        assert f.capture_time_us == 40_000
        assert np.linalg.norm(f.p_world_m - truth.translation) < 1e-9
    grown = np.diag(out[1.0].covariance)[:3] - np.diag(out[0.0].covariance)[:3]
    np.testing.assert_allclose(grown, (1.0 * 0.040) ** 2, rtol=1e-6)


@pytest.mark.parametrize("after_us", [20_000, 3 * FRAME_US + 40_000])
def test_composed_pose_nees_is_about_6_with_the_leaders_full_covariance_lever_arm_and_time_step(after_us):
    """Monte Carlo: the leader's observations carry a full 6x6 covariance (its attitude error swings
    the follower 2 m away), the follower's single view its own, the leader accelerates and turns as the
    model's spread says, and the follower's image is 20 ms past the leader's newest. The follower's
    published 6x6 describes its error: NEES6 about 6. The follower's image is ``after_us`` past the
    leader's third pose: between two of its poses, or (the leader's next ones missed) past them all."""
    rng = np.random.default_rng(7)
    L = np.array(
        [[1.5e-3, 0, 0, 0, 0, 0], [0.3e-3, 1.2e-3, 0, 0, 0, 0], [0.1e-3, 0.2e-3, 2.0e-3, 0, 0, 0],
         [0, 0, 0, 2e-3, 0, 0], [0, 0, 0, 0.5e-3, 2.5e-3, 0], [0.2e-3, 0, 0, 0.3e-3, 0.4e-3, 4e-3]]
    )  # fmt: skip
    C_leader = L @ L.T
    C_edge = np.diag([1.5e-3, 1.5e-3, 5e-3, 6e-3, 6e-3, 3e-3]) ** 2
    C_edge[2, 3] = C_edge[3, 2] = 0.5 * 5e-3 * 6e-3  # depth and tilt coupled
    p0, v, R0, w = np.array([0.0, 0.0, 1.2]), np.array([0.6, -0.2, 0.0]), Rotation.identity(), np.array([0.0, 0.0, 0.4])
    nees = []
    for _ in range(600):
        a = rng.normal(0.0, ACCEL_SIGMA_M_S2, 3)
        alpha = rng.normal(0.0, ANGULAR_ACCEL_SIGMA_RAD_S2, 3)
        g = TransformGraph(NAMES, 250 * MS, align=True)
        t_b = 2 * FRAME_US + after_us
        for k in range(4 if after_us < FRAME_US else 3):
            t_us = k * FRAME_US
            T = noisy(leader_at(t_us / 1e6, p0, v, a, R0, w, alpha), C_leader, rng)
            put(g, (1, 1), "world", "leader", T, C_leader, t_us, t_us * 1000)
            g.evaluate(t_us * 1000)
        truth = leader_at(t_b / 1e6, p0, v, a, R0, w, alpha) * T_LF
        now = (max(t_b, 3 * FRAME_US) + 30_000) * 1000
        put(g, (2, 9), "leader", "follower", noisy(T_LF, C_edge, rng), C_edge, t_b, now)
        f = g.evaluate(now).poses["follower"]
        e = pose_error(f, truth)
        nees.append(float(e @ np.linalg.solve(f.covariance, e)))
    assert 5.4 <= np.mean(nees) <= 6.6


def test_a_leader_with_no_fresh_view_places_its_follower_only_while_the_covariance_allows():
    """The leader's camera stops seeing; the follower keeps seeing the leader at 30 Hz. New poses of
    the follower (new capture times: what goes to its autopilot) are given, from the leader's last
    poses extrapolated, only while their position sigma stays under the limit; then the last one is
    kept, not re-sent, for at most 0.3 s, then the pose is lost, while the leader's last edge is still
    live. With no limit new poses go on, ever less certain."""
    p0, v, R0, w = np.array([0.0, 0.0, 1.2]), np.array([0.6, 0.0, 0.0]), Rotation.identity(), np.array([0.0, 0.0, 0.3])
    zero = np.zeros(3)
    cov = np.diag([1e-6] * 3 + [1e-6] * 3)
    limit = 0.02
    for max_sigma in (limit, 0.0):
        g = TransformGraph(NAMES, 1000 * MS, align=True, max_relayed_sigma_m=max_sigma)
        for k in range(6):
            t_us = k * FRAME_US
            put(g, (1, 1), "world", "leader", leader_at(t_us / 1e6, p0, v, zero, R0, w, zero), cov, t_us, t_us * 1000)
            g.evaluate(t_us * 1000)
        stamps, sigmas, lost_at = [], [], None
        for k in range(6, 30):  # 0.8 s without a view of the leader's own
            t_us = k * FRAME_US
            put(g, (2, 9), "leader", "follower", T_LF, cov, t_us, t_us * 1000)
            f = g.evaluate(t_us * 1000).poses.get("follower")
            if f is None:
                lost_at = t_us if lost_at is None else lost_at
                continue
            assert lost_at is None  # never back
            if not stamps or f.capture_time_us > stamps[-1]:
                stamps.append(f.capture_time_us)
                sigmas.append(float(np.sqrt(np.linalg.eigvalsh(f.covariance[:3, :3])[-1])))
        assert g.evaluate(29 * FRAME_US * 1000).poses.get("leader") is not None  # its edge still live
        if max_sigma:
            assert len(stamps) >= 1 and max(sigmas) <= limit
            assert lost_at is not None and lost_at - stamps[-1] <= 300_000 + FRAME_US
        else:
            assert lost_at is None and len(stamps) == 24 and max(sigmas) > limit


# A leader accelerating and turning: p0, v, a, R0, w, alpha of leader_at.
ACCELERATING_LEADER = (
    np.array([1.0, 0.5, 1.2]),
    np.array([0.6, 0.3, 0.0]),
    np.array([0.9, -0.6, 0.2]),
    Rotation.from_euler("z", 15, degrees=True),
    np.array([0.05, -0.02, 0.5]),
    np.array([0.8, -0.5, 2.5]),
)


@pytest.mark.parametrize("late_ms", [20, 30, 45])
def test_a_follower_whose_leader_poses_arrive_late_gets_its_images_placed_in_capture_order(late_ms):
    """The leader and the follower's camera both at 15 Hz, 11 ms apart; the leader accelerates and turns,
    its poses (errors drawn from their covariance) reach the follower's graph ``late_ms`` after its
    images, the follower's own views 5 ms after theirs, as over a network. Each follower image is then
    too far past the leader's newest pose to extrapolate within the relayed limit, and its next image
    replaces the edge before the leader's bracketing pose comes: still every image is placed once that
    pose arrives (interpolated), its covariance describing its error (NEES6 about 6), and the poses come
    out in capture order (never an older image after a newer one)."""
    rng = np.random.default_rng(3)
    p0, v, a, R0, w, alpha = ACCELERATING_LEADER
    c_leader = np.diag([1.5e-3] * 3 + [3e-3] * 3) ** 2
    c_edge = np.diag([1e-3] * 3 + [2e-3] * 3) ** 2
    g = TransformGraph(NAMES, 250 * MS, align=True, max_relayed_sigma_m=0.02)
    period = 2 * FRAME_US
    events = [(k * period + late_ms * 1000, "leader", k * period) for k in range(24)]  # (arrival, whose, capture)
    images = [k * period + 11_000 for k in range(3, 21)]
    events += [(t + 5_000, "follower", t) for t in images]
    published: list[int] = []
    nees, pos_nees = [], []
    for arrival, whose, t_us in sorted(events):
        if whose == "leader":
            T = noisy(leader_at(t_us / 1e6, p0, v, a, R0, w, alpha), c_leader, rng)
            put(g, (1, 1), "world", "leader", T, c_leader, t_us, arrival * 1000)
        else:
            put(g, (2, 9), "leader", "follower", noisy(T_LF, c_edge, rng), c_edge, t_us, arrival * 1000)
        f = g.evaluate(arrival * 1000).poses.get("follower")
        if f is None or (published and f.capture_time_us == published[-1]):
            continue
        published.append(f.capture_time_us)
        e = pose_error(f, leader_at(f.capture_time_us / 1e6, p0, v, a, R0, w, alpha) * T_LF)
        nees.append(float(e @ np.linalg.solve(f.covariance, e)))
        pos_nees.append(float(e[:3] @ np.linalg.solve(f.covariance[:3, :3], e[:3])))
    assert published == sorted(set(published))  # capture order, each image once
    assert set(published) <= set(images)
    assert len(published) >= len(images) - 1
    assert 3.0 <= np.mean(nees) <= 9.0
    assert max(pos_nees) <= 16.0  # 4 sigma in 3 dof


def _waiting(row, capture_us, parent=1, child=2):
    return Waiting(row, (2, row), parent, child, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), 0.01,
                   np.eye(6) * 1e-6, capture_us)  # fmt: skip


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.integers(0, 400_000), min_size=1, max_size=10),
    st.integers(0, 400_000),
    st.integers(0, 500_000),
)
def test_waiting_views_give_the_oldest_bracketed_view_newer_than_the_childs_last(captures, after_us, parent_us):
    """Views queued in capture order; ready() gives the views of the oldest image that the parent's
    newest pose brackets and that is newer than the child's last pose (within the queue's count and age
    bounds), and forgets it and every older view: the next call gives the next newer one, never an
    older one."""
    views = WaitingViews(max_views=4, window_us=100_000)
    captures = sorted(captures)
    for row, t in enumerate(captures):
        views.add(0, _waiting(row, t))
    held = captures[-4:]
    expected = sorted({t for t in held if after_us < t <= parent_us and held[-1] - t <= 100_000})
    given_out = []
    while got := views.ready(0, 2, after_us, {1: parent_us}):
        assert len({w.capture_us for w in got}) == 1
        given_out.append(got[0].capture_us)
    assert given_out == expected


@pytest.mark.parametrize("late_ms", [80, 150])
def test_a_leader_whose_poses_come_later_than_a_frame_is_waited_for_by_its_measured_lateness(late_ms):
    """The leader and the follower's camera both at 15 Hz, at the same instants (as two drones of one
    swarm); the leader's poses reach the follower's graph ``late_ms`` after its own images (a slower node
    or link: more than a leader frame). Once the first views have shown how late the leader comes, each
    follower image waits for the leader pose at or after its time, so every pose published from then
    on is an interpolation, never the leader's newest extrapolated over ``late_ms`` and a frame; in
    capture order, each image once."""
    p0, v, a, R0, w, alpha = ACCELERATING_LEADER
    cov = np.diag([1e-3] * 3 + [2e-3] * 3) ** 2
    g = TransformGraph(NAMES, 250 * MS, align=True)
    period = 2 * FRAME_US
    events = [(k * period + late_ms * 1000, "leader", k * period) for k in range(40)]  # (arrival, whose, capture)
    images = [k * period for k in range(2, 36)]
    events += [(t + 5_000, "follower", t) for t in images]
    published, leader_newest = [], -1
    for arrival, whose, t_us in sorted(events):
        if whose == "leader":
            put(g, (1, 1), "world", "leader", leader_at(t_us / 1e6, p0, v, a, R0, w, alpha), cov, t_us, arrival * 1000)
            leader_newest = t_us
        else:
            put(g, (2, 9), "leader", "follower", T_LF, cov, t_us, arrival * 1000)
        f = g.evaluate(arrival * 1000).poses.get("follower")
        if f is None or (published and f.capture_time_us == published[-1][0]):
            continue
        err = np.linalg.norm(
            f.p_world_m - (leader_at(f.capture_time_us / 1e6, p0, v, a, R0, w, alpha) * T_LF).translation
        )
        published.append((f.capture_time_us, leader_newest, err))
    captures = [c for c, _, _ in published]
    assert captures == sorted(set(captures)) and set(captures) <= set(images)
    learned = [(c, newest, err) for c, newest, err in published if c >= 1_000_000]
    assert len(learned) >= len([t for t in images if t >= 1_000_000]) - 1
    assert all(c <= newest for c, newest, _ in learned), learned  # the leader's pose at or after each image
    # A line between leader poses a frame apart misses this path by a * dt^2 / 8 and the lever arm's turn
    # by alpha * dt^2 / 8: millimetres, where the extrapolation was centimetres.
    assert max(err for _, _, err in learned) < 0.005

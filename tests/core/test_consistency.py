"""The consistency of markers with each other (pairs and joint solves that leave one out) and of a
camera with itself over time (it cannot jump)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.core.consistency import A_MAX_M_S2, MarkerConsistency, MotionCheck, Sighting

FRAME_30_US = 33_333


def test_a_pair_that_disagrees_names_no_culprit_until_one_of_them_agrees_with_others():
    graph = MarkerConsistency()
    for k in range(3):  # markers 2 and 7 seen together, not fitting: either may have moved
        graph.add(k * FRAME_30_US, "world", 2, 7, False)
    assert graph.relation("world", 2, 7, 3 * FRAME_30_US) is False
    assert graph.suspects("world", 3 * FRAME_30_US) == set()
    # 7 agrees with 8 (seen together, or one after the other): 2 alone disagrees with a group of two.
    graph.add_group(4 * FRAME_30_US, "world", [7, 8], [])
    assert graph.suspects("world", 4 * FRAME_30_US) == set()  # one verdict is no relation
    graph.add_group(5 * FRAME_30_US, "world", [7, 8], [])
    assert graph.suspects("world", 5 * FRAME_30_US) == {2}
    assert graph.support("world", 7, 5 * FRAME_30_US) == 2 and graph.support("world", 2, 5 * FRAME_30_US) == 1


def test_a_joint_solve_that_leaves_one_out_makes_it_the_suspect():
    graph = MarkerConsistency()
    for k in range(2):
        graph.add_group(k * FRAME_30_US, "world", [1, 3, 4], [5])
    assert graph.suspects("world", FRAME_30_US) == {5}
    assert graph.support("world", 1, FRAME_30_US) == 3


def test_a_suspect_put_back_is_cleared_once_it_agrees_again_and_old_evidence_is_forgotten():
    graph = MarkerConsistency(window_s=10.0)
    graph.add_group(0, "world", [7, 8], [])
    graph.add_group(FRAME_30_US, "world", [7, 8], [])
    for k in range(2, 6):
        graph.add(k * FRAME_30_US, "world", 2, 7, False)
    assert graph.suspects("world", 6 * FRAME_30_US) == {2}
    # Put back: it fits with 7 again. The newest verdicts decide: two of five are no longer enough.
    for k in range(6, 8):
        graph.add(k * FRAME_30_US, "world", 2, 7, True)
    assert graph.suspects("world", 8 * FRAME_30_US) == {2}  # 3 disagree, 2 agree of the newest five
    graph.add(8 * FRAME_30_US, "world", 2, 7, True)
    assert graph.suspects("world", 9 * FRAME_30_US) == set()
    assert graph.support("world", 2, 9 * FRAME_30_US) == 3
    # Disagreements older than the window are forgotten.
    fresh = MarkerConsistency(window_s=10.0)
    fresh.add_group(0, "world", [7, 8], [])
    fresh.add_group(FRAME_30_US, "world", [7, 8], [])
    fresh.add(0, "world", 2, 7, False)
    fresh.add(FRAME_30_US, "world", 2, 7, False)
    assert fresh.suspects("world", 2 * FRAME_30_US) == {2}
    assert fresh.suspects("world", 11_000_000) == set()


def _path(t_s: np.ndarray, accel_m_s2: np.ndarray, v0_m_s: np.ndarray) -> np.ndarray:
    """Positions (N, 3) under a constant acceleration from the origin."""
    return v0_m_s[None, :] * t_s[:, None] + 0.5 * accel_m_s2[None, :] * t_s[:, None] ** 2


def _sighting(t_us: int, p_m: np.ndarray, sigma_m: float = 0.002) -> Sighting:
    return Sighting(t_us, np.asarray(p_m, dtype=float), np.eye(3) * sigma_m**2)


def test_a_marker_that_puts_the_camera_10_cm_off_one_frame_later_disagrees_with_the_one_before():
    check = MotionCheck()
    t_us = np.arange(4) * FRAME_30_US
    p = _path(t_us / 1e6, np.array([2.0, -1.0, 0.0]), np.array([0.8, 0.3, 0.0]))
    assert check.compare("world", {7: _sighting(t_us[0], p[0])}) == []
    assert check.compare("world", {7: _sighting(t_us[1], p[1])}) == []
    # Marker 2, whose world-file place is 10 cm off along x, puts the camera 10 cm off along x.
    offset = np.array([0.10, 0.0, 0.0])
    (v,) = check.compare("world", {2: _sighting(t_us[2], p[2] + offset)})
    assert (v.marker_id, v.other, v.agree) == (2, 7, False)
    np.testing.assert_allclose(v.offset_m, -offset, atol=0.005)
    # Where it truly is, it agrees.
    check2 = MotionCheck()
    check2.compare("world", {7: _sighting(t_us[0], p[0])})
    check2.compare("world", {7: _sighting(t_us[1], p[1])})
    (v,) = check2.compare("world", {2: _sighting(t_us[2], p[2])})
    assert v.agree


def test_after_a_gap_the_camera_may_be_anywhere_so_nothing_is_compared():
    check = MotionCheck()
    check.compare("world", {7: _sighting(0, [0.0, 0.0, 1.0])})
    check.compare("world", {7: _sighting(FRAME_30_US, [0.01, 0.0, 1.0])})
    # Re-acquired 0.3 s later by another marker, 20 cm further: no verdict (it may really have moved).
    assert check.compare("world", {2: _sighting(FRAME_30_US + 300_000, [0.21, 0.0, 1.0])}) == []
    # Poses too uncertain to tell a move of a few centimetres prove nothing either.
    vague = MotionCheck()
    vague.compare("world", {7: _sighting(0, [0.0, 0.0, 1.0], 0.03)})
    vague.compare("world", {7: _sighting(FRAME_30_US, [0.0, 0.0, 1.0], 0.03)})
    assert vague.compare("world", {2: _sighting(2 * FRAME_30_US, [0.2, 0.0, 1.0], 0.03)}) == []


@settings(max_examples=80, deadline=None)
@given(
    accel=st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    v0=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
    frames=st.lists(st.integers(1, 3), min_size=3, max_size=3),  # frame periods between sightings
    seed=st.integers(0, 2**31 - 1),
)
def test_a_camera_moving_as_a_multirotor_can_never_disagree_with_itself(accel, v0, frames, seed):
    """Any motion within the acceleration bound, seen with noise of its stated sigma (within 3 sigma), by
    one marker and then another, never gives a disagreement: the check costs no marker that fits."""
    a = np.asarray(accel)
    a = a / max(np.linalg.norm(a), 1.0) * A_MAX_M_S2  # at most the bound
    rng = np.random.default_rng(seed)
    t_us = np.cumsum([0, *frames]) * FRAME_30_US
    p = _path(t_us / 1e6, a, np.asarray(v0))
    sigma = 0.002
    noisy = p + np.clip(rng.normal(0, sigma / np.sqrt(3), p.shape), -sigma, sigma)
    check = MotionCheck()
    verdicts = []
    for k in range(3):
        verdicts += check.compare("world", {7: _sighting(int(t_us[k]), noisy[k], sigma)})
    verdicts += check.compare("world", {2: _sighting(int(t_us[3]), noisy[3], sigma)})
    assert all(v.agree for v in verdicts)
    if frames[-1] == 1 and frames[-2] <= 2:  # a frame after a velocity from frames close together: compared
        assert [v.marker_id for v in verdicts] == [2]

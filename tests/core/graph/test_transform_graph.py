"""Targeted (partial) evaluation: the target's pose as a full evaluation gives it, and the rest kept."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform

from atlas_onboard.core.graph import TransformGraph
from tests.core.graph.builders import MS, add, noisy_random_graph
from tests.helpers import pose


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 10), st.integers(1, 30), st.integers(0, 2**16), st.sampled_from(["bfs", "dijkstra"]),
       st.booleans())  # fmt: skip
def test_a_targeted_evaluation_gives_the_full_evaluations_pose(n, n_edges, seed, path, gate):
    """evaluate(target=X) computes X's pose exactly as a full evaluation does (position, attitude,
    sigma, covariance, level, count, stamp), and the poses of X's lower stages; nothing else."""
    options = {"path": path, "outlier_gate_sigma": 3.0 if gate else 0.0}
    g, _ = noisy_random_graph(n, n_edges, seed, **options)
    full = g.evaluate(120 * MS)
    for target in full.order[1:]:
        g_t, _ = noisy_random_graph(n, n_edges, seed, **options)  # the gate keeps state: same history
        got = g_t.evaluate(120 * MS, target=target)
        assert not got.complete and got.levels == full.levels and got.order == full.order
        assert target in got.poses and set(got.poses) <= set(full.poses)
        for name, e in got.poses.items():
            ref = full.poses[name]
            np.testing.assert_allclose(e.p_world_m, ref.p_world_m, atol=1e-12)
            np.testing.assert_allclose(e.q_world_xyzw, ref.q_world_xyzw, atol=1e-12)
            np.testing.assert_allclose(e.covariance, ref.covariance, atol=1e-15)
            assert (e.sigma_m, e.level, e.n_observations, e.capture_time_us) == pytest.approx(
                (ref.sigma_m, ref.level, ref.n_observations, ref.capture_time_us), abs=1e-15
            )
    if full.unreached:  # a target with no path to world: a full evaluation
        assert g.evaluate(120 * MS, target=full.unreached[0]).complete


def _same_pose(e, ref):
    np.testing.assert_allclose(e.p_world_m, ref.p_world_m, atol=1e-12)
    np.testing.assert_allclose(e.q_world_xyzw, ref.q_world_xyzw, atol=1e-12)
    np.testing.assert_allclose(e.covariance, ref.covariance, atol=1e-15)
    assert (e.sigma_m, e.level, e.n_observations, e.capture_time_us) == pytest.approx(
        (ref.sigma_m, ref.level, ref.n_observations, ref.capture_time_us), abs=1e-15
    )


@settings(max_examples=25, deadline=None)
@given(st.integers(3, 8), st.integers(0, 2**16), st.booleans(), st.booleans())
def test_partial_evaluation_with_the_previous_result_equals_a_full_evaluation(n, seed, ageing, relative):
    """A node's history on random graphs: twin graphs get the same edges (the target's own edges to
    world refreshed often, others now and then, some expiring); one is evaluated in full every time,
    the other for the target with its previous result (in full one time in four). The target's pose
    is always the full evaluation's; when the result says ``current``, so is every other pose."""
    rng = np.random.default_rng(seed)
    names = ["world"] + [f"e{i}" for i in range(1, n)]
    truth = {"world": RigidTransform.identity()}
    truth.update({v: pose(rng.uniform(-5, 5, 3), rng.uniform(-60, 60, 3)) for v in names[1:]})
    options = {"age_sigma_m_per_s": 0.5 if ageing else 0.0, "relative": relative}
    full_g, part_g = (TransformGraph(names, 250 * MS, **options) for _ in range(2))
    target, now_ms, previous = "e1", 0, None
    for _ in range(20):
        now_ms += int(rng.integers(1, 80))
        for _ in range(int(rng.integers(0, 4))):
            if rng.random() < 0.6:  # the target's own camera sees the world's markers, or the world sees it
                a, b = ("e1", "world") if rng.random() < 0.5 else ("world", "e1")
                key = (int(rng.integers(0, 2)), int(rng.integers(0, 2)))
            else:
                a, b = (names[i] for i in rng.choice(n, size=2, replace=False))
                key = (int(rng.integers(2, 8)), int(rng.integers(0, 8)))
            T = truth[a].inv() * truth[b] * pose(rng.normal(0, 0.02, 3), rng.normal(0, 2, 3))
            sigma = float(rng.uniform(0.005, 0.05))
            for g in (full_g, part_g):
                add(g, key, a, b, T, sigma=sigma, now_ns=now_ms * MS, capture_us=now_ms * 1000)
        full = full_g.evaluate(now_ms * MS)
        if previous is None or rng.random() < 0.25:
            got = part_g.evaluate(now_ms * MS)
        else:
            got = part_g.evaluate(now_ms * MS, target=target, previous=previous)
        assert got.order == full.order and got.levels == full.levels and got.unreached == full.unreached
        if target in full.poses:
            _same_pose(got.poses[target], full.poses[target])
        if got.complete or got.current:
            assert list(got.poses) == list(full.poses)
            for name, e in got.poses.items():
                _same_pose(e, full.poses[name])
            assert got.relative.keys() == full.relative.keys()
            for root, group in full.relative.items():
                for name, e in group.items():
                    _same_pose(got.relative[root][name], e)
        if ageing:  # the others' sigmas grow with time: never current without a full evaluation
            assert got.complete or not got.current
        previous = got


def _small_swarm(**options):
    """world sees A, B and E; B sees C; A sees D (D rests on A's pose); nothing rests on E.
    Returns the graph and ``see(key, a, b, now_ms, noise_m)``, which adds or refreshes an edge."""
    truth = {"world": RigidTransform.identity(), "A": pose([1, 0, 1], [0, 0, 30]), "B": pose([0, 2, 1]),
             "C": pose([2, 3, 1.5], [5, -5, 90]), "D": pose([3, 0, 1]),
             "E": pose([-1, -1, 2])}  # fmt: skip
    g = TransformGraph(list(truth), 250 * MS, **options)

    def see(key, a, b, now_ms, noise_m=0.0):
        add(g, key, a, b, truth[a].inv() * truth[b] * pose([noise_m, 0, 0]), now_ns=now_ms * MS)

    for key, a, b in (((1, 1), "world", "A"), ((1, 2), "world", "B"), ((2, 3), "B", "C"), ((3, 4), "A", "D"),
                      ((1, 5), "world", "E")):  # fmt: skip
        see(key, a, b, 0)
    return g, see


def test_a_targeted_evaluation_keeps_the_others_poses_and_says_whether_they_are_current():
    g, see = _small_swarm()
    first = g.evaluate(10 * MS)
    see((1, 5), "world", "E", 20, noise_m=0.01)  # only E's edge to world changed, and nothing rests on E
    got = g.evaluate(20 * MS, target="E", previous=first)
    assert not got.complete and got.current
    assert list(got.poses) == list(first.poses)
    for name in ("A", "B", "C", "D"):
        assert got.poses[name] is first.poses[name]
    np.testing.assert_allclose(got.poses["E"].p_world_m, [-0.99, -1, 2], atol=1e-12)
    full = g.evaluate(20 * MS)
    for name, e in full.poses.items():
        _same_pose(got.poses[name], e)


def test_the_others_are_not_current_when_they_rest_on_the_target_or_their_edges_changed():
    g, see = _small_swarm()
    first = g.evaluate(10 * MS)
    see((1, 1), "world", "A", 20, noise_m=0.01)  # A moved; D, seen by A, rests on A's pose
    got = g.evaluate(20 * MS, target="A", previous=first)
    assert not got.current and got.poses["D"] is first.poses["D"]
    assert np.linalg.norm(g.evaluate(20 * MS).poses["D"].p_world_m - got.poses["D"].p_world_m) > 0.009
    g, see = _small_swarm()
    first = g.evaluate(10 * MS)
    see((1, 5), "world", "E", 20)
    see((3, 4), "A", "D", 20, noise_m=0.01)  # another entity's edge changed
    assert not g.evaluate(20 * MS, target="E", previous=first).current
    g, see = _small_swarm()
    for key, a, b in (((1, 1), "world", "A"), ((1, 2), "world", "B"), ((3, 4), "A", "D"), ((1, 5), "world", "E")):
        see(key, a, b, 200)
    first = g.evaluate(200 * MS)  # B-C, from 0 ms, is now the oldest edge: it expires at 250 ms + 1 ns
    see((1, 5), "world", "E", 220)
    assert g.evaluate(250 * MS, target="E", previous=first).current
    assert not g.evaluate(251 * MS, target="E", previous=first).current  # C lost its only edge
    g, see = _small_swarm(age_sigma_m_per_s=0.5)  # with ageing every sigma grows with time
    first = g.evaluate(10 * MS)
    see((1, 5), "world", "E", 20)
    assert not g.evaluate(20 * MS, target="E", previous=first).current


def test_a_targeted_evaluation_without_a_previous_result_holds_only_what_it_computed():
    g, _ = _small_swarm()
    got = g.evaluate(10 * MS, target="E")
    assert not got.complete and not got.current
    assert set(got.poses) == {"world", "E"}  # the lower stages and the target, not its own stage's others


def test_an_edge_key_that_comes_to_join_other_entities_makes_the_old_ones_not_current():
    """Found by the property above (n=3, seed 10547): a key that joined world and C, refreshed joining world
    and A (the target), took C's edge away; C's pose from the previous full evaluation is no longer what a
    full evaluation gives, so a targeted evaluation must not call it current."""
    truth = {"world": RigidTransform.identity(), "A": pose([1, 0, 1]), "C": pose([0, 2, 1], [0, 0, 40])}
    g = TransformGraph(list(truth), 250 * MS)
    add(g, (2, 1), "world", "C", truth["C"] * pose([0.05, 0, 0]), now_ns=0)
    add(g, (3, 1), "world", "C", truth["C"], now_ns=0)
    add(g, (1, 1), "world", "A", truth["A"], now_ns=0)
    previous = g.evaluate(0)
    add(g, (2, 1), "world", "A", truth["A"], now_ns=10 * MS)  # the key (2, 1) now joins world and A
    full_now = TransformGraph(list(truth), 250 * MS)
    for key, b, T in (((3, 1), "C", truth["C"]), ((1, 1), "A", truth["A"]), ((2, 1), "A", truth["A"])):
        add(full_now, key, "world", b, T, now_ns=0)
    got = g.evaluate(10 * MS, target="A", previous=previous)
    full = full_now.evaluate(10 * MS)
    assert not np.allclose(previous.poses["C"].p_world_m, full.poses["C"].p_world_m)  # C's pose did change
    assert not got.current

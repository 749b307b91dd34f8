"""The transform graph: the paper's Figure 4, expiry, the pose phase against ground truth."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.graph import TransformGraph
from tests.helpers import assert_pose_close, pose

MS = 1_000_000  # nanoseconds per millisecond


def add(graph, key, a, b, T_a_b, sigma=0.01, now_ns=0, capture_us=0):
    graph.update_edge(key, a, b, T_a_b.translation, T_a_b.rotation.as_quat(), sigma, now_ns, capture_us)


def figure4_graph():
    """The paper's Figure 4 as described in its text and caption.

    world sees A and B directly (level 1); A and B see each other (the A-B cycle); C is seen by B
    (level 2); D and E see only each other, so they are never reached from world.
    """
    truth = {
        "world": RigidTransform.identity(),
        "A": pose([1, 0, 1], [0, 0, 30]),
        "B": pose([0, 2, 1], [0, 0, -60]),
        "C": pose([2, 3, 1.5], [5, -5, 90]),
        "D": pose([5, 5, 0]),
        "E": pose([6, 5, 0]),
    }
    g = TransformGraph(["world", "A", "B", "C", "D", "E"], edge_timeout_ns=250 * MS)

    def rel(a, b):
        return truth[a].inv() * truth[b]

    add(g, (1, 1), "world", "A", rel("world", "A"))
    add(g, (1, 2), "world", "B", rel("world", "B"))
    add(g, (2, 3), "A", "B", rel("A", "B") * pose([0.5, 0, 0]))  # a wrong A-B edge: must be ignored
    add(g, (3, 4), "B", "A", rel("B", "A") * pose([0, 0.5, 0]))  # and the reverse one
    add(g, (4, 5), "B", "C", rel("B", "C"))
    add(g, (5, 6), "D", "E", rel("D", "E"))
    return g, truth


def test_figure4_levels_and_order():
    g, _ = figure4_graph()
    result = g.evaluate(now_ns=0)
    assert result.levels == {"world": 0, "A": 1, "B": 1, "C": 2}
    assert result.order == ("world", "A", "B", "C")
    assert [result.poses[n].order for n in result.order] == [0, 1, 2, 3]
    assert set(result.unreached) == {"D", "E"}
    assert "D" not in result.poses and "E" not in result.poses


def test_figure4_cycle_between_same_level_vertices_is_ignored():
    g, truth = figure4_graph()
    result = g.evaluate(now_ns=0)
    # The A-B edges carry a 0.5 m error; A and B come only from world, so they are exact.
    for name in ("A", "B", "C"):
        pose_ = result.poses[name]
        assert_pose_close(pose_.p_world_m, pose_.q_world_xyzw, truth[name], 1e-12, 1e-12)
    assert result.poses["A"].n_observations == 1
    assert result.poses["C"].n_observations == 1


def test_parents_must_be_exactly_one_level_lower():
    # world sees A and C (both level 1); A also sees C, but A is at C's own level, so that edge is
    # not a candidate (it would be a cyclic dependency).
    truth = {"world": RigidTransform.identity(), "A": pose([1, 0, 0]), "C": pose([0, 1, 0])}
    g = TransformGraph(["world", "A", "C"], 250 * MS)
    add(g, (1, 1), "world", "A", truth["A"])
    add(g, (1, 2), "world", "C", truth["C"])
    add(g, (2, 3), "A", "C", truth["A"].inv() * truth["C"] * pose([1, 1, 1]))  # wrong, same level
    result = g.evaluate(0)
    assert result.levels["C"] == 1
    assert result.poses["C"].n_observations == 1
    np.testing.assert_allclose(result.poses["C"].p_world_m, [0, 1, 0], atol=1e-12)


def test_edge_expiry_at_exactly_the_timeout():
    g = TransformGraph(["world", "A"], edge_timeout_ns=250 * MS)
    add(g, (1, 1), "world", "A", pose([1, 2, 3]), now_ns=1_000 * MS)
    assert "A" in g.evaluate(now_ns=1_250 * MS).poses  # age == timeout: still live
    assert "A" not in g.evaluate(now_ns=1_250 * MS + 1).poses  # one nanosecond older: removed
    assert g.edges == {}


def test_refreshed_edge_restarts_its_age():
    g = TransformGraph(["world", "A"], edge_timeout_ns=250 * MS)
    add(g, (1, 1), "world", "A", pose([1, 2, 3]), now_ns=0)
    add(g, (1, 1), "world", "A", pose([1, 2, 4]), now_ns=200 * MS)
    result = g.evaluate(now_ns=400 * MS)
    np.testing.assert_allclose(result.poses["A"].p_world_m, [1, 2, 4])
    assert len(g.edges) == 1  # same (sensor, marker) key: replaced, not added


def test_pose_phase_fuses_candidates_with_paper_weights():
    g = TransformGraph(["world", "A"], 250 * MS)
    add(g, (1, 1), "world", "A", pose([0, 0, 0]), sigma=0.01)
    add(g, (1, 2), "world", "A", pose([0.3, 0, 0]), sigma=0.02)  # weight 0.5
    add(g, (2, 1), "A", "world", pose([0, -0.6, 0]), sigma=0.04)  # A sees world: T_world_A = (0, 0.6, 0), weight 0.25
    result = g.evaluate(0)
    a = result.poses["A"]
    np.testing.assert_allclose(a.p_world_m, [0.15 / 1.75, 0.15 / 1.75, 0], atol=1e-12)
    assert a.n_observations == 3
    expected_sigma = np.sqrt((1 * 0.01) ** 2 + (0.5 * 0.02) ** 2 + (0.25 * 0.04) ** 2) / 1.75
    assert a.sigma_m == pytest.approx(expected_sigma)


def test_inverse_variance_option_changes_weights():
    g = TransformGraph(["world", "A"], 250 * MS, inverse_variance=True)
    add(g, (1, 1), "world", "A", pose([0, 0, 0]), sigma=0.01)
    add(g, (1, 2), "world", "A", pose([0.5, 0, 0]), sigma=0.02)  # weight 0.25
    np.testing.assert_allclose(g.evaluate(0).poses["A"].p_world_m, [0.1, 0, 0], atol=1e-12)


def test_inverse_variance_weighs_by_the_candidates_covariances():
    """Beyond the paper: with inverse_variance, a candidate's weight is its propagated position
    variance, not its sigma: two views with the same sigma, one placed 3 times more precisely (a
    ceiling camera's view of a tag), weigh 9 : 1; the paper's sigma_min weighting gives 1 : 1."""
    from atlas_onboard.core import covariance

    got = {}
    for inverse in (False, True):
        g = TransformGraph(["world", "A"], 250 * MS, inverse_variance=inverse)
        for key, x, s_p in (((1, 1), 0.0, 0.001), ((1, 2), 1.0, 0.003)):
            T = pose([x, 0, 0])
            C = covariance.diagonal(s_p, 0.01)
            g.update_edge(key, "world", "A", T.translation, T.rotation.as_quat(), 0.01, 0, 0, cov_a_b=C)
        got[inverse] = g.evaluate(0).poses["A"].p_world_m
    np.testing.assert_allclose(got[False], [0.5, 0, 0], atol=1e-12)
    np.testing.assert_allclose(got[True], [0.1, 0, 0], atol=1e-12)


def test_relay_through_another_drone():
    # The paper's Figure 1: B sees no world marker; A sees the world and B.
    truth = {"world": RigidTransform.identity(), "A": pose([1, 1, 2], [0, 10, 45]), "B": pose([3, 0, 1.5], [0, 0, 180])}
    g = TransformGraph(["world", "A", "B"], 250 * MS)
    add(g, (1, 1), "A", "world", truth["A"].inv(), sigma=0.01, capture_us=100)
    add(g, (1, 7), "A", "B", truth["A"].inv() * truth["B"], sigma=0.03, capture_us=250)
    result = g.evaluate(0)
    b = result.poses["B"]
    assert b.level == 2
    assert_pose_close(b.p_world_m, b.q_world_xyzw, truth["B"], 1e-12, 1e-12)
    assert b.sigma_m == pytest.approx(np.hypot(0.01, 0.03))  # the chain's uncertainty adds up
    assert b.capture_time_us == 250
    assert result.poses["A"].capture_time_us == 100


def test_world_has_identity_pose_and_level_zero():
    g = TransformGraph(["A"], 250 * MS)
    result = g.evaluate(0)
    w = result.poses["world"]
    assert w.level == 0 and w.order == 0
    np.testing.assert_array_equal(w.p_world_m, [0, 0, 0])
    assert result.unreached == ("A",)


poses_st = st.tuples(
    st.lists(st.floats(-10, 10), min_size=3, max_size=3),
    st.lists(st.floats(-179, 179), min_size=3, max_size=3).map(lambda a: [a[0], a[1] / 2.1, a[2]]),
)


@settings(max_examples=60, deadline=None)
@given(st.lists(poses_st, min_size=4, max_size=4), st.integers(0, 2**16))
def test_same_pose_whatever_path(truth_list, seed):
    """Exact edges: every entity's pose equals the truth whichever edges the graph happens to use."""
    names = ["world", "A", "B", "C", "D"]
    truth = {"world": RigidTransform.identity()}
    truth.update({n: pose(p, r) for n, (p, r) in zip(names[1:], truth_list, strict=True)})
    rng = np.random.default_rng(seed)
    g = TransformGraph(names, 250 * MS)
    pairs = [("world", "A"), ("A", "B"), ("B", "C"), ("C", "D")]  # a chain so everything is reached
    extra = [(a, b) for a in names for b in names if a < b and (a, b) not in pairs]
    pairs += [extra[i] for i in rng.choice(len(extra), size=3, replace=False)]
    for k, (a, b) in enumerate(pairs):
        if rng.random() < 0.5:
            a, b = b, a
        add(g, (k, k), a, b, truth[a].inv() * truth[b], sigma=float(rng.uniform(0.005, 0.05)))
    result = g.evaluate(0)
    for n in names:
        e = result.poses[n]
        assert_pose_close(e.p_world_m, e.q_world_xyzw, truth[n], 1e-8, 1e-8)


def test_evaluation_does_not_mutate_live_edges():
    g, _ = figure4_graph()
    before = {k: (e.p_a_b.copy(), e.q_a_b.copy()) for k, e in g.edges.items()}
    g.evaluate(0)
    g.evaluate(0)
    for k, (p, q) in before.items():
        np.testing.assert_array_equal(g.edges[k].p_a_b, p)
        np.testing.assert_array_equal(g.edges[k].q_a_b, q)


def test_fused_rotation_mean_of_two_candidates():
    g = TransformGraph(["world", "A"], 250 * MS)
    add(g, (1, 1), "world", "A", pose([0, 0, 0], [0, 0, 10]), sigma=0.01)
    add(g, (1, 2), "world", "A", pose([0, 0, 0], [0, 0, 30]), sigma=0.01)
    yaw = Rotation.from_quat(g.evaluate(0).poses["A"].q_world_xyzw).as_euler("ZYX", degrees=True)[0]
    assert yaw == pytest.approx(20.0, abs=1e-9)


def short_noisy_long_precise(path):
    """world sees D directly through a noisy edge (sigma 0.2 m, 0.3 m off) and through A precisely."""
    truth = {"world": RigidTransform.identity(), "A": pose([2, 0, 1], [0, 0, 40]), "D": pose([3, 1, 1], [0, 0, -20])}
    g = TransformGraph(["world", "A", "D"], 250 * MS, path=path)
    add(g, (1, 1), "world", "D", truth["D"] * pose([0.3, 0, 0]), sigma=0.2)
    add(g, (1, 2), "world", "A", truth["A"], sigma=0.005)
    add(g, (2, 3), "A", "D", truth["A"].inv() * truth["D"], sigma=0.005)
    return g, truth


def test_dijkstra_prefers_the_long_precise_chain():
    g_bfs, truth = short_noisy_long_precise("bfs")
    g_dij, _ = short_noisy_long_precise("dijkstra")
    bfs = g_bfs.evaluate(0).poses["D"]
    dij = g_dij.evaluate(0).poses["D"]
    err_bfs = np.linalg.norm(bfs.p_world_m - truth["D"].translation)
    err_dij = np.linalg.norm(dij.p_world_m - truth["D"].translation)
    assert err_bfs == pytest.approx(0.3, abs=1e-9)  # the paper's method: level 1, the noisy edge only
    assert bfs.n_observations == 1
    # Dijkstra fuses both; the chain's sigma is sqrt(2) * 0.005, so the noisy edge weighs 0.0354.
    w_noisy = np.hypot(0.005, 0.005) / 0.2
    assert err_dij == pytest.approx(0.3 * w_noisy / (1 + w_noisy), rel=1e-6)
    assert dij.n_observations == 2
    assert dij.sigma_m < bfs.sigma_m


def test_dijkstra_equals_bfs_on_exact_edges():
    g, truth = figure4_graph()
    g.path = "dijkstra"
    result = g.evaluate(0)
    for name in ("A", "B", "C"):
        e = result.poses[name]
        assert_pose_close(e.p_world_m, e.q_world_xyzw, truth[name], 1e-12, 1e-12)
    assert set(result.unreached) == {"D", "E"}


def test_relative_poses_of_a_group_without_world():
    g, truth = figure4_graph()
    g.relative = True
    result = g.evaluate(0)
    assert "E" not in result.poses  # no world pose
    rel = result.relative["D"]["E"]
    assert rel.frame == "D" and rel.level == 1
    assert_pose_close(rel.p_world_m, rel.q_world_xyzw, truth["D"].inv() * truth["E"], 1e-12, 1e-12)
    assert result.poses["A"].frame == "world"
    # A target with no path to world gets the full evaluation, relative poses included.
    targeted = g.evaluate(0, target="E")
    assert targeted.complete and set(targeted.poses) == set(result.poses)
    rel_t = targeted.relative["D"]["E"]
    assert_pose_close(rel_t.p_world_m, rel_t.q_world_xyzw, truth["D"].inv() * truth["E"], 1e-12, 1e-12)


def test_relative_off_by_default():
    g, _ = figure4_graph()
    assert g.evaluate(0).relative == {}


def _queue_bfs(names, pairs):
    """The paper's broad phase written the plain way (a queue, neighbours in world-file order)."""
    from collections import deque

    idx = {n: i for i, n in enumerate(names)}
    nbrs = {i: set() for i in range(len(names))}
    for a, b in pairs:
        nbrs[idx[a]].add(idx[b])
        nbrs[idx[b]].add(idx[a])
    level, order, queue = {0: 0}, [0], deque([0])
    while queue:
        v = queue.popleft()
        for c in sorted(nbrs[v]):
            if c not in level:
                level[c] = level[v] + 1
                order.append(c)
                queue.append(c)
    return [names[v] for v in order], {names[v]: lv for v, lv in level.items()}


@settings(max_examples=80, deadline=None)
@given(st.integers(2, 12), st.integers(0, 40), st.integers(0, 2**16))
def test_broad_phase_order_is_a_queues(n, n_edges, seed):
    """The array BFS visits vertices exactly as a queue-based BFS does, on random graphs."""
    rng = np.random.default_rng(seed)
    names = ["world"] + [f"e{i}" for i in range(1, n)]
    g = TransformGraph(names, 250 * MS)
    pairs = []
    for k in range(n_edges):
        a, b = rng.choice(n, size=2, replace=False)
        pairs.append((names[a], names[b]))
        add(g, (k, k), names[a], names[b], pose([1, 0, 0]))
    order, levels = _queue_bfs(names, pairs)
    result = g.evaluate(0)
    assert list(result.order) == order
    assert result.levels == levels


def test_edge_rows_are_reused_and_grow_without_changing_results():
    """More edges than the initial row capacity, some expired and replaced, then cleared: the poses
    equal those of a graph built fresh from the same live edges."""
    names = ["world"] + [f"e{i}" for i in range(1, 40)]
    rng = np.random.default_rng(3)
    truth = {"world": RigidTransform.identity()}
    truth.update({n: pose(rng.uniform(-5, 5, 3), rng.uniform(-60, 60, 3)) for n in names[1:]})

    def edges(first_key, count):
        out = []
        for k in range(first_key, first_key + count):
            a = names[k % 39]
            b = names[k % 39 + 1]
            T = truth[a].inv() * truth[b] * pose(rng.normal(0, 0.01, 3))
            out.append(((k, k), a, b, T, float(rng.uniform(0.01, 0.05))))
        return out

    g = TransformGraph(names, 250 * MS)
    old, new = edges(0, 150), edges(150, 100)
    for key, a, b, T, s in old:
        add(g, key, a, b, T, sigma=s, now_ns=0)
    g.evaluate(0)
    for key, a, b, T, s in new:
        add(g, key, a, b, T, sigma=s, now_ns=200 * MS)
    got = g.evaluate(300 * MS)  # the first 150 have expired; their rows are free again
    assert got.n_edges == 100 and len(g.edges) == 100
    fresh = TransformGraph(names, 250 * MS)
    for key, a, b, T, s in new:
        add(fresh, key, a, b, T, sigma=s, now_ns=200 * MS)
    ref = fresh.evaluate(300 * MS)
    assert got.order == ref.order
    for n in ref.order:
        np.testing.assert_allclose(got.poses[n].p_world_m, ref.poses[n].p_world_m, atol=1e-12)
        np.testing.assert_allclose(got.poses[n].covariance, ref.poses[n].covariance, atol=1e-15)
    for key, a, b, T, s in old[:20]:  # rows reused by new keys
        add(g, key, a, b, T, sigma=s, now_ns=300 * MS)
    assert g.evaluate(300 * MS).n_edges == 120
    g.clear()
    assert g.edges == {} and g.next_expiry_ns() is None
    assert g.evaluate(300 * MS).order == ("world",)


def _noisy_random_graph(n, n_edges, seed, **options):
    """A random graph of noisy edges with distinct sigmas (several candidates per entity, cycles)."""
    rng = np.random.default_rng(seed)
    names = ["world"] + [f"e{i}" for i in range(1, n)]
    truth = {"world": RigidTransform.identity()}
    truth.update({v: pose(rng.uniform(-5, 5, 3), rng.uniform(-60, 60, 3)) for v in names[1:]})
    g = TransformGraph(names, 250 * MS, **options)
    for k in range(n_edges):
        a, b = (names[i] for i in rng.choice(n, size=2, replace=False))
        T = truth[a].inv() * truth[b] * pose(rng.normal(0, 0.02, 3), rng.normal(0, 2, 3))
        add(g, (k, k), a, b, T, sigma=float(rng.uniform(0.005, 0.05)), now_ns=int(rng.integers(0, 100)) * MS,
            capture_us=int(rng.integers(0, 10**6)))  # fmt: skip
    return g, names


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 10), st.integers(1, 30), st.integers(0, 2**16), st.sampled_from(["bfs", "dijkstra"]),
       st.booleans())  # fmt: skip
def test_a_targeted_evaluation_gives_the_full_evaluations_pose(n, n_edges, seed, path, gate):
    """evaluate(target=X) computes X's pose exactly as a full evaluation does (position, attitude,
    sigma, covariance, level, count, stamp), and the poses of X's lower stages; nothing else."""
    options = {"path": path, "outlier_gate_sigma": 3.0 if gate else 0.0}
    g, _ = _noisy_random_graph(n, n_edges, seed, **options)
    full = g.evaluate(120 * MS)
    for target in full.order[1:]:
        g_t, _ = _noisy_random_graph(n, n_edges, seed, **options)  # the gate keeps state: same history
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


def test_a_kept_plan_never_outlives_the_shape_of_the_graph():
    """The evaluation plan is kept while only edge values change; an edge that appears, expires or
    is cleared gives a new plan: each evaluation equals a fresh graph's on the same live edges."""
    names = ["world", "A", "B", "C"]
    truth = {"world": RigidTransform.identity(), "A": pose([1, 0, 0]), "B": pose([0, 2, 0], [0, 0, 90]),
             "C": pose([0, 0, 3], [10, 0, 0])}  # fmt: skip
    g = TransformGraph(names, 250 * MS)

    def step(now_ms, edges):
        for key, a, b, noise in edges:
            add(g, key, a, b, truth[a].inv() * truth[b] * pose(noise), now_ns=now_ms * MS)
        got = g.evaluate(now_ms * MS)
        fresh = TransformGraph(names, 250 * MS)
        for e in g.live_edges(now_ms * MS):
            fresh.update_edge(e.key, names[e.a], names[e.b], e.p_a_b, e.q_a_b, e.sigma_m, e.stamp_ns)
        ref = fresh.evaluate(now_ms * MS)
        assert got.order == ref.order and got.levels == ref.levels
        for n in ref.poses:
            np.testing.assert_allclose(got.poses[n].p_world_m, ref.poses[n].p_world_m, atol=1e-12)
        return got

    r = step(0, [((1, 0), "world", "A", [0.01, 0, 0]), ((2, 0), "A", "B", [0, 0, 0])])
    assert r.levels == {"world": 0, "A": 1, "B": 2}
    r = step(10, [((1, 0), "world", "A", [0.02, 0, 0])])  # values only: the kept plan
    np.testing.assert_allclose(r.poses["A"].p_world_m, [1.02, 0, 0], atol=1e-12)
    r = step(20, [((3, 0), "world", "B", [0, 0, 0]), ((4, 0), "B", "C", [0, 0, 0])])  # B one level up
    assert r.levels == {"world": 0, "A": 1, "B": 1, "C": 2}
    r = step(270, [((3, 0), "world", "B", [0, 0, 0]), ((4, 0), "B", "C", [0, 0, 0])])  # A's edges expire
    assert r.levels == {"world": 0, "B": 1, "C": 2}
    g.clear()
    r = step(280, [((1, 0), "world", "A", [0, 0, 0])])
    assert r.levels == {"world": 0, "A": 1} and r.unreached == ("B", "C")

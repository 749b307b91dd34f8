"""The broad phase (BFS levels, the paper's Figure 4), Dijkstra on the edges' variances, kept plans."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform

from atlas_onboard.core.graph import TransformGraph
from tests.core.graph.builders import MS, add, figure4_graph
from tests.helpers import assert_pose_close, pose


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


def test_a_key_that_comes_to_join_other_entities_gives_a_new_plan():
    """An edge key re-used between other entities changes the graph's shape as an edge that comes
    and goes does: the kept plan is not used for it."""
    g = TransformGraph(["world", "A", "B"], 250 * MS)
    add(g, (1, 1), "world", "A", pose([1, 0, 0]))
    assert g.evaluate(0).order == ("world", "A")
    add(g, (1, 1), "world", "B", pose([0, 2, 0]))
    got = g.evaluate(0)
    assert got.order == ("world", "B") and got.unreached == ("A",)
    np.testing.assert_allclose(got.poses["B"].p_world_m, [0, 2, 0], atol=1e-12)

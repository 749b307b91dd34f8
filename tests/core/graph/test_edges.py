"""The edges: expiry at exactly the timeout, refresh, rows reused, edges never mutated."""

import numpy as np
from scipy.spatial.transform import RigidTransform

from atlas_onboard.core.graph import TransformGraph
from tests.core.graph.builders import MS, add, figure4_graph
from tests.helpers import pose


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


def test_evaluation_does_not_mutate_live_edges():
    g, _ = figure4_graph()
    before = {k: (e.p_a_b.copy(), e.q_a_b.copy()) for k, e in g.edges.items()}
    g.evaluate(0)
    g.evaluate(0)
    for k, (p, q) in before.items():
        np.testing.assert_array_equal(g.edges[k].p_a_b, p)
        np.testing.assert_array_equal(g.edges[k].q_a_b, q)


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


def test_an_observation_older_than_its_edge_is_superseded():
    """is_superseded: the edge already holds an observation that arrived later, or one of a later
    image (a datagram overtaken on the way); an equal or newer one, or an unknown edge, is not."""
    g = TransformGraph(["world", "A"], 250 * MS)
    add(g, (1, 1), "world", "A", pose([1, 2, 3]), now_ns=100 * MS, capture_us=5_000)
    assert g.is_superseded((1, 1), 99 * MS, 5_000)  # arrived before the edge's
    assert g.is_superseded((1, 1), 100 * MS, 4_999)  # from an earlier image
    assert not g.is_superseded((1, 1), 100 * MS, 5_000)
    assert not g.is_superseded((1, 1), 101 * MS, 5_001)
    assert not g.is_superseded((1, 2), 0, 0)  # no such edge yet


def test_a_cameras_newer_view_of_an_entity_replaces_its_older_view_through_another_marker():
    """The joint solve reports an entity through one of its markers, which changes from image to image:
    camera 1's view of the drone through marker 5 at 0 ms is replaced by its view through marker 6 at
    33 ms (else, without ageing, the stale view is fused as new for 250 ms and drags the pose). Views of
    one image (the same capture time) are all kept, another camera's too, and an older image arriving
    late replaces nothing."""
    g = TransformGraph(["world", "d"], edge_timeout_ns=250 * MS)
    g.update_edge((1, 5), "d", "world", np.zeros(3), np.array([0, 0, 0, 1.0]), 0.01, 0, 0)
    g.update_edge((1, 7), "d", "world", np.zeros(3), np.array([0, 0, 0, 1.0]), 0.01, 0, 0)  # same image
    g.update_edge((2, 5), "d", "world", np.zeros(3), np.array([0, 0, 0, 1.0]), 0.01, 0, 0)  # another camera
    assert set(g.edges) == {(1, 5), (1, 7), (2, 5)}
    g.update_edge((1, 6), "d", "world", np.array([0.1, 0, 0]), np.array([0, 0, 0, 1.0]), 0.01, 33 * MS, 33_000)
    assert set(g.edges) == {(1, 6), (2, 5)}
    g.update_edge((1, 5), "d", "world", np.zeros(3), np.array([0, 0, 0, 1.0]), 0.01, 40 * MS, 20_000)  # late
    assert set(g.edges) == {(1, 5), (1, 6), (2, 5)}
    np.testing.assert_allclose(g.evaluate(40 * MS).poses["d"].n_observations, 3)


def test_an_images_views_of_an_entity_refreshed_by_the_next_image_keep_their_rows():
    """A camera that reports an entity through several markers per image: the next image's views of the
    same markers refresh the edges in their rows (the graph keeps its shape, and its evaluation plan),
    a marker the next image does not see still goes, and the poses are those of the newer image."""
    g = TransformGraph(["world", "d"], edge_timeout_ns=250 * MS)
    q = np.array([0, 0, 0, 1.0])
    for m in (5, 7, 9):
        g.update_edge((1, m), "d", "world", np.zeros(3), q, 0.01, 0, 0)
    rows = {k: e.slot for k, e in g.edges.items()}
    for m in (5, 7):  # the next image sees 5 and 7, not 9
        g.update_edge((1, m), "d", "world", np.array([0.2, 0, 0]), q, 0.01, 33 * MS, 33_000)
    assert set(g.edges) == {(1, 5), (1, 7)}
    assert {k: e.slot for k, e in g.edges.items()} == {(1, 5): rows[(1, 5)], (1, 7): rows[(1, 7)]}
    np.testing.assert_allclose(g.evaluate(40 * MS).poses["world"].p_world_m, 0.0)
    d = g.evaluate(40 * MS).poses["d"]
    assert d.n_observations == 2
    np.testing.assert_allclose(d.p_world_m, [-0.2, 0, 0], atol=1e-12)

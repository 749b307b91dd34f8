"""Graphs the graph tests share: the paper's Figure 4, random noisy graphs."""

import numpy as np
from scipy.spatial.transform import RigidTransform

from atlas_onboard.core.graph import TransformGraph
from tests.helpers import pose

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


def noisy_random_graph(n, n_edges, seed, **options):
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

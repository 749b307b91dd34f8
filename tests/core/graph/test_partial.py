"""Targeted (partial) evaluation: the target's pose as a full evaluation gives it, and the rest kept."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.core.graph.builders import MS, noisy_random_graph


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

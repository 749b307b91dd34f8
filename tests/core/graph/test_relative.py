"""Relative poses of the groups of entities that have no path to world."""

from tests.core.graph.builders import figure4_graph
from tests.helpers import assert_pose_close


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

"""Beyond the paper: relative poses of the groups of entities that have no path to world.

Each such group is evaluated from its first entity (in world-file order), and its poses are given
in that entity's frame: two drones that see each other but no world marker still know where each
is relative to the other.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from atlas_onboard.core.graph.pose import FrameEvaluation
from atlas_onboard.core.graph.result import EntityPose


def relative_groups(
    names: Sequence[str], unreached: Sequence[int], evaluate_from: Callable[[int], FrameEvaluation]
) -> tuple[dict[str, dict[str, EntityPose]], int]:
    """The poses of each group of the ``unreached`` vertices (indices into ``names``, in world-file
    order) in the frame of its first entity, by that entity's name (groups of one left out), and
    how many candidates the gate left out. ``evaluate_from(root)`` runs the pose phase from a root."""
    relative: dict[str, dict[str, EntityPose]] = {}
    gated = 0
    remaining = list(unreached)
    while remaining:
        root = remaining[0]
        frame = evaluate_from(root)
        gated += frame.gated
        if len(frame.order) > 1:
            relative[names[root]] = frame.poses
        group = set(frame.order)
        remaining = [v for v in remaining if v not in group]
    return relative, gated

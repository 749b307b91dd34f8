"""The transform graph (the paper's section 3.2), one module per part:

- :mod:`.edges`: the edge record and the edge storage (arrays, expiry);
- :mod:`.paths`: the broad phase (BFS levels, or Dijkstra on the edges' variances) and the plan;
- :mod:`.pose`: the pose phase (eq. 2 and 4-7), stage by stage;
- :mod:`.gate`: the consensus gate and its memory (:class:`PriorEstimate`);
- :mod:`.relative`: relative poses of the groups without a path to world;
- :mod:`.result`: what an evaluation gives (:class:`EntityPose`, :class:`Candidate`, :class:`GraphResult`);
- :mod:`.transform_graph`: :class:`TransformGraph`, which ties them together.
"""

from atlas_onboard.core.graph.edges import WORLD, Edge, EdgeKey
from atlas_onboard.core.graph.gate import MAX_RATE_RAD_S, MAX_SPEED_M_S, PriorEstimate
from atlas_onboard.core.graph.result import Candidate, EntityPose, GraphResult
from atlas_onboard.core.graph.transform_graph import TransformGraph

__all__ = [
    "MAX_RATE_RAD_S",
    "MAX_SPEED_M_S",
    "WORLD",
    "Candidate",
    "Edge",
    "EdgeKey",
    "EntityPose",
    "GraphResult",
    "PriorEstimate",
    "TransformGraph",
]

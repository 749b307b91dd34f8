"""What an evaluation gives: each entity's fused pose (:class:`EntityPose`), the candidates a
filter may fuse itself (:class:`Candidate`), and the whole (:class:`GraphResult`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.graph.edges import WORLD, EdgeKey


@dataclass(frozen=True, slots=True)
class Candidate:
    """One edge's vote for an entity's pose (eq. 2: the parent's pose times the edge), for a filter.

    ``covariance`` is 6x6 in the convention of :mod:`atlas_onboard.core.covariance` (position in the
    frame of the result, small rotation about the entity's body axes), including the parent's.
    ``parent`` is None when the parent is the frame's root (world, exact); otherwise the candidate
    is the parent's fused pose times the edge ``p_pc``, ``q_pc`` (parent to entity) whose own
    covariance is ``edge_covariance``, so that a filter can compose it with its own estimate of the
    parent instead (unless ``aligned``: the graph took the parent at the candidate's own time).
    """

    entity: str
    key: EdgeKey
    stamp_ns: int
    capture_time_us: int
    p_m: NDArray[np.float64]
    q_xyzw: NDArray[np.float64]
    covariance: NDArray[np.float64]
    parent: str | None = None
    p_pc: NDArray[np.float64] | None = None
    q_pc: NDArray[np.float64] | None = None
    edge_covariance: NDArray[np.float64] | None = None
    # The parent taken at this candidate's capture time, the step's uncertainty in ``covariance``
    # (:mod:`atlas_onboard.core.graph.timing`): the candidate stands as it is.
    aligned: bool = False


@dataclass(frozen=True, slots=True)
class EntityPose:
    """The fused world pose of one entity (Table 2, Vertex, plus what the publisher needs).

    Attributes:
        name: entity name.
        p_world_m: position in the world frame (ENU), metres, shape (3,).
        q_world_xyzw: orientation of the entity's body frame (FLU) in the world, x-first, shape (4,).
        level: hops from ``world`` (world itself is 0).
        order: position in the evaluation order (world is 0).
        n_observations: number of candidates fused for this entity (edges from parents one level lower).
        sigma_m: standard deviation of the fused position, metres, propagated along the chain.
        capture_time_us: capture time of the newest observation that contributed (through the chain).
        frame: the entity whose frame the pose is in: ``world``, or for a relative pose the first
            entity of a group that has no path to world.
        covariance: 6x6 covariance of (position in ``frame``, small rotation about the body axes),
            propagated along the chains of transforms (None: not computed).
        velocity_m_s: velocity in ``frame`` (None unless a filter estimates it).
        angular_rate_rad_s: body angular rate about the body axes (None unless a filter estimates it).
        velocity_covariance: 6x6 covariance of (velocity, angular rate) (None unless a filter
            estimates them).
        own_view: whether a fused candidate is a direct view of the frame's root by the node's own
            cameras (False: the pose rests on peers' work alone; None: the graph was not told which
            sensors are the node's own).
    """

    name: str
    p_world_m: NDArray[np.float64]
    q_world_xyzw: NDArray[np.float64]
    level: int
    order: int
    n_observations: int
    sigma_m: float
    capture_time_us: int
    frame: str = WORLD
    covariance: NDArray[np.float64] | None = None
    velocity_m_s: NDArray[np.float64] | None = None
    angular_rate_rad_s: NDArray[np.float64] | None = None
    velocity_covariance: NDArray[np.float64] | None = None
    own_view: bool | None = None

    @property
    def T_world_entity(self) -> RigidTransform:
        return RigidTransform.from_components(self.p_world_m, Rotation.from_quat(self.q_world_xyzw))


@dataclass(frozen=True, slots=True)
class GraphResult:
    """The output of one evaluation: poses of the entities reachable from world, and the rest."""

    poses: dict[str, EntityPose]
    order: tuple[str, ...]  # evaluation order (BFS order from world)
    levels: dict[str, int]  # broad-phase level of each reached entity
    unreached: tuple[str, ...]  # entities with no edge path to world: no pose this time
    n_edges: int  # live edges used in this evaluation
    relative: dict[str, dict[str, EntityPose]] = field(default_factory=dict)  # root -> poses in root's frame
    candidates: dict[str, list[Candidate]] = field(default_factory=dict)  # only with keep_candidates
    gated: int = 0  # candidates rejected by the outlier gate in this evaluation
    # False: a targeted evaluation, which computed only the target and the entities below it; the
    # others' poses, if any, are those of the previous result (see TransformGraph.evaluate).
    complete: bool = True
    # Every pose in ``poses`` is the one a full evaluation would give now (always, when complete).
    current: bool = True

    def pose(self, name: str) -> EntityPose | None:
        return self.poses.get(name)

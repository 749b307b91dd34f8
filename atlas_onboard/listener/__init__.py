"""The sensor listener (the paper's section 3.1): MarkerData -> validated, EMA-filtered graph edges.

- :mod:`.listener`: :class:`Listener`, eq. 1 and the edge filter (eq. 3), counting what it refuses;
- :mod:`.ambiguity`: :class:`AmbiguityResolver`, a planar ambiguity decided by the current estimates and
  the autopilot's gravity reference (the rule itself is :mod:`atlas_onboard.core.ambiguity`).

The covariance of each edge through eq. 1 is pure math: :mod:`atlas_onboard.core.edge_covariance`.
"""

from atlas_onboard.listener.listener import ESTIMATE_ATTITUDE_SIGMA_RAD, EdgeUpdate, Listener

__all__ = ["ESTIMATE_ATTITUDE_SIGMA_RAD", "EdgeUpdate", "Listener"]

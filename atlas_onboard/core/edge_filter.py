"""Each edge's filter (the paper's eq. 3, and beyond it a per-edge Kalman blend): how a new eq. 1 edge
combines with the edge's filtered value. Pure: times are passed in (the node's monotonic ns)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import fusion


@dataclass(frozen=True, slots=True)
class EdgeState:
    """One edge's filtered value: position ``p`` (3,) m and quaternion ``q`` (4,) xyzw of ``T_a_b``, its
    position sigma ``sigma_m``, and when it was last updated, ``stamp_ns``."""

    p: NDArray[np.float64]
    q: NDArray[np.float64]
    stamp_ns: int
    sigma_m: float


@dataclass(frozen=True, slots=True)
class EdgeFilter:
    """The filter's settings: ``alpha`` of eq. 3, ``age_sigma_m_per_s`` of the random walk (0: none), and
    ``timeout_ns``, the age at which an edge's value expires and the filter starts afresh."""

    alpha: float
    age_sigma_m_per_s: float
    timeout_ns: int

    @property
    def keeps_state(self) -> bool:
        """Whether an edge's value is read by its next update (else each update is the measurement)."""
        return self.alpha != 1.0 or self.age_sigma_m_per_s > 0.0

    def expired(self, state: EdgeState, now_ns: int) -> bool:
        return now_ns - state.stamp_ns > self.timeout_ns

    def update(
        self,
        state: EdgeState | None,
        p: NDArray[np.float64],
        q_xyzw: NDArray[np.float64],
        sigma_m: float,
        has_covariance: bool,
        now_ns: int,
    ) -> EdgeState:
        """The edge's value after the new edge ``p``, ``q_xyzw`` with sigma ``sigma_m`` (``has_covariance``:
        its record carries the detector's 6x6), given its value so far ``state`` (None: a new edge)."""
        sigma = sigma_m
        if state is None or self.expired(state, now_ns):
            # A new or expired edge starts the filter afresh: old information is not mixed in.
            pass
        elif self.age_sigma_m_per_s > 0.0 and not has_covariance:
            # Beyond the paper: a per-edge Kalman filter with a random walk of age_sigma m/s. The old
            # value's variance grows with its age; the blend weighs old and new by inverse variance,
            # so a blurred frame (large sigma) cannot overwrite a sharp one taken a moment before.
            age_s = (now_ns - state.stamp_ns) / 1e9
            var_old = state.sigma_m**2 + (age_s * self.age_sigma_m_per_s) ** 2
            var_new = sigma**2
            alpha = var_old / (var_old + var_new)
            p = fusion.ema_position(state.p, p, alpha)
            q_xyzw = fusion.ema_quaternion(state.q, q_xyzw, alpha)
            sigma = float(np.sqrt(var_old * var_new / (var_old + var_new)))
        elif self.alpha == 1.0 or (self.age_sigma_m_per_s > 0.0 and has_covariance):
            # eq. 3 with alpha 1 (the paper's default): the measurement itself. A record with its own
            # 6x6 covariance is not blended as above: a scalar random walk of the position says nothing
            # of how the observer's turning swings the edge (the world origin seen from a drone moves
            # metres per radian), and the blend would claim a covariance the errors do not follow.
            pass
        else:
            p = fusion.ema_position(state.p, p, self.alpha)  # eq. 3
            q_xyzw = fusion.ema_quaternion(state.q, q_xyzw, self.alpha)
        return EdgeState(p, q_xyzw, now_ns, sigma)

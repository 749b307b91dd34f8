"""The records of the map refinement: its options, what goes in and what comes out.

Conventions as in :mod:`atlas_onboard.core.covariance`: a pose's error is ``[dp, dtheta]``, ``dp`` in the
parent frame (m) and ``dtheta`` about the child's own axes (rad).
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class RefineOptions:
    """When evidence counts and when a refined pose is used (lengths m, angles deg, times s)."""

    min_others: int = 2  # other world markers in the image; two can be checked against each other
    consistency_p: float = 1e-4  # the others' camera poses disagree when their chi2 has this tail probability
    outlier_p: float = 1e-4  # an evidence item is an outlier when its distance has this tail probability
    min_views: int = 12  # independent views (images at least view_gap_s apart per camera)
    view_gap_s: float = 0.5
    min_spread_deg: float = 5.0  # the viewing directions' widest angle from their mean direction
    max_sigma_m: float = 0.005  # the refined position's largest 1-sigma
    max_sigma_deg: float = 1.0  # the refined rotation's largest 1-sigma
    significance_p: float = 1e-6  # the offset from the current pose, against the refined covariance
    min_offset_m: float = 0.01  # smaller offsets are left alone (well within what the poses' noise hides)
    min_offset_deg: float = 1.0
    max_step_m: float = 0.05  # one update moves a marker at most this far
    max_step_deg: float = 2.0
    max_evidence: int = 2000  # items kept per marker (the newest)


@dataclass(frozen=True)
class Sighting:
    """One world marker in one image: its pose in the sensor's optical frame and its covariance.

    ``p_sensor_marker_m`` (3,), ``R_sensor_marker`` (3, 3), ``cov`` (6, 6): ``[dp, dtheta]`` with dp
    in the sensor frame (m) and dtheta about the marker's axes (rad)."""

    marker_id: int
    p_sensor_marker_m: NDArray[np.float64]
    R_sensor_marker: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass(frozen=True)
class Image:
    """One camera's image: the world markers it shows."""

    camera: Hashable
    capture_time_us: int
    sightings: tuple[Sighting, ...]


@dataclass(frozen=True)
class Evidence:
    """Where one image places one marker, from the other markers it shows (world frame)."""

    p_world_marker_m: NDArray[np.float64]
    R_world_marker: NDArray[np.float64]
    cov: NDArray[np.float64]  # (6, 6)
    direction: NDArray[np.float64]  # (3,) unit: from the marker towards the camera, in the marker's frame
    camera: Hashable  # which camera (sensor) took the image
    capture_time_us: int
    others: frozenset[int] = frozenset()  # the markers that placed the camera


@dataclass(frozen=True)
class WorldMarkerPose:
    """A marker's pose in the world frame and its 6x6 covariance: ``p_world_marker_m`` (3,), ``R_world_marker``
    (3, 3), ``cov`` (6, 6) of ``[dp, dtheta]`` (dp world frame m, dtheta about the marker's axes rad)."""

    marker_id: int
    p_world_marker_m: NDArray[np.float64]
    R_world_marker: NDArray[np.float64]
    cov: NDArray[np.float64]

    @property
    def max_sigma_m(self) -> float:
        """The position's largest 1-sigma, m."""
        return float(math.sqrt(max(np.linalg.eigvalsh(self.cov[:3, :3])[-1], 0.0)))

    @property
    def max_sigma_deg(self) -> float:
        """The rotation's largest 1-sigma, degrees."""
        return float(math.degrees(math.sqrt(max(np.linalg.eigvalsh(self.cov[3:, 3:])[-1], 0.0))))


@dataclass(frozen=True)
class Estimate(WorldMarkerPose):
    """A marker's refined pose in the world frame, from its inlying evidence.

    ``cov`` (6, 6) is the refined pose's covariance; ``views`` the independent views among the inliers;
    ``spread_deg`` the widest angle of a viewing direction from their mean; ``offset_m`` /
    ``offset_deg`` how far it is from the current map pose; ``distance2`` that offset's squared
    Mahalanobis distance under ``cov``; ``view_cov``, ``view_chi2``, ``view_dof``: see
    :func:`~atlas_onboard.core.refine.mean.view_scatter`."""

    items: int
    outliers: int
    views: int
    spread_deg: float
    offset_m: NDArray[np.float64]
    offset_deg: float
    distance2: float
    scatter: float = 1.0  # the inliers' median squared distance over its chi-square median (at least 1)
    view_cov: NDArray[np.float64] | None = None  # (6, 6) the pose's covariance with each view one average image
    view_chi2: float = 0.0  # the views' chi-square about their mean under view_cov's model
    view_dof: int = 0  # its degrees of freedom: 6 per view beyond the first

    @property
    def sigma_m(self) -> NDArray[np.float64]:
        """(3,) 1-sigma of the position along the world axes, m."""
        return np.sqrt(np.diag(self.cov)[:3])

    @property
    def sigma_deg(self) -> NDArray[np.float64]:
        """(3,) 1-sigma of the rotation about the world axes, degrees."""
        R = self.R_world_marker
        return np.degrees(np.sqrt(np.diag(R @ self.cov[3:, 3:] @ R.T)))


@dataclass(frozen=True)
class Update(WorldMarkerPose):
    """A marker moved by :meth:`MapRefiner.step`: its new map pose and covariance, and the estimate."""

    step_m: float
    step_deg: float
    reached: bool  # the step reached the estimate (not cut short by the step bound)
    estimate: Estimate

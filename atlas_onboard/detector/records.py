"""The records that link the detector's stages: a marker's own solve (:class:`SingleSolve`), the joint
solve's result for an entity's markers seen together (:class:`JointResult`), the frame's report
(:class:`FrameReport`) and the one builder of the MarkerData records it sends (:func:`marker_data`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core.markerdata import MarkerData, matrix_to_upper
from atlas_onboard.detector import pose


@dataclass(frozen=True)
class TimedCorners:
    """A square's corners as the image has them (undistorted px (4, 2), not moved to the frame's stamp), their
    (8, 8) covariance from the edge fit alone (no motion in it), and each corner's instant after the stamp
    (s, (4,): its row's, :class:`atlas_onboard.core.shutter.RowClock`)."""

    corners: NDArray[np.float64]
    covariance: NDArray[np.float64]
    dt_s: NDArray[np.float64]


@dataclass(frozen=True)
class SingleSolve:
    """One marker's own solve: its pose, undistorted corners (4, 2), their undistortion Jacobian
    (:func:`pose.undistortion_jacobian`, None without distortion) and measured corner noise (px)."""

    pose: pose.MarkerPose
    corners: NDArray[np.float64]
    stretch: NDArray[np.float64] | None
    measured_px: float
    corner_cov: NDArray[np.float64] | None = None  # (8, 8), px^2: refine.RefinedCorners.covariance
    motion_px: float = 0.0  # RMS corner noise of the camera motion's shear (detector.motion), in corner_cov too
    timed: TimedCorners | None = None  # a rolling shutter's corners at their rows' instants (a moving camera)


@dataclass(frozen=True)
class LeftOut:
    """A marker the joint solve left out because it does not fit with the others: where its own square is
    minus where the others' joint pose puts it (entity frame, m; None when they cannot be solved), and
    that distance (m; nan without it)."""

    marker_id: int
    offset: NDArray[np.float64] | None
    distance_m: float


@dataclass(frozen=True)
class JointResult:
    """The joint solve of an entity's markers seen together.

    ``md``: the entity's observation (None: none); ``used``: the ids that gave it, or all ids when the joint
    solve failed (the squares are then reported one by one), None when no subset of two or more fits;
    ``left_out``: the markers left out in turn, in that order; ``unfit``: the markers that remained and do
    not fit together; ``pair_offset``: when those are two (which of them moved cannot be said), the
    second's offset from the first (as in :class:`LeftOut`)."""

    md: MarkerData | None
    used: list[int] | None
    left_out: list[LeftOut] = field(default_factory=list)
    unfit: list[int] = field(default_factory=list)
    pair_offset: LeftOut | None = None

    @property
    def misfit_pair(self) -> list[int]:
        """The two markers that disagree, when no subset fits and two remained; else empty."""
        return self.unfit if self.pair_offset is not None else []


@dataclass
class FrameReport:
    """What the last frame gave: ids found, ids reported, and why the others were not (id -> reason)."""

    found: list[int] = field(default_factory=list)
    reported: list[int] = field(default_factory=list)
    dropped: dict[int, str] = field(default_factory=dict)

    def explain(self) -> str:
        """One line saying why nothing (or not everything) found was reported."""
        if not self.found:
            return "no tag found"
        ids = ", ".join(str(i) for i in self.found)
        why = "; ".join(f"marker {i}: {r}" for i, r in sorted(self.dropped.items()))
        n = len(self.found)
        head = f"{n} tag{'s' if n != 1 else ''} found (ids {ids})"
        if not self.reported:
            return f"{head}; none reported: {why}"
        return f"{head}; reported {', '.join(str(i) for i in self.reported)}" + (f"; not: {why}" if why else "")


def marker_data(
    sensor_id: int,
    marker_id: int,
    p: NDArray[np.float64],
    q_xyzw: NDArray[np.float64],
    sigma: float,
    err: float,
    ambiguity: float,
    capture_time_us: int,
    alt: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    covariance: NDArray[np.float64] | None = None,
) -> MarkerData:
    """The detector's record of a marker's pose. ``alt``: the other IPPE solution (p, q_xyzw), carried along
    for the listener; ``covariance``: the chosen solution's 6x6 (:func:`pose.pose_covariance`; None: the
    record carries none)."""
    x, y, z, w = q_xyzw
    if alt is None:
        p_alt, q_alt = (math.nan,) * 3, (math.nan,) * 4
    else:
        pa, (xa, ya, za, wa) = alt
        p_alt, q_alt = (float(pa[0]), float(pa[1]), float(pa[2])), (float(wa), float(xa), float(ya), float(za))
    return MarkerData(
        sensor_id=sensor_id,
        marker_id=marker_id,
        sigma_m=float(sigma),
        p_sensor_marker_m=(float(p[0]), float(p[1]), float(p[2])),
        q_sensor_marker_wxyz=(float(w), float(x), float(y), float(z)),
        capture_time_us=capture_time_us,
        reprojection_error_px=float(err),
        ambiguity_ratio=float(ambiguity),
        p_sensor_marker_alt_m=p_alt,  # type: ignore[arg-type]
        q_sensor_marker_alt_wxyz=q_alt,  # type: ignore[arg-type]
        covariance=matrix_to_upper(covariance) if covariance is not None else (),
    )

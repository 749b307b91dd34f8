"""What the map says of each marker and of the whole, with the figures behind a marker's report: how
correlated its residuals are, from how wide a spread of directions it was seen."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.mapping import ba
from atlas_onboard.mapping.geometry import _inv
from atlas_onboard.mapping.observations import FrameInfo

MAX_LAG_FRAMES = 30  # the residuals' autocorrelation is summed over at most this many frames


@dataclass
class MarkerReport:
    """What the map says of one marker (lengths in metres, angles in degrees)."""

    id: int
    size_m: float
    frames: int
    # mapped, anchor, too_rare, unanchored, degenerate, moved, duplicated, wrong_size, not_seen; refined, kept (live)
    status: str
    M_world_marker: NDArray[np.float64] | None = None
    sigma_m: tuple[float, float, float] | None = None
    sigma_deg: tuple[float, float, float] | None = None
    rms_px: float = math.nan
    view_spread_deg: float = math.nan
    detail: str = ""


@dataclass
class MapResult:
    markers: dict[int, MarkerReport]
    frame_rms_px: NDArray[np.float64]  # per adjusted frame
    frame_names: list[str]
    solution: ba.Solution | None
    sigma0_px: float
    timings_s: dict[str, float]
    unknown_ids: dict[int, int]
    frames_read: int
    frames_used: int
    observations: int

    def mapped(self) -> dict[int, NDArray[np.float64]]:
        """The marker poses the map gives (anchors and mapped markers), 4x4 T_world_marker by id."""
        return {
            m.id: m.M_world_marker
            for m in self.markers.values()
            if m.status in ("mapped", "anchor", "degenerate", "refined") and m.M_world_marker is not None
        }


def _correlation_inflation(
    r: NDArray[np.float64], frames: NDArray[np.int64], infos: list[FrameInfo], max_lag: int = MAX_LAG_FRAMES
) -> float:
    """The integrated autocorrelation time ``1 + 2 sum_k rho_k`` of one marker's corner residuals ``r``
    (n, 4, 2) along the frames of each input (``frames``: their adjusted-frame indices), summed over
    lags of 1, 2, ... frames while the correlation stays positive (at most ``max_lag``): how many
    times fewer independent errors the marker's sightings hold than their count."""
    v = r.reshape(len(r), -1)
    var = float(np.mean(np.sum(v * v, axis=1)))
    if var <= 0.0:
        return 1.0
    row = {(infos[f].source, infos[f].index): i for i, f in enumerate(frames)}
    tau = 1.0
    for lag in range(1, max_lag + 1):
        pairs = [(i, row[(s, k + lag)]) for (s, k), i in row.items() if (s, k + lag) in row]
        if len(pairs) < 5:
            break
        a, b = np.array(pairs).T
        rho = float(np.mean(np.sum(v[a] * v[b], axis=1))) / var
        if rho <= 0.0:
            break
        tau += 2.0 * rho
    return tau


def _view_spread(sol: ba.Solution, problem: ba.Problem, k: int) -> float:
    """The largest angle between two directions from which the marker was seen, degrees."""
    frames = np.unique(problem.obs_frame[problem.obs_marker == k])
    if len(frames) < 2:
        return 0.0
    centres = np.array([_inv(sol.M_cam_world[f])[:3, 3] for f in frames])
    d = centres - sol.M_world_marker[k][:3, 3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # The widest pair: the angle of each direction from the mean, twice the largest (cheap and close).
    mean = d.mean(axis=0)
    mean /= np.linalg.norm(mean)
    return float(np.degrees(np.arccos(np.clip(d @ mean, -1, 1)).max() + np.arccos(np.clip(d @ mean, -1, 1)).min()))

"""Scoring a simulated run against ground truth, and writing what a researcher needs from it:
the per-entity figures, trajectories in TUM format (for ``evo_ape``), and plots like the paper's
Figures 6 and 7."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import frames
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim.flight import LandingScore
from atlas_onboard.sim.world import FRESH_S, FRESH_STEP_S, SimWorld, fresh_share

_ROWS, _COLS = np.triu_indices(6)  # MAVLink's row-major upper triangle: (0,0) (0,1) ... (0,5) (1,1) ... (5,5)


@dataclass
class Track:
    """Estimates of one entity: times are seconds since the run's start (capture and arrival)."""

    capture_s: NDArray[np.float64]
    arrival_s: NDArray[np.float64]
    p_m: NDArray[np.float64]  # (N, 3) ENU
    q_xyzw: NDArray[np.float64]  # (N, 4) FLU body in ENU
    n_observations: NDArray[np.float64] | None = None
    # What the autopilot received, as sent: position in local NED, body FRD in NED, and the 6x6
    # covariance (x y z in NED, small rotations about the FRD body axes); NaN where unknown.
    p_ned_m: NDArray[np.float64] | None = None  # (N, 3)
    q_ned_frd_xyzw: NDArray[np.float64] | None = None  # (N, 4)
    covariance_ned_frd: NDArray[np.float64] | None = None  # (N, 6, 6)
    reset_counter: NDArray[np.int64] | None = None  # (N,) the message's reset_counter


@dataclass
class EntityScore:
    entity: str
    source: str  # "autopilot" (what the flight controller received) or "fused" (the node's broadcast)
    messages: int
    rate_hz: float
    rmse_m: float
    max_error_m: float
    median_error_m: float
    attitude_rmse_deg: float
    availability: float
    expected_availability: float
    latency_median_ms: float
    latency_p95_ms: float
    detections_per_s: float = 0.0
    longest_gap_s: float = 0.0
    stale_after_loss_s: float = 0.0
    # Mean normalised estimation error squared against the covariance published with each message:
    # about 3 (position) and 6 (pose) when the covariance is honest; NaN when it is unknown.
    position_nees: float = float("nan")
    pose_nees: float = float("nan")
    p95_error_m: float = float("nan")
    # Share of messages whose error on each axis (x y z of local NED) is within 3 sigma of the
    # covariance sent with them; NaN where it was unknown.
    within_3sigma: tuple[float, float, float] = (float("nan"), float("nan"), float("nan"))
    reset_changes: int = 0  # changes of reset_counter between consecutive messages


@dataclass
class RunReport:
    scenario: str
    duration_s: float
    seed: int
    clock: str
    rates: dict[str, str]
    entities: list[EntityScore] = field(default_factory=list)
    counters: dict[str, dict[str, int]] = field(default_factory=dict)
    bars: list[dict[str, object]] = field(default_factory=list)
    landing: LandingScore | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, default=float)

    def table(self) -> str:
        head = (
            f"{'entity':<10} {'source':<9} {'msgs':>5} {'rate Hz':>7} {'RMSE cm':>8} {'max cm':>7} {'att deg':>7}"
            f" {'avail':>6} {'expect':>6} {'det/s':>6} {'lat ms':>7} {'p95 ms':>7} {'NEES3':>7} {'NEES6':>7}"
        )
        rows = [head]
        for e in self.entities:
            rows.append(
                f"{e.entity:<10} {e.source:<9} {e.messages:>5} {e.rate_hz:>7.1f} {e.rmse_m * 100:>8.2f}"
                f" {e.max_error_m * 100:>7.2f} {e.attitude_rmse_deg:>7.2f} {e.availability:>6.1%}"
                f" {e.expected_availability:>6.1%} {e.detections_per_s:>6.1f} {e.latency_median_ms:>7.1f}"
                f" {e.latency_p95_ms:>7.1f} {e.position_nees:>7.2f} {e.pose_nees:>7.2f}"
            )
        if (ls := self.landing) is not None:
            where = (
                "did not land"
                if ls.touchdown_m is None
                else (f"touched down {ls.touchdown_m * 100:.2f} cm from the landing point at {ls.touchdown_s:.1f} s")
            )
            rows.append(f"landing: {ls.entity} {where}; LANDING_TARGET received {ls.targets}, stale"
                        f" {ls.stale_targets}, refused {ls.refused}; aborts {ls.aborts}")  # fmt: skip
        return "\n".join(rows)


def score(
    entity: str,
    source: str,
    track: Track,
    world: SimWorld,
    t0_s: float,
    t1_s: float,
    expected: float,
    fresh_s: float = FRESH_S,
) -> EntityScore:
    """Errors at each estimate's capture time; availability as the share of [t0, t1] at which the
    newest estimate that arrived was at most ``fresh_s`` old (:func:`fresh_share`)."""
    inside = (track.arrival_s >= t0_s) & (track.arrival_s <= t1_s)
    cap, arr = track.capture_s[inside], track.arrival_s[inside]
    p, q = track.p_m[inside], track.q_xyzw[inside]
    n = len(cap)
    if n == 0:
        return EntityScore(
            entity,
            source,
            0,
            0.0,
            *([float("nan")] * 4),
            0.0,
            expected,
            float("nan"),
            float("nan"),
            longest_gap_s=t1_s - t0_s,
        )
    p_true, q_true = world.truth_series(entity, cap)
    err = np.linalg.norm(p - p_true, axis=1)
    att = (Rotation.from_quat(q).inv() * Rotation.from_quat(q_true)).magnitude()
    latency_ms = (arr - cap) * 1e3
    gaps = np.diff(np.concatenate(([t0_s], np.sort(arr), [t1_s])))
    nees3 = nees6 = float("nan")
    if track.p_ned_m is not None and track.q_ned_frd_xyzw is not None and track.covariance_ned_frd is not None:
        e = pose_errors_ned_frd(track.p_ned_m[inside], track.q_ned_frd_xyzw[inside], p_true, q_true)
        cov = track.covariance_ned_frd[inside]
        nees3 = _mean_known(nees(e[:, :3], cov[:, :3, :3]))
        nees6 = _mean_known(nees(e, cov))
        within = within_sigma(e[:, :3], cov[:, :3, :3], 3.0)
    else:
        within = (float("nan"),) * 3
    resets = 0
    if track.reset_counter is not None:
        resets = int(np.count_nonzero(np.diff(track.reset_counter[inside])))
    return EntityScore(
        entity=entity,
        source=source,
        messages=n,
        rate_hz=n / (t1_s - t0_s),
        rmse_m=float(np.sqrt(np.mean(err**2))),
        max_error_m=float(err.max()),
        median_error_m=float(np.median(err)),
        attitude_rmse_deg=float(np.degrees(np.sqrt(np.mean(att**2)))),
        availability=fresh_share(track.arrival_s, t0_s, t1_s, fresh_s),
        expected_availability=expected,
        latency_median_ms=float(np.median(latency_ms)),
        latency_p95_ms=float(np.percentile(latency_ms, 95)),
        longest_gap_s=float(gaps.max()),
        position_nees=nees3,
        pose_nees=nees6,
        p95_error_m=float(np.percentile(err, 95)),
        within_3sigma=within,  # type: ignore[arg-type]
        reset_changes=resets,
    )


def within_sigma(errors: NDArray[np.float64], covariances: NDArray[np.float64], k: float = 3.0) -> tuple[float, ...]:
    """Per axis, the share of rows whose error (N, d) is within ``k`` standard deviations of the
    covariance (N, d, d); rows with an unknown (non-finite) or non-positive variance are left out."""
    e = np.atleast_2d(np.asarray(errors, dtype=float))
    var = np.diagonal(np.asarray(covariances, dtype=float), axis1=1, axis2=2)
    out = []
    for a in range(e.shape[1]):
        ok = np.isfinite(var[:, a]) & (var[:, a] > 0) & np.isfinite(e[:, a])
        out.append(float(np.mean(np.abs(e[ok, a]) <= k * np.sqrt(var[ok, a]))) if np.any(ok) else float("nan"))
    return tuple(out)


def coverage(
    arrival_s: NDArray[np.float64], ideal_s: NDArray[np.float64], t0_s: float, t1_s: float, fresh_s: float = FRESH_S
) -> float:
    """The share of the time an ideal node holds a fresh pose (``ideal_s``: the frame times at which a
    camera sees a path to the world) during which the receiver held one too (``arrival_s``): availability
    against the time a tag is in view, on the 5 ms grid of :func:`fresh_share`. NaN if never in view."""
    grid = np.arange(t0_s, t1_s, FRESH_STEP_S)
    want = _fresh_mask(np.asarray(ideal_s, dtype=float), grid, fresh_s)
    have = _fresh_mask(np.asarray(arrival_s, dtype=float), grid, fresh_s)
    return float(np.mean(have[want])) if np.any(want) else float("nan")


def _fresh_mask(times_s: NDArray[np.float64], grid: NDArray[np.float64], fresh_s: float) -> NDArray[np.bool_]:
    t = np.sort(times_s)
    if len(t) == 0:
        return np.zeros(len(grid), dtype=bool)
    k = np.searchsorted(t, grid, side="right") - 1
    newest = np.where(k >= 0, t[np.maximum(k, 0)], -np.inf)
    return grid - newest <= fresh_s


def reset_changes_at_gaps(
    capture_s: NDArray[np.float64], reset_counter: NDArray[np.int64], ideal_s: NDArray[np.float64], min_gap_s: float
) -> tuple[int, int, int]:
    """Reset-counter changes against real re-acquisitions: (changes, changes at a re-acquisition,
    re-acquisitions). A re-acquisition is the end of a stretch of at least ``min_gap_s`` in which no
    camera saw a path to the world (``ideal_s``: the frame times at which one did); a change between
    two messages is at one when such a stretch lies between their capture times."""
    cap = np.asarray(capture_s, dtype=float)
    rc = np.asarray(reset_counter)
    ideal = np.sort(np.asarray(ideal_s, dtype=float))
    gaps = np.diff(ideal)
    long_ = gaps >= min_gap_s
    gap_start, gap_end = ideal[:-1][long_], ideal[1:][long_]
    changed = np.flatnonzero(np.diff(rc) != 0) + 1
    justified = 0
    for i in changed:
        a, b = cap[i - 1], cap[i]
        # the invisible stretch (gap_start, gap_end) must overlap the interval between the messages
        if np.any((gap_start < b) & (gap_end > a)):
            justified += 1
    inside = (gap_end > cap[0]) & (gap_end <= cap[-1]) if len(cap) else np.zeros(0, dtype=bool)
    return len(changed), justified, int(np.count_nonzero(inside))


def covariance_from_upper_triangle(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """6x6 covariances (N, 6, 6) from MAVLink's 21-element row-major upper triangles (N, 21).

    The inverse of :func:`atlas_onboard.mavlink.autopilot.covariance_upper_triangle`. A triangle whose
    first element is NaN means "unknown" (MAVLink's convention) and gives an all-NaN matrix.
    """
    v = np.atleast_2d(np.asarray(values, dtype=float))
    if v.shape[-1] != 21:
        raise AtlasError(f"expected covariance triangles of shape (N, 21), got shape {v.shape}")
    out = np.zeros((len(v), 6, 6))
    out[:, _ROWS, _COLS] = v
    out[:, _COLS, _ROWS] = v
    out[np.isnan(v[:, 0])] = np.nan
    return out


def pose_errors_ned_frd(
    p_est_ned_m: NDArray[np.float64],
    q_est_ned_frd_xyzw: NDArray[np.float64],
    p_true_enu_m: NDArray[np.float64],
    q_true_enu_flu_xyzw: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Errors (N, 6) of estimates sent in NED/FRD against truth in ENU/FLU, in the frame of the
    published covariance: position estimate - truth in NED (m), then the small rotation d (rad) about
    the FRD body axes with ``R_est = R_true * exp(d)`` (the error-state convention of the EKF and of
    :func:`atlas_onboard.mavlink.autopilot.covariance_ned_frd`)."""
    T_true = frames.enu_flu_to_ned_frd(
        RigidTransform.from_components(np.asarray(p_true_enu_m, float), Rotation.from_quat(q_true_enu_flu_xyzw))
    )
    dp = np.asarray(p_est_ned_m, dtype=float) - T_true.translation
    dtheta = (T_true.rotation.inv() * Rotation.from_quat(q_est_ned_frd_xyzw)).as_rotvec()
    return np.hstack([np.atleast_2d(dp), np.atleast_2d(dtheta)])


def nees(errors: NDArray[np.float64], covariances: NDArray[np.float64]) -> NDArray[np.float64]:
    """Normalised estimation error squared ``e^T C^-1 e`` per row: errors (N, k), covariances (N, k, k).

    NaN for a covariance that is unknown (non-finite) or not positive definite.
    """
    e = np.atleast_2d(np.asarray(errors, dtype=float))
    c = np.asarray(covariances, dtype=float).reshape(len(e), e.shape[1], e.shape[1])
    out = np.full(len(e), np.nan)
    ok = np.all(np.isfinite(c), axis=(1, 2))
    if np.any(ok):
        ok[ok] = np.linalg.eigvalsh(c[ok]).min(axis=1) > 0.0
    if np.any(ok):
        x = np.linalg.solve(c[ok], e[ok][:, :, None])[:, :, 0]
        out[ok] = np.einsum("ij,ij->i", e[ok], x)
    return out


def _mean_known(values: NDArray[np.float64]) -> float:
    known = values[np.isfinite(values)]
    return float(known.mean()) if len(known) else float("nan")


def write_tum(path: Path, t_s: NDArray[np.float64], p: NDArray[np.float64], q_xyzw: NDArray[np.float64]) -> None:
    """TUM trajectory format: ``timestamp tx ty tz qx qy qz qw`` per line (evo_ape reads it)."""
    with open(path, "w", encoding="utf-8") as f:
        for t, pp, qq in zip(t_s, p, q_xyzw, strict=True):
            f.write(f"{t:.6f} {pp[0]:.6f} {pp[1]:.6f} {pp[2]:.6f} {qq[0]:.8f} {qq[1]:.8f} {qq[2]:.8f} {qq[3]:.8f}\n")


def plot_entity(path: Path, entity: str, track: Track, world: SimWorld, t0_s: float, t1_s: float) -> bool:
    """The paper's Figure 6/7 layout: x, y, z of Atlas against ground truth, and the number of
    measurements, over time. Returns False (and writes nothing) when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    t_truth = np.linspace(t0_s, t1_s, 600)
    p_truth, _ = world.truth_series(entity, t_truth)
    fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    for k, (ax, label) in enumerate(zip(axes[:3], "xyz", strict=True)):
        ax.plot(t_truth, p_truth[:, k], color="black", lw=1.2, label="ground truth")
        ax.plot(track.capture_s, track.p_m[:, k], ".", ms=2.5, color="tab:red", label="Atlas")
        ax.set_ylabel(f"{label} [m]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(f"{entity}: Atlas estimate against ground truth")
    if track.n_observations is not None and len(track.n_observations):
        axes[3].step(track.capture_s, track.n_observations, where="post", color="tab:blue")
    axes[3].set_ylabel("measurements")
    axes[3].set_xlabel("time [s]")
    axes[3].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True

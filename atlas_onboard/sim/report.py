"""Scoring a simulated run against ground truth, and writing what a researcher needs from it:
the per-entity figures, trajectories in TUM format (for ``evo_ape``), and plots like the paper's
Figures 6 and 7."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.sim.world import SimWorld


@dataclass
class Track:
    """Estimates of one entity: times are seconds since the run's start (capture and arrival)."""

    capture_s: NDArray[np.float64]
    arrival_s: NDArray[np.float64]
    p_m: NDArray[np.float64]  # (N, 3) ENU
    q_xyzw: NDArray[np.float64]  # (N, 4) FLU body in ENU
    n_observations: NDArray[np.float64] | None = None


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

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, default=float)

    def table(self) -> str:
        head = (
            f"{'entity':<10} {'source':<9} {'msgs':>5} {'rate Hz':>7} {'RMSE cm':>8} {'max cm':>7} {'att deg':>7}"
            f" {'avail':>6} {'expect':>6} {'det/s':>6} {'lat ms':>7} {'p95 ms':>7}"
        )
        rows = [head]
        for e in self.entities:
            rows.append(
                f"{e.entity:<10} {e.source:<9} {e.messages:>5} {e.rate_hz:>7.1f} {e.rmse_m * 100:>8.2f}"
                f" {e.max_error_m * 100:>7.2f} {e.attitude_rmse_deg:>7.2f} {e.availability:>6.1%}"
                f" {e.expected_availability:>6.1%} {e.detections_per_s:>6.1f} {e.latency_median_ms:>7.1f}"
                f" {e.latency_p95_ms:>7.1f}"
            )
        return "\n".join(rows)


def score(
    entity: str,
    source: str,
    track: Track,
    world: SimWorld,
    t0_s: float,
    t1_s: float,
    expected: float,
    bin_s: float = 0.1,
) -> EntityScore:
    """Errors at each estimate's capture time, availability as the share of ``bin_s`` bins of
    [t0, t1] in which at least one estimate arrived."""
    inside = (track.arrival_s >= t0_s) & (track.arrival_s <= t1_s)
    cap, arr = track.capture_s[inside], track.arrival_s[inside]
    p, q = track.p_m[inside], track.q_xyzw[inside]
    n = len(cap)
    bins = max(round((t1_s - t0_s) / bin_s), 1)
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
    hit = np.zeros(bins, dtype=bool)
    hit[np.clip(((arr - t0_s) / bin_s).astype(int), 0, bins - 1)] = True
    latency_ms = (arr - cap) * 1e3
    gaps = np.diff(np.concatenate(([t0_s], np.sort(arr), [t1_s])))
    return EntityScore(
        entity=entity,
        source=source,
        messages=n,
        rate_hz=n / (t1_s - t0_s),
        rmse_m=float(np.sqrt(np.mean(err**2))),
        max_error_m=float(err.max()),
        median_error_m=float(np.median(err)),
        attitude_rmse_deg=float(np.degrees(np.sqrt(np.mean(att**2)))),
        availability=float(hit.mean()),
        expected_availability=expected,
        latency_median_ms=float(np.median(latency_ms)),
        latency_p95_ms=float(np.percentile(latency_ms, 95)),
        longest_gap_s=float(gaps.max()),
    )


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

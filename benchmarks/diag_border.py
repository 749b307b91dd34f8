"""Whether the detector's image-border refusal is too strict: single-marker pose accuracy by how near the
border a marker's nearest corner lies, the refusal lowered so that the markers inside ``BORDER_MARGIN_PX``
are solved too.

Rendered frames of one marker of the rolling scenes' camera (640x480, its barrel distortion) and world,
placed so that its nearest corner lies a chosen distance (px) inside a random side of the image, its side
35-120 px, tilted about 20 deg, any roll, pixel noise 2 and a motion blur of about 1 px, over a smooth or a
concrete background; each frame through a fresh detector (the node's settings, ``joint`` off so that each
pose is the marker's own) whose image-border refusal is lowered to ``LOW_PX`` (its region searches keep
theirs). Per distance: frames solved, position error (mean, median, p95, max, mm) against the truth, and
NEES3 with the detector's own covariance (median, mean, share over 11.34, chi-square's 99 % for 3 dof),
beside the anchor: the markers at least ``BORDER_MARGIN_PX`` inside (what the detector uses). Its bar: the
p95 error of the band a margin of half would add ([BORDER_MARGIN_PX / 2, BORDER_MARGIN_PX)) over the
anchor's, against 1.5 (pass: a smaller margin would keep the accuracy; not a change by itself).

    taskset -c 0 python benchmarks/diag_border.py [--frames 60] [--seed 3]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_onboard.core.markerdata import upper_to_matrix
from atlas_onboard.detector import pipeline
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import MarkerView, render
from atlas_onboard.detector.search import BORDER_MARGIN_PX
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.world import SimWorld, marker_corners

LOW_PX = 0.5  # the refusal while measuring: only corners (nearly) outside the image
DISTANCES_PX = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 12.0, 40.0)
SIDE_PX = (35.0, 120.0)
CHI2_3_99 = 11.34
BAR_RATIO = 1.5


def _at_border_low(c: NDArray[np.float64], w: int, h: int) -> bool:
    lo, hi = c.min(axis=0), c.max(axis=0)
    return bool(lo[0] < LOW_PX or lo[1] < LOW_PX or hi[0] > w - 1 - LOW_PX or hi[1] > h - 1 - LOW_PX)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60, help="frames per distance")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    pipeline.at_border = _at_border_low  # the image-border refusal only (the pipeline's name for it)
    sc = scenarios.get("rolling-global")
    world = sc.world()
    sim = SimWorld(sc)
    sensor, intr = next(v for v in sim.cameras.values() if v[0].entity == "drone")
    cal = intr.calibration()
    marker = min((m for m in world.markers.values() if m.entity == "world"), key=lambda m: m.size_m)
    w, h = intr.width_px, intr.height_px
    corners = marker_corners(marker.size_m)
    rng = np.random.default_rng(args.seed)

    def inside(px: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.array([px[:, 0].min(), px[:, 1].min(), w - 1 - px[:, 0].max(), h - 1 - px[:, 1].max()])

    results: dict[float, list[tuple[float, float]]] = {d: [] for d in DISTANCES_PX}
    dropped: dict[float, dict[str, int]] = {d: {} for d in DISTANCES_PX}
    for d in DISTANCES_PX:
        for k in range(args.frames):
            z = intr.fx * marker.size_m / rng.uniform(*SIDE_PX)
            tilt = np.r_[rng.normal(0.0, 0.35, 2), rng.uniform(-np.pi, np.pi)]
            R = Rotation.from_rotvec(tilt) * Rotation.from_euler("x", np.pi)  # facing the camera
            side = int(rng.integers(4))  # left, top, right, bottom
            axis, sign = side % 2, (-1.0 if side < 2 else 1.0)
            p = np.array([0.0, 0.0, z])
            for _ in range(40):  # slide towards that side until the nearest corner there is d px inside
                err = inside(intr.project(R.apply(corners) + p))[side] - d
                if abs(err) < 1e-3:
                    break
                p[axis] += sign * 0.9 * err * z / intr.fx
            px = intr.project(R.apply(corners) + p)
            if abs(inside(px)[side] - d) >= 1e-3 or inside(px).min() < d - 1e-3:
                continue  # the marker does not fit that near this side (another side nearer)
            view = MarkerView(marker.family, marker.id, marker.size_m, RigidTransform.from_components(p, R))
            img = render(
                cal, [view], seed=k + 1000 * int(d), background_seed=k, noise_sigma=2.0,
                blur_px=tuple(rng.normal(0.0, 1.0, 2)), supersample=3,
                background_style="concrete" if k % 2 else "smooth",
            )  # fmt: skip
            det = Detector(sensor, world, cal, decimate=2.0, joint=False)
            md = next((m for m in det.detect(img, 0) if m.marker_id == marker.id), None)
            if md is None:
                why = det.report.dropped.get(marker.id, "not found")
                dropped[d][why] = dropped[d].get(why, 0) + 1
                continue
            e = np.asarray(md.p_sensor_marker_m) - p
            C = upper_to_matrix(np.asarray(md.covariance))[:3, :3]
            results[d].append((float(np.linalg.norm(e)) * 1e3, float(e @ np.linalg.solve(C, e))))

    def figures(rows: list[tuple[float, float]]) -> tuple[float, ...]:
        if not rows:
            return (math.nan,) * 7
        e, n = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
        return (e.mean(), float(np.median(e)), float(np.percentile(e, 95)), e.max(), float(np.median(n)), n.mean(),
                100 * float(np.mean(n > CHI2_3_99)))  # fmt: skip

    print(f"one {marker.family} marker, a side of {SIDE_PX[0]:g}-{SIDE_PX[1]:g} px, on {w}x{h}; the image-border"
          f" refusal lowered from {BORDER_MARGIN_PX:g} to {LOW_PX:g} px; {args.frames} frames a distance")  # fmt: skip
    print(f"{'corner px':>9} {'solved':>9} {'mean mm':>8} {'median':>7} {'p95':>7} {'max':>7} {'NEES3 med':>9}"
          f" {'mean':>6} {'>99%':>6}  not solved")  # fmt: skip
    anchor = [r for d in DISTANCES_PX if d >= BORDER_MARGIN_PX for r in results[d]]
    band = [r for d in DISTANCES_PX if BORDER_MARGIN_PX / 2 <= d < BORDER_MARGIN_PX for r in results[d]]
    rows = [(f"{d:g}", results[d], dropped[d]) for d in DISTANCES_PX]
    rows += [(f">={BORDER_MARGIN_PX:g}", anchor, {}), (f"[{BORDER_MARGIN_PX / 2:g},{BORDER_MARGIN_PX:g})", band, {})]
    for name, res, why in rows:
        f = figures(res)
        tried = len(res) + sum(why.values())
        print(f"{name:>9} {len(res):>4}/{tried:<4} {f[0]:>8.2f} {f[1]:>7.2f} {f[2]:>7.2f} {f[3]:>7.1f} {f[4]:>9.2f}"
              f" {f[5]:>6.2f} {f[6]:>5.1f}%  {why or ''}")  # fmt: skip
    ratio = figures(band)[2] / figures(anchor)[2]
    ok = "pass" if ratio <= BAR_RATIO else "fail"
    print(f"BAR border_band_p95_over_inside {ratio:.3g} x {BAR_RATIO:g} {ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

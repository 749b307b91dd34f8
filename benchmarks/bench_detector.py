"""Detector speed and accuracy on rendered frames with known truth, side by side with its anchors.

Sequences of frames (markers drifting and turning slowly, as seen from a hovering drone) over a textured
concrete floor, at several distances, sharp and with blur and noise, at 640x480 and 1280x720, one core
(run it under ``taskset -c 0``; OpenCV and the library are set to one thread). Each sequence has a few
frames in which every marker is out of view, so the tracker loses them and hunts again. Compared on the
same frames, interleaved frame by frame (the machine's noise falls on every method alike): the AprilTag 3
library at decimate 1 and 2, OpenCV's ArucoDetector (DICT_APRILTAG_36h11), and ours. Times are given for
our hunting frames (nothing tracked) and tracking frames separately, with the anchors' times on the same
frames. Poses of every method come from the same IPPE solve on the method's corners, so pose figures
compare the corners.

Recall, the same rule for every method: the markers to report are those whose four true corners lie at
least BORDER_MARGIN_PX inside the image (the border rule of the detector, issue 19 class 1: closer to
the border, the edges cannot be fitted and such poses were wrong). A detection of a marker in that band
or cut by the border is neither a hit nor a false id; how many each method made is printed ("border"),
so that the rule's effect is seen: the library reports some, ours drops them after finding (in
``detect``, not in the ``find`` timed here).

Other methods deliver IPPE's chosen solution whatever its ambiguity. Ours delivers it when the IPPE
ratio is at most 0.5; above, the detector keeps both solutions and the listener resolves them with the
current estimate (core/ambiguity.py), simulated here as the truth with the error the listener assumes
(3 degrees per axis, and 2 cm), or rejects them as unresolved. Its flips figure is over the poses it
delivers, resolved ones included.

    taskset -c 0 python benchmarks/bench_detector.py [--frames N]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_onboard.config import parse_world
from atlas_onboard.core import ambiguity
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.markerdata import upper_to_matrix
from atlas_onboard.detector import pose
from atlas_onboard.detector.backends import Detection, _library_detector
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.families import opencv_dictionary
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import LENS_RESIDUAL_PX, Camera, MarkerView, render
from atlas_onboard.detector.search import BORDER_MARGIN_PX
from atlas_onboard.listener import ESTIMATE_ATTITUDE_SIGMA_RAD

SIZE = 0.15
IDS = (3, 11, 25)


GAP = (0.45, 0.6)  # the part of each sequence (fractions of its frames) in which no marker is in view


def sequences(width: int, height: int, n: int):
    """(name, K, frames): each frame an image and the views of the markers drawn in it."""
    f = width * 0.78
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    cam = Camera(width, height, K, np.zeros(5))
    for distance in (0.7, 1.5, 3.0, 5.0):
        for variant, blur, noise in (("sharp", 0.0, 1.0), ("blur+noise", 2.5, 4.0)):
            frames = []
            for k in range(n):
                views = []
                if not GAP[0] * n <= k < GAP[1] * n:
                    for j, mid in enumerate(IDS):
                        x = (j - 1) * 0.45 * distance * width / 1280 + 0.02 * distance * np.sin(0.2 * k + j)
                        rot = Rotation.from_euler(
                            "xyz", [180 + 25 * np.sin(0.05 * k + j), 15 * j, 10 * k / n + 30 * j], degrees=True
                        )
                        T = RigidTransform.from_components([x, 0.1 * distance, distance], rot)
                        views.append(MarkerView("tag36h11", mid, SIZE, T))
                img = render(cam, views, seed=k, noise_sigma=noise, blur_px=(blur, 0.0), supersample=3,
                             background_style="concrete", background_seed=int(distance * 10))  # fmt: skip
                frames.append((img, views))
            yield f"{width}x{height} {distance} m {variant}", K, cam, frames


def in_view(cam: Camera, views: list[MarkerView], margin_px: float = BORDER_MARGIN_PX) -> list[MarkerView]:
    """The markers whose four corners lie inside the image by ``margin_px``: those every method should find
    (ours drops markers closer to the border than that, whose edges cannot be fitted)."""
    out = []
    for v in views:
        M = v.T_camera_marker.as_matrix()
        P = pose.object_corners(v.size_m) @ M[:3, :3].T + M[:3, 3]
        px = P[:, :2] / P[:, 2:] * np.diag(cam.K)[:2] + cam.K[:2, 2]
        if np.all(P[:, 2] > 0) and np.all((px >= margin_px) & (px <= [cam.width_px - 1 - margin_px,
                                                                       cam.height_px - 1 - margin_px])):  # fmt: skip
            out.append(v)
    return out


ESTIMATE_POS_M = 0.02  # position error of the simulated estimate (per axis); attitude: the listener's


def estimate(T: RigidTransform, rng: np.random.Generator) -> RigidTransform:
    """A simulated current estimate of T_camera_marker: the truth with the error the listener assumes
    for a drone's estimate (per axis: ESTIMATE_ATTITUDE_SIGMA_RAD, ESTIMATE_POS_M)."""
    err = RigidTransform.from_components(
        rng.normal(0.0, ESTIMATE_POS_M, 3), Rotation.from_rotvec(rng.normal(0.0, ESTIMATE_ATTITUDE_SIGMA_RAD, 3))
    )
    return err * T


def score(
    found: list[Detection],
    views: list[MarkerView],
    visible: list[MarkerView],
    K: np.ndarray,
    rng: np.random.Generator | None = None,
) -> dict[str, int | list[float]]:
    """Hits, false ids, translation errors (% of distance) and flips (> 10 deg) of the poses a method
    delivers. Other methods deliver IPPE's chosen solution. Ours (``rng`` given) delivers it when the
    ratio is at most AMBIGUITY_THRESHOLD; above, it keeps both solutions and the listener resolves them
    with a current estimate (simulated: the truth with the listener's assumed error), or rejects them."""
    truth = {v.marker_id: v for v in views}
    seen = {v.marker_id for v in visible}
    counts = (
        "hits",
        "false",
        "border",
        "flips",
        "ambiguous",
        "resolved",
        "swapped",
        "unresolved",
        "flips_unresolved_as_chosen",
        "flips_resolved",
    )
    out: dict[str, int | list[float]] = {"errs": [], **dict.fromkeys(counts, 0)}
    for d in found:
        v = truth.get(d.marker_id)
        if v is None:
            out["false"] += 1
            continue
        if d.marker_id not in seen:  # a marker in the border band or cut: neither a hit nor a false id
            out["border"] += 1
            continue
        out["hits"] += 1
        mp = pose.solve(d.corners_px, SIZE, K, pose.SIGMA_PX_APRILTAG)
        if mp is None:
            continue
        T_true = v.T_camera_marker
        T = RigidTransform.from_components(mp.p_m, Rotation.from_quat(mp.q_xyzw))
        if rng is not None and mp.ambiguity > AMBIGUITY_THRESHOLD:
            out["ambiguous"] += 1
            if mp.p_alt_m is None or mp.q_alt_xyzw is None:
                out["unresolved"] += 1
                continue
            T_alt = RigidTransform.from_components(mp.p_alt_m, Rotation.from_quat(mp.q_alt_xyzw))
            sigma_rad, sigma_m = ambiguity.prediction_sigmas(
                float(np.linalg.norm(mp.p_m)), mp.sigma_m, ESTIMATE_POS_M, 0.0, ESTIMATE_ATTITUDE_SIGMA_RAD, 0.0
            )
            res = ambiguity.resolve(T, T_alt, estimate(T_true, rng), float(sigma_rad), float(sigma_m))
            if not res.verdict.decided:
                out["unresolved"] += 1
                out["flips_unresolved_as_chosen"] += _angle_deg(T, T_true) > 10
                continue
            out["resolved"] += 1
            if res.verdict is ambiguity.Verdict.ALT:
                out["swapped"] += 1
                T = T_alt
        dist = float(np.linalg.norm(T_true.translation))
        out["errs"].append(float(np.linalg.norm(T.translation - T_true.translation)) / dist * 100)
        flip = _angle_deg(T, T_true) > 10
        out["flips"] += flip
        out["flips_resolved"] += flip and rng is not None and mp.ambiguity > AMBIGUITY_THRESHOLD
    return out


def _angle_deg(a: RigidTransform, b: RigidTransform) -> float:
    return float(np.degrees((a.rotation.inv() * b.rotation).magnitude()))


def covariance_check(
    n: int, states: list[str] | None = None, inside: list[np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Single markers anywhere in a 640x480 image with strong barrel distortion (k1 = -0.3), 0.4-3 m,
    0-70 degrees, half of them with motion blur, noise 3 grey levels, over concrete: the detector's
    reported 6x6 covariance against the truth. Returns NEES3 (position), NEES6 and the share within
    3 sigma per axis [dp, dtheta]; ``states``, when given, gets each detection's state (sharp or
    blurred, centre or edge of the image: beyond 0.6 of the half diagonal from the centre); ``inside``, when
    given, gets each detection's per-axis within-3-sigma flags (6,)."""
    K = np.array([[460.0, 0.0, 319.5], [0.0, 460.0, 239.5], [0.0, 0.0, 1.0]])
    dist = np.array([-0.3, 0.08, 0.0, 0.0, 0.0])
    cam = Camera(640, 480, K, dist)
    world = parse_world({"entities": {"world": {"markers": [{"id": 7, "size_m": SIZE, "pose": {}}]},
                                      "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]}}})  # fmt: skip
    # The renderer's lens is its model: the calibration states the residual a simulated camera's does.
    cal = Calibration(640, 480, K, dist, False, LENS_RESIDUAL_PX)
    det = Detector(world.sensors[1], world, cal, decimate=1.0, track=False)
    rng = np.random.default_rng(42)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    errs = []
    for k in range(n):
        distance, angle = rng.uniform(0.4, 3.0), rng.uniform(0.0, 70.0)
        rot = Rotation.from_euler("zxz", [rng.uniform(0, 360), 180 + angle, rng.uniform(0, 360)], degrees=True)
        uv = np.array([[[rng.uniform(20, 620), rng.uniform(20, 460)]]])
        xy = cv2.undistortPoints(uv, K, dist, None, None, criteria=crit).ravel()
        T = RigidTransform.from_components([xy[0] * distance, xy[1] * distance, distance], rot)
        blur = tuple(rng.uniform(0, 3, 2)) if rng.random() < 0.5 else (0.0, 0.0)
        img = render(cam, [MarkerView("tag36h11", 7, SIZE, T)], noise_sigma=3.0, blur_px=blur, seed=k,
                     background_style="concrete", background_seed=k % 7)  # fmt: skip
        for md in det.detect(img, k):
            if md.ambiguity_ratio > AMBIGUITY_THRESHOLD:  # both solutions go downstream
                continue
            w, x, y, z = md.q_sensor_marker_wxyz
            e = np.concatenate([T.translation - np.array(md.p_sensor_marker_m),
                                (Rotation.from_quat([x, y, z, w]).inv() * T.rotation).as_rotvec()])  # fmt: skip
            errs.append((e, upper_to_matrix(np.array(md.covariance))))
            if states is not None:
                edge = np.hypot(uv[0, 0, 0] - 319.5, uv[0, 0, 1] - 239.5) > 0.6 * 400.0
                states.append(f"{'blurred' if blur[0] else 'sharp'} {'edge' if edge else 'centre'}")
    nees3 = np.array([e[:3] @ np.linalg.solve(C[:3, :3], e[:3]) for e, C in errs])
    nees6 = np.array([e @ np.linalg.solve(C, e) for e, C in errs])
    flags = [np.abs(e) <= 3 * np.sqrt(np.diag(C)) for e, C in errs]
    if inside is not None:
        inside.extend(flags)
    return nees3, nees6, np.mean(flags, axis=0)


def stats(t: list[float]) -> str:
    if not t:
        return f"{'-':>7} {'-':>7} {'-':>7}"
    return f"{statistics.mean(t):>7.2f} {statistics.median(t):>7.2f} {np.percentile(t, 95):>7.2f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames per sequence")
    ap.add_argument("--covariance-frames", type=int, default=200, help="frames of the covariance check")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    lib1 = _library_detector("tag36h11", 1, 1.0)
    lib2 = _library_detector("tag36h11", 1, 2.0)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    aruco = cv2.aruco.ArucoDetector(opencv_dictionary("DICT_APRILTAG_36h11"), params)

    def library(det):
        def run(img):
            return [
                Detection(r.tag_id, "tag36h11", np.asarray(r.corners, float)[[3, 2, 1, 0]] - 0.5)
                for r in det.detect(img)
            ]

        return run

    def opencv(img):
        c, ids, _ = aruco.detectMarkers(img)
        # OpenCV's AprilTag bitmaps are the library's turned by 180 degrees: corner 0 is our BR.
        return (
            []
            if ids is None
            else [
                Detection(int(i), "tag36h11", np.asarray(cc, float).reshape(4, 2)[[2, 3, 0, 1]])
                for cc, i in zip(c, ids.ravel(), strict=True)
            ]
        )

    methods = {"library d1": library(lib1), "library d2": library(lib2), "opencv aruco": opencv}
    keys = (
        "hits",
        "false",
        "border",
        "flips",
        "ambiguous",
        "resolved",
        "swapped",
        "unresolved",
        "flips_unresolved_as_chosen",
        "flips_resolved",
    )
    names = [*methods, "atlas"]
    # Times per resolution and per state of our tracker (hunting / tracking), for every method on the same frames.
    times = {(r, st, m): [] for r in ("640x480", "1280x720") for st in ("hunting", "tracking") for m in names}
    totals = {m: {"errs": [], "n": 0, **dict.fromkeys(keys, 0)} for m in names}
    res_hits = {(r, m): 0 for r in ("640x480", "1280x720") for m in names}
    res_n = dict.fromkeys(("640x480", "1280x720"), 0)
    print(f"load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    rng = np.random.default_rng(0)
    for res in ((640, 480), (1280, 720)):
        rname = f"{res[0]}x{res[1]}"
        for name, K, cam, frames in sequences(*res, args.frames):
            markers = [{"id": i, "size_m": SIZE, "pose": {"pos": [float(i), 0, 0]}} for i in IDS]
            sensor = {"sensors": [{"name": "c", "id": 1, "pose": {}}]}
            world = parse_world({"entities": {"world": {"markers": markers}, "cam": sensor}})
            ours = Detector(
                world.sensors[1], world, Calibration(res[0], res[1], K, np.zeros(5)), decimate=2.0, track=True
            )
            runners = {**methods, "atlas": ours.find}
            hits = dict.fromkeys(runners, 0)
            for k, (img, views) in enumerate(frames):
                state = "tracking" if ours.tracking else "hunting"
                visible = in_view(cam, views)
                order = list(runners)
                order = order[k % len(order) :] + order[: k % len(order)]  # interleaved, in turn first
                for m in order:
                    t0 = time.perf_counter()
                    found = runners[m](img)
                    times[(rname, state, m)].append((time.perf_counter() - t0) * 1e3)
                    got = score(found, views, visible, K, rng if m == "atlas" else None)
                    tot = totals[m]
                    tot["errs"] += got["errs"]
                    for key in keys:
                        tot[key] += got[key]
                    tot["n"] += len(visible)
                    hits[m] += got["hits"]
                    res_hits[(rname, m)] += got["hits"]
                res_n[rname] += len(visible)
            print(f"{name:28s} hits " + "  ".join(f"{m}: {hits[m]}" for m in runners), flush=True)
    print()
    print(f"{'frames':20} {'method':14} {'mean':>7} {'median':>7} {'p95':>7}   (ms; ratio of means to library d2)")
    for (r, st, m), t in times.items():
        d2 = times[(r, st, "library d2")]
        ratio = statistics.mean(t) / statistics.mean(d2) if t and d2 else math.nan
        print(f"{r + ' ' + st:20} {m:14} {stats(t)}   {ratio:.2f} ({len(t)} frames)")
    print()
    print(f"load average at the end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(
        f"recall: hits over the markers whose four corners lie at least {BORDER_MARGIN_PX:g} px inside the "
        f"image, every method alike; border: detections of markers nearer the border or cut (not counted)"
    )
    print(
        f"{'method':14} {'recall':>7} {'640x480':>8} {'1280x720':>8} {'false ids':>9} {'border':>7} "
        f"{'err % med':>9} {'flips %':>8}"
    )
    for m, tot in totals.items():
        flip_pct = 100 * tot["flips"] / max(len(tot["errs"]), 1)
        per_res = " ".join(f"{res_hits[(r, m)] / max(n, 1):>8.3f}" for r, n in res_n.items())
        print(
            f"{m:14} {tot['hits'] / tot['n']:>7.3f} {per_res} {tot['false']:>9d} {tot['border']:>7d} "
            f"{statistics.median(tot['errs']):>9.3f} {flip_pct:>8.2f}"
        )
    a, d1 = totals["atlas"], totals["library d1"]
    recall_a, recall_1 = a["hits"] / a["n"], d1["hits"] / d1["n"]
    flips = 100 * a["flips"] / max(len(a["errs"]), 1)
    hits = max(a["hits"], 1)
    amb = max(a["ambiguous"], 1)
    print(
        f"atlas keeps {100 * a['ambiguous'] / hits:.1f} % of its detections as ambiguous (IPPE ratio > "
        f"{AMBIGUITY_THRESHOLD}) with both solutions; with an estimate "
        f"{math.degrees(ESTIMATE_ATTITUDE_SIGMA_RAD):.1f} deg / {100 * ESTIMATE_POS_M:.0f} cm off per axis the "
        f"listener resolves {100 * a['resolved'] / amb:.1f} % of them ({100 * a['swapped'] / amb:.1f} % to the "
        f"other solution) and rejects {100 * a['unresolved'] / amb:.1f} % as unresolved; flips among delivered "
        f"poses: {a['flips']} of {len(a['errs'])}"
    )
    err = statistics.median(a["errs"])
    states: list[str] = []
    inside: list[np.ndarray] = []
    nees3, nees6, within = covariance_check(args.covariance_frames, states, inside)
    print("single-marker covariance per state: NEES3 mean / median / p95, NEES6 mean / median / p95, within 3 "
          "sigma on the worst axis (chi-square: 3.00 2.37 7.81, 6.00 5.35 12.59, 0.997)")  # fmt: skip
    labels = np.array(states)
    flags = np.array(inside)
    for state in sorted(set(states)):
        m = labels == state
        cells = [f"{x[m].mean():6.2f} {np.median(x[m]):6.2f} {np.percentile(x[m], 95):6.2f}" for x in (nees3, nees6)]
        print(f"  {state:16} {int(m.sum()):>4} " + " ".join(cells) + f" {flags[m].mean(axis=0).min():6.3f}")
    print(
        f"single-marker covariance, 640x480 k1 -0.3, whole image, blur and noise, {len(nees3)} detections: "
        f"NEES3 mean {nees3.mean():.2f} median {np.median(nees3):.2f} (ideal 3, 2.37), NEES6 mean "
        f"{nees6.mean():.2f} median {np.median(nees6):.2f} (ideal 6, 5.35); within 3 sigma per axis "
        f"[dp x y z, dtheta x y z] {np.round(within, 3).tolist()} (ideal 0.997)"
    )
    for r in ("640x480", "1280x720"):
        mine = times[(r, "hunting", "atlas")] + times[(r, "tracking", "atlas")]
        d2 = times[(r, "hunting", "library d2")] + times[(r, "tracking", "library d2")]
        ratio = statistics.mean(mine) / statistics.mean(d2)
        print(f"BAR detector_mean_vs_library_d2_{r} {ratio:.2f} ratio 1.0 {'pass' if ratio <= 1.0 else 'fail'}")
    p95 = float(np.percentile(times[("640x480", "hunting", "atlas")] + times[("640x480", "tracking", "atlas")], 95))
    print(f"BAR detector_p95_640x480 {p95:.1f} ms 33 {'pass' if p95 <= 33 else 'fail'}")
    hunt = statistics.mean(times[("640x480", "hunting", "atlas")])
    hunt_d2 = statistics.mean(times[("640x480", "hunting", "library d2")])
    print(f"640x480 hunting mean {hunt:.1f} ms, {hunt / hunt_d2:.2f} x the library d2 ({hunt_d2:.1f} ms, same frames)")
    print(f"BAR detector_hunting_mean_640x480 {hunt:.1f} ms 15 {'pass' if hunt <= 15 else 'fail'}")
    verdict = "pass" if recall_a >= recall_1 else "fail"
    print(f"BAR detector_recall_minus_library_d1 {recall_a - recall_1:+.3f} fraction 0.0 {verdict}")
    print(f"BAR detector_false_ids {a['false']} count 0 {'pass' if a['false'] == 0 else 'fail'}")
    print(f"BAR detector_flips {flips:.2f} percent 1.0 {'pass' if flips <= 1.0 else 'fail'}")
    print(f"BAR detector_median_translation_error {err:.3f} percent_of_distance 0.5 {'pass' if err <= 0.5 else 'fail'}")
    w = float(within.min())
    print(f"BAR single_marker_within_3_sigma_worst_axis {w:.3f} fraction 0.99 {'pass' if w >= 0.99 else 'fail'}")
    m3, m6 = float(nees3.mean()), float(nees6.mean())
    # About their dimension: overconfidence (above) is the danger, a covariance far too large (below) wastes it.
    print(f"BAR single_marker_nees3_mean {m3:.2f} nees 1.5-4.5 {'pass' if 1.5 <= m3 <= 4.5 else 'fail'}")
    print(f"BAR single_marker_nees6_mean {m6:.2f} nees 3-9 {'pass' if 3.0 <= m6 <= 9.0 else 'fail'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

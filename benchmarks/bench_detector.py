"""Detector speed and accuracy on rendered frames with known truth, side by side with its anchors.

Sequences of frames (a marker drifting and turning slowly, as seen from a hovering drone) at several
distances, sharp and with blur and noise, at 640x480 and 1280x720, one core. Compared on the same
frames: the AprilTag 3 library at decimate 1 and 2, OpenCV's ArucoDetector (DICT_APRILTAG_36h11),
and ours (decimate 2 plus full-resolution regions where markers were or are small). Poses of every
method come from the same IPPE solve, so pose figures compare the corners.

    python benchmarks/bench_detector.py [--frames N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_onboard.config import parse_world
from atlas_onboard.detector import pose
from atlas_onboard.detector.backends import Detection, _library_detector
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.families import opencv_dictionary
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import Camera, MarkerView, render

SIZE = 0.15
IDS = (3, 11, 25)


def sequences(width: int, height: int, n: int):
    f = width * 0.78
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    cam = Camera(width, height, K, np.zeros(5))
    for distance in (0.7, 1.5, 3.0, 5.0):
        for variant, blur, noise in (("sharp", 0.0, 1.0), ("blur+noise", 2.5, 4.0)):
            frames = []
            for k in range(n):
                views = []
                for j, mid in enumerate(IDS):
                    x = (j - 1) * 0.45 * distance * width / 1280 + 0.02 * distance * np.sin(0.2 * k + j)
                    rot = Rotation.from_euler(
                        "xyz", [180 + 25 * np.sin(0.05 * k + j), 15 * j, 10 * k / n + 30 * j], degrees=True
                    )
                    views.append(
                        MarkerView(
                            "tag36h11", mid, SIZE, RigidTransform.from_components([x, 0.1 * distance, distance], rot)
                        )
                    )
                img = render(cam, views, seed=k, noise_sigma=noise, blur_px=(blur, 0.0), supersample=3)
                frames.append((img, views))
            yield f"{width}x{height} {distance} m {variant}", K, frames


def score(
    found: list[Detection], views: list[MarkerView], K: np.ndarray, max_ambiguity: float = 1.0
) -> tuple[int, int, list[float], int]:
    """Hits, false ids, translation errors (% of distance) and flips (> 10 deg) of the poses a method
    delivers; ours drops poses whose two IPPE solutions fit almost equally (``max_ambiguity``)."""
    truth = {v.marker_id: v for v in views}
    hits, false_ids, errs, flips = 0, 0, [], 0
    for d in found:
        v = truth.get(d.marker_id)
        if v is None:
            false_ids += 1
            continue
        hits += 1
        mp = pose.solve(d.corners_px, SIZE, K, 0.1)
        if mp is None or mp.ambiguity > max_ambiguity:
            continue
        dist = float(np.linalg.norm(v.T_camera_marker.translation))
        errs.append(float(np.linalg.norm(mp.p_m - v.T_camera_marker.translation)) / dist * 100)
        if np.degrees((Rotation.from_quat(mp.q_xyzw).inv() * v.T_camera_marker.rotation).magnitude()) > 10:
            flips += 1
    return hits, false_ids, errs, flips


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames per sequence")
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
    totals = {m: {"t": [], "hits": 0, "false": 0, "errs": [], "flips": 0, "n": 0} for m in [*methods, "atlas"]}
    for res in ((640, 480), (1280, 720)):
        for name, K, frames in sequences(*res, args.frames):
            markers = [{"id": i, "size_m": SIZE, "pose": {"pos": [float(i), 0, 0]}} for i in IDS]
            cam = {"sensors": [{"name": "c", "id": 1, "pose": {}}]}
            world = parse_world({"entities": {"world": {"markers": markers}, "cam": cam}})
            ours = Detector(
                world.sensors[1], world, Calibration(res[0], res[1], K, np.zeros(5)), decimate=2.0, track=True
            )
            runners = {**methods, "atlas": ours.find}
            for m, run in runners.items():
                for img, views in frames:
                    t0 = time.perf_counter()
                    found = run(img)
                    totals[m]["t"].append((time.perf_counter() - t0) * 1e3)
                    amb = ours.max_ambiguity if m == "atlas" else 1.0
                    hits, false_ids, errs, flips = score(found, views, K, amb)
                    tot = totals[m]
                    tot["hits"] += hits
                    tot["false"] += false_ids
                    tot["errs"] += errs
                    tot["flips"] += flips
                    tot["n"] += len(views)
            print(f"{name:28s} " + "  ".join(f"{m}: {totals[m]['hits']}" for m in runners), flush=True)
    print()
    print(
        f"{'method':14} {'ms median':>9} {'ms p95':>7} {'recall':>7} {'false ids':>9} {'err % med':>9} {'flips %':>8}"
    )
    for m, tot in totals.items():
        t = tot["t"]
        flip_pct = 100 * tot["flips"] / max(len(tot["errs"]), 1)
        print(
            f"{m:14} {statistics.median(t):>9.2f} {np.percentile(t, 95):>7.2f} {tot['hits'] / tot['n']:>7.3f} "
            f"{tot['false']:>9d} {statistics.median(tot['errs']):>9.3f} {flip_pct:>8.2f}"
        )
    a, d1, d2 = totals["atlas"], totals["library d1"], totals["library d2"]
    ratio = statistics.median(a["t"]) / statistics.median(d2["t"])
    recall_a, recall_1 = a["hits"] / a["n"], d1["hits"] / d1["n"]
    flips = 100 * a["flips"] / max(len(a["errs"]), 1)
    dropped = 100 * (1 - len(a["errs"]) / max(a["hits"], 1))
    print(f"atlas drops {dropped:.1f} % of its detections as ambiguous (IPPE ratio > 0.5)")
    err = statistics.median(a["errs"])
    print(f"BAR detector_time_vs_library_d2 {ratio:.2f} ratio 1.0 {'pass' if ratio <= 1.0 else 'fail'}")
    verdict = "pass" if recall_a >= recall_1 else "fail"
    print(f"BAR detector_recall_minus_library_d1 {recall_a - recall_1:+.3f} fraction 0.0 {verdict}")
    print(f"BAR detector_false_ids {a['false']} count 0 {'pass' if a['false'] == 0 else 'fail'}")
    print(f"BAR detector_flips {flips:.2f} percent 1.0 {'pass' if flips <= 1.0 else 'fail'}")
    print(f"BAR detector_median_translation_error {err:.3f} percent_of_distance 0.5 {'pass' if err <= 0.5 else 'fail'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

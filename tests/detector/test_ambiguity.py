"""The detector keeps ambiguous detections with both IPPE solutions, and one of them is the truth
(rendered images of a small tag far away and nearly face-on, where IPPE flips)."""

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.markerdata import AltState, MarkerData
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import Camera, MarkerView, render

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
CAM = Camera(1280, 720, K, np.zeros(5))
SIZE_M = 0.15
FLIP_DEG = 10.0


def detector() -> Detector:
    world = parse_world(
        {
            "entities": {
                "world": {"markers": [{"id": 7, "size_m": SIZE_M, "pose": {}}]},
                "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]},
            }
        }
    )
    return Detector(world.sensors[1], world, Calibration(1280, 720, K, np.zeros(5)), decimate=1.0, track=False)


def solutions(md: MarkerData) -> list[RigidTransform]:
    w, x, y, z = md.q_sensor_marker_wxyz
    wa, xa, ya, za = md.q_sensor_marker_alt_wxyz
    return [
        RigidTransform.from_components(md.p_sensor_marker_m, Rotation.from_quat([x, y, z, w])),
        RigidTransform.from_components(md.p_sensor_marker_alt_m, Rotation.from_quat([xa, ya, za, wa])),
    ]


def frames(n: int = 40):
    rng = np.random.default_rng(3)
    for k in range(n):
        tilt = rng.uniform(2.0, 8.0)  # near face-on: with corners placed by area, 8-12 degrees is rarely ambiguous
        rot = Rotation.from_euler("zxz", [rng.uniform(0, 360), 180 + tilt, rng.uniform(0, 360)], degrees=True)
        T = RigidTransform.from_components([rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), 5.0], rot)
        yield render(CAM, [MarkerView("tag36h11", 7, SIZE_M, T)], noise_sigma=4.0, seed=k), T


def test_ambiguous_detections_carry_both_solutions_and_one_is_the_truth():
    det = detector()
    ambiguous = flipped = 0
    for k, (img, T_true) in enumerate(frames()):
        for md in det.detect(img, capture_time_us=k):
            if not md.ambiguity_ratio > AMBIGUITY_THRESHOLD:
                continue
            ambiguous += 1
            assert md.alt_state() is AltState.VALID
            errs = [np.degrees((s.rotation.inv() * T_true.rotation).magnitude()) for s in solutions(md)]
            dist = [np.linalg.norm(s.translation - T_true.translation) for s in solutions(md)]
            best = int(np.argmin(errs))
            assert errs[best] < FLIP_DEG, f"frame {k}: neither solution within {FLIP_DEG} deg ({errs})"
            assert dist[best] < 0.02 * 5.0
            flipped += best == 1
    assert det.counters["ambiguous"] == ambiguous
    assert ambiguous >= 5 and flipped >= 1, f"{ambiguous} ambiguous detections, {flipped} with the flip chosen"

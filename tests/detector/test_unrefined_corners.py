"""A single full tag near the edge of a distorted image whose corners the edge
fit cannot refine was reported from the library's straight-line corners, centimetres off with a sigma
of about 2 mm. On rendered frames of the hard-near scenario (tags of ~70 px near the left border, barrel
distortion, blur): every reported detection must lie within 5 of its sigmas of the truth."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.camera import FrameRenderer

SC = scenarios.get("hard-near")
FRAMES = range(138, 143)  # marker 6 drifts to the left border; the edge fit fails on some of them


def _camera():
    """The hard-near drone's camera: its world, sensor, renderer and a fresh detector."""
    world = SC.world()
    sensor = world.sensors[1]
    render = FrameRenderer(SC, world, sensor, 0)
    intr = render.intr
    cal = intr.calibration()
    return world, sensor, render, Detector(sensor, world, cal, decimate=2.0)


@pytest.fixture(scope="module")
def detections():
    world, sensor, render, det = _camera()
    out = []
    for j in FRAMES:
        t = j / render.fps
        M_ws = render.sim.truth(t)["drone"].as_matrix() @ sensor.T_entity_sensor.as_matrix()
        for md in det.detect(render(j), round(t * 1e6)):
            M_sm = np.eye(4)
            w, x, y, z = md.q_sensor_marker_wxyz
            M_sm[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
            M_sm[:3, 3] = md.p_sensor_marker_m
            M_ws_det = world.markers[md.marker_id].T_entity_marker.as_matrix() @ np.linalg.inv(M_sm)
            out.append((j, md, float(np.linalg.norm(M_ws_det[:3, 3] - M_ws[:3, 3]))))
    return out, det


def test_no_detection_is_far_beyond_its_sigma_near_the_border(detections):
    out, det = detections
    assert len(out) >= 2, det.counters  # not vacuous: the tag was reported where the fit worked
    for j, md, err in out:
        assert err <= 5 * md.sigma_m, (
            f"frame {j}: marker {md.marker_id} {err * 1e3:.1f} mm off, sigma {md.sigma_m * 1e3:.1f}"
        )


def test_a_big_tag_bent_by_the_lens_is_refined_not_refused(detections):
    # Frames 140-142: marker 6, ~150 px wide near the top border, where the lens bends its sides by
    # 2-3 px; the refitted corners are that far from the library's (straight-side) ones and right.
    # A fixed 2 px limit on that move refused every one of them (refine_failed): no pose at all.
    out, det = detections
    seen = {j for j, md, _ in out if md.marker_id == 6}
    assert {140, 141, 142} <= seen, (sorted(seen), det.counters)


def test_a_failed_edge_fit_is_counted_and_explained():
    # Frame 494 of hard-near: marker 6 whose edge fit fails (with a fresh detector, as here).
    _, _, render, det = _camera()
    assert det.detect(render(494), 0) == []
    assert det.counters["refine_failed"] >= 1
    assert "corner refinement failed" in det.report.explain()

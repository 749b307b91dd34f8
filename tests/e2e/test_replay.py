"""End to end over 127.0.0.1: a node replaying an image folder every frame, faster than it can detect,
with the EKF, still sends poses to a simulated autopilot: late, stamped with their capture time, and
says that it is late."""

import os
from pathlib import Path

import numpy as np

from atlas_onboard.sim.autopilot import SimAutopilot
from tests.e2e.helpers import NodeProcess, wait_for, write_world
from tests.helpers import write_ubiquity_calibration

DATA = Path(__file__).resolve().parents[1] / "data"
FRAMES = 60
# fiducial_slam's expectation for 403.jpg: marker 403 at this position in base_link (m), the camera
# at this one. The drone's frame here is the camera's and the marker is at the world origin: the
# drone's distance from the origin is the camera's from the marker, whatever the rotations.
P_BASE_MARKER_M = np.array([0.7611, 0.2505, 0.4028])
P_BASE_CAMERA_M = np.array([0.035, 0.145, 0.14])


def test_every_frame_replay_that_falls_behind_with_the_ekf_keeps_sending(tmp_path):
    cal = write_ubiquity_calibration(tmp_path / "cal.yaml")
    # The same photo as 60 frames of a 1000 Hz file: no detector keeps up, the replay falls seconds behind.
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(FRAMES):
        os.link(DATA / "ubiquity" / "403.jpg", folder / f"frame{k:04d}.jpg")
    ap = SimAutopilot(system_id=1).start()
    doc = {
        "marker_family": "DICT_5X5_1000",
        "fusion": {"filter": "ekf"},
        "entities": {
            "world": {"markers": [{"id": 403, "size_m": 0.145, "pose": {}}]},
            "drone": {
                "sensors": [
                    {
                        "name": "cam", "id": 1, "pose": {},
                        "camera": {
                            "source": str(folder), "calibration": str(cal), "fps": 1000, "replay": "every_frame",
                        },
                    }
                ]
            },
        },
        "nodes": {"drone": {"system_id": 1, "autopilot": {"url": f"udpout:127.0.0.1:{ap.port}"}}},
    }  # fmt: skip
    node = NodeProcess(write_world(tmp_path, doc), "drone")
    try:
        assert wait_for(lambda: "end of" in node.log(), timeout=60), node.log()[-3000:]
        wait_for(lambda: False, timeout=0.5)  # the last frame's pose on its way
        code = node.stop()
        got = [m for m in ap.snapshot() if m.kind == "VISION_POSITION_ESTIMATE"]
        statustexts = list(ap.statustexts)
    finally:
        node.stop()
        ap.stop()
    assert code == 0
    counters = node.final_counters()
    ages_s = np.array([m.arrival_s - m.usec / 1e6 for m in got])
    # The replay fell far behind (each frame's stamp is its file time from the start of the replay)
    # and the poses kept going out all along: more than the autopilot can compensate, but not silent.
    late = ages_s > 1.5
    assert late.sum() >= 10, (len(got), ages_s)
    # A frame that comes late is not a gap to predict across: a pose predicted ahead of the frames
    # still to come would make each of them too old to send. (At most 30 Hz go out: the rate cap.)
    assert len(got) >= FRAMES // 4, (len(got), ages_s)
    # Every pose the autopilot received is the drone where the photo puts it (truth: fiducial_slam's
    # marker position), within 3 sigma of its own covariance (a prediction through a pause between
    # frames is less sure), and the median within 3 mm (fiducial_slam's pose is itself an estimate).
    truth_m = np.linalg.norm(P_BASE_MARKER_M - P_BASE_CAMERA_M)
    err = np.abs(np.linalg.norm(np.array([m.xyz_m for m in got]), axis=1) - truth_m)
    sigma = np.sqrt([max(m.covariance[0], m.covariance[6], m.covariance[11]) for m in got])
    assert np.all(err <= np.maximum(3 * sigma, 0.003)), (err, sigma)
    assert np.median(err) < 0.003, err
    assert counters["late_observations"] > 0 and counters["autopilot_sent"] == len(got)
    assert any(b"late" in t for t in statustexts), statustexts
    assert "late" in node.log()

"""The detect command on rendered images: what it prints when tags were found but none reported, and
when none were found."""

from __future__ import annotations

import cv2
import numpy as np

from tests.detector.scenes import DIST, SIZE, H, K, W, moved_marker_image


def test_detect_command_says_why_it_printed_nothing(tmp_path):
    import subprocess
    import sys

    import yaml

    cal = tmp_path / "cal.yaml"
    cal.write_text(yaml.safe_dump({
        "image_width": W, "image_height": H, "distortion_model": "plumb_bob",
        "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": DIST.tolist()},
    }))  # fmt: skip
    spots = {1: (0.0, 0.0), 5: (0.6, 0.0)}
    markers = [{"id": i, "size_m": SIZE, "pose": {"pos": [x + (0.1 if i == 5 else 0.0), y, 0.0]}}
               for i, (x, y) in spots.items()]  # fmt: skip
    sensor = {"name": "cam", "id": 1, "pose": {}, "camera": {"calibration": str(cal)}}
    (tmp_path / "w.yaml").write_text(yaml.safe_dump({"entities": {"world": {"markers": markers},
                                                                  "robot": {"sensors": [sensor]}}}))  # fmt: skip
    img, _ = moved_marker_image(spots)
    cv2.imwrite(str(tmp_path / "two.png"), img)
    cv2.imwrite(str(tmp_path / "none.png"), np.full((H, W), 128, np.uint8))

    def detect(name):
        cmd = [sys.executable, "-m", "atlas_onboard", "detect", "--config", str(tmp_path / "w.yaml"),
               "--sensor", "cam", "--image", str(tmp_path / name)]  # fmt: skip
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)

    two = detect("two.png")
    assert two.returncode == 0, two.stderr
    assert "2 tags found (ids 1, 5); none reported: " in two.stdout
    assert "markers 1 and 5 disagree by " in two.stdout
    none = detect("none.png")
    assert none.returncode == 0 and none.stdout.strip() == "frame 0: no tag found"

"""The detect and markers commands: the detector on a real photo and on rendered images (what it prints
when tags were found but none reported, and when none were found), and one SVG per configured marker."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from atlas_onboard.detector.families import family
from tests.detector.scenes import DIST, SIZE, H, K, W, moved_marker_image
from tests.helpers import write_ubiquity_calibration

DATA = Path(__file__).resolve().parents[1] / "data"
REPO = Path(__file__).resolve().parents[2]


def test_detect_command_says_why_it_printed_nothing(tmp_path):
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


def run_cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "atlas_onboard", *args], capture_output=True, text=True, timeout=60, check=False
    )


def test_detect_command_on_a_real_photo(tmp_path):
    cal = write_ubiquity_calibration(tmp_path / "cal.yaml")
    world = tmp_path / "w.yaml"
    world.write_text(
        yaml.safe_dump(
            {
                "marker_family": "DICT_5X5_1000",
                "entities": {
                    "world": {"markers": [{"id": 403, "size_m": 0.145, "pose": {}}]},
                    "robot": {"sensors": [{"name": "cam", "id": 1, "pose": {}, "camera": {"calibration": str(cal)}}]},
                },
            }
        )
    )
    proc = run_cli("detect", "--config", str(world), "--sensor", "cam", "--image", str(DATA / "ubiquity" / "403.jpg"),
                   "--json", "--annotate", str(tmp_path / "a.png"))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [r["marker_id"] for r in rows] == [403]
    # The source's own expectation (fiducial_slam's auto_init_403 test): marker 403 in base_link at
    # (0.7611, 0.2505, 0.4028) m, with the camera at base_link (x y z yaw pitch roll) below.
    cam = Rotation.from_euler("ZYX", [-1.479119, -0.041544, -1.204205])
    p_base = cam.apply(rows[0]["p_sensor_marker_m"]) + np.array([0.035, 0.145, 0.14])
    np.testing.assert_allclose(p_base, [0.7611, 0.2505, 0.4028], atol=0.002)
    assert (tmp_path / "a.png").stat().st_size > 1000
    bad = run_cli("detect", "--config", str(world), "--sensor", "cam", "--image", str(tmp_path / "missing.png"))
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "cannot read" in bad.stderr


def test_markers_command_writes_one_svg_per_marker_at_its_size(tmp_path, capsys):
    from atlas_onboard.cli import main
    from atlas_onboard.config import load_world

    config = REPO / "config" / "paper-test1.yaml"
    world = load_world(config)
    assert main(["markers", "--config", str(config), "--out", str(tmp_path / "print")]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == len(world.markers)
    for m in world.markers.values():
        svg = (tmp_path / "print" / f"{m.family}-{m.id}.svg").read_text()
        width_mm = float(re.search(r'width="([\d.]+)mm"', svg).group(1))
        cells = family(m.family).cells
        assert width_mm == pytest.approx(m.size_m * 1000 * (1 + 2 / cells), abs=1e-3)
        assert f"id {m.id}" in svg
    (tmp_path / "file").write_text("")
    assert main(["markers", "--config", str(config), "--out", str(tmp_path / "file" / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out: cannot create" in err[0], err

"""Calibration files: OpenCV FileStorage and ROS camera_info, pinhole and fisheye; bad files refused."""

import numpy as np
import pytest

from atlas_onboard.detector.calibration import Calibration, CalibrationError, load, write_opencv

K = np.array([[612.5, 0.0, 320.25], [0.0, 611.0, 239.75], [0.0, 0.0, 1.0]])
D = np.array([-0.11, 0.05, 0.001, -0.002, 0.0])

ROS = """image_width: 640
image_height: 480
camera_name: front
camera_matrix: {rows: 3, cols: 3, data: [612.5, 0, 320.25, 0, 611.0, 239.75, 0, 0, 1]}
distortion_model: DISTORTION
distortion_coefficients: {rows: 1, cols: N, data: COEFFS}
rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
projection_matrix: {rows: 3, cols: 4, data: [612.5, 0, 320.25, 0, 0, 611.0, 239.75, 0, 0, 0, 1, 0]}
"""


def test_opencv_round_trip(tmp_path):
    write_opencv(tmp_path / "c.yaml", Calibration(640, 480, K, D))
    cal = load(tmp_path / "c.yaml")
    np.testing.assert_allclose(cal.K, K)
    np.testing.assert_allclose(cal.dist, D)
    assert (cal.width_px, cal.height_px, cal.fisheye) == (640, 480, False)


@pytest.mark.parametrize(
    ("model", "coeffs", "fisheye"),
    [("plumb_bob", [-0.11, 0.05, 0.001, -0.002, 0.0], False), ("equidistant", [0.01, -0.02, 0.003, -0.001], True)],
)
def test_ros_camera_info(tmp_path, model, coeffs, fisheye):
    f = tmp_path / "c.yaml"
    f.write_text(ROS.replace("DISTORTION", model).replace("N", str(len(coeffs))).replace("COEFFS", str(coeffs)))
    cal = load(f)
    np.testing.assert_allclose(cal.K, K)
    np.testing.assert_allclose(cal.dist, coeffs)
    assert cal.fisheye is fisheye


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("%YAML:1.0\n---\nfoo: 1\n", "expected camera_matrix and distortion_coefficients"),
        (ROS.replace("612.5, 0, 320.25, 0, 611.0", "612.5, 0, 320.25, 0"), "camera_matrix"),
        (ROS.replace("DISTORTION", "kannala").replace("N", "4").replace("COEFFS", "[0, 0, 0, 0]"), "not supported"),
        (
            ROS.replace("DISTORTION", "equidistant").replace("N", "5").replace("COEFFS", "[0, 0, 0, 0, 0]"),
            "4 distortion",
        ),
        (
            ROS.replace("DISTORTION", "plumb_bob").replace("N", "3").replace("COEFFS", "[0, 0, 0]"),
            "distortion coefficients",
        ),
        (
            ROS.replace("320.25", "900.0")
            .replace("DISTORTION", "plumb_bob")
            .replace("N", "5")
            .replace("COEFFS", "[0,0,0,0,0]"),
            "principal point",
        ),
        ("[1, 2, 3]\n", "expected a mapping"),
        ("{{{", "not valid YAML"),
    ],
)
def test_malformed_calibration_is_one_line(tmp_path, text, words):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(CalibrationError) as info:
        load(f)
    assert words in str(info.value) and str(f) in str(info.value) and "\n" not in str(info.value)


def test_missing_calibration_file(tmp_path):
    with pytest.raises(CalibrationError, match="cannot read"):
        load(tmp_path / "nope.yaml")


def test_mismatched_image_size():
    with pytest.raises(CalibrationError, match="frames are 1280x720 but the calibration is for 640x480"):
        Calibration(640, 480, K, D).check_size(1280, 720, "sensor front")

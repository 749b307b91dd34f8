"""Calibration files: OpenCV FileStorage and ROS camera_info, pinhole and fisheye; bad files refused."""

import numpy as np
import pytest

from atlas_onboard.detector import calibration
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


KF = np.array([[285.0, 0.0, 424.5], [0.0, 285.3, 400.25], [0.0, 0.0, 1.0]])  # a T265-like fisheye
DF = np.array([-0.0076, 0.0459, -0.0435, 0.0083])


def test_opencv_fisheye_round_trip(tmp_path):
    write_opencv(tmp_path / "f.yaml", Calibration(848, 800, KF, DF, fisheye=True))
    cal = load(tmp_path / "f.yaml")
    np.testing.assert_allclose(cal.K, KF)
    np.testing.assert_allclose(cal.dist, DF)
    assert (cal.width_px, cal.height_px, cal.fisheye) == (848, 800, True)
    assert "equidistant" in (tmp_path / "f.yaml").read_text()


def test_an_opencv_fisheye_file_needs_four_coefficients(tmp_path):
    write_opencv(tmp_path / "f.yaml", Calibration(848, 800, KF, np.zeros(5), fisheye=False))
    text = (tmp_path / "f.yaml").read_text().replace("plumb_bob", "equidistant")
    (tmp_path / "f.yaml").write_text(text)
    with pytest.raises(CalibrationError, match="4 distortion coefficients"):
        load(tmp_path / "f.yaml")


@pytest.mark.parametrize("fisheye", [True, False])
def test_pose_through_the_lens_model_matches_truth(fisheye):
    """Corners projected through the real lens (fisheye or radial-tangential) far off the optical
    axis, where distortion is tens of pixels: undistorted, IPPE gives back the marker's true pose."""
    import cv2
    from scipy.spatial.transform import Rotation

    from atlas_onboard.detector import pose

    Kc, dist = (KF, DF) if fisheye else (K, D)
    size = 0.2
    rvec = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_rotvec()
    tvec = np.array([0.9, -0.6, 1.4])
    obj = pose.object_corners(size).reshape(-1, 1, 3)
    if fisheye:
        img, _ = cv2.fisheye.projectPoints(obj, rvec, tvec, Kc, dist)
        ideal, _ = cv2.projectPoints(obj, rvec, tvec, Kc, None)
    else:
        img, _ = cv2.projectPoints(obj, rvec, tvec, Kc, dist)
        ideal, _ = cv2.projectPoints(obj, rvec, tvec, Kc, None)
    img, ideal = img.reshape(-1, 2), ideal.reshape(-1, 2)
    assert np.abs(img - ideal).max() > 10.0  # the lens matters here
    und = pose.undistort(img, Kc, dist, fisheye)
    np.testing.assert_allclose(und, ideal, atol=1e-3)
    mp = pose.solve(und, size, Kc, 0.1)
    np.testing.assert_allclose(mp.p_m, tvec, atol=1e-6)
    assert (Rotation.from_quat(mp.q_xyzw).inv() * Rotation.from_rotvec(rvec)).magnitude() < 1e-6
    # Taken as a pinhole camera, the same corners give a pose centimetres off.
    wrong = pose.solve(img, size, Kc, 0.1)
    assert np.linalg.norm(wrong.p_m - tvec) > 0.01


def test_the_calibrations_own_residual_is_read_written_and_defaulted(tmp_path):
    """The RMS reprojection error a calibration states (OpenCV's avg_reprojection_error) is the lens
    residual the corners' covariance gets; a file without one (ROS camera_info has no field for it) gets
    the documented conservative default; a bad one is refused by name."""
    write_opencv(tmp_path / "c.yaml", Calibration(640, 480, K, D, False, 0.173))
    assert load(tmp_path / "c.yaml").lens_residual_px == 0.173
    write_opencv(tmp_path / "none.yaml", Calibration(640, 480, K, D))
    unstated = load(tmp_path / "none.yaml")
    assert unstated.reprojection_rms_px is None
    assert unstated.lens_residual_px == calibration.DEFAULT_REPROJECTION_RMS_PX > 0
    ros = ROS.replace("DISTORTION", "plumb_bob").replace("N", "5").replace("COEFFS", str(D.tolist()))
    (tmp_path / "ros.yaml").write_text(ros + f"{calibration.RMS_KEY}: 0.21\n")
    assert load(tmp_path / "ros.yaml").lens_residual_px == 0.21
    (tmp_path / "bad.yaml").write_text(ros + f"{calibration.RMS_KEY}: -1\n")
    with pytest.raises(CalibrationError, match=calibration.RMS_KEY):
        load(tmp_path / "bad.yaml")


def test_the_lens_residual_moves_the_corners_alike_in_their_covariance():
    """A calibration's residual is a shift of a marker's four corners alike (the model is smooth over a
    marker): it adds its square to the covariance of the corners' mean and nothing to their differences."""
    from atlas_onboard.detector import refine
    from tests.detector.synthetic import marker_image

    img, truth = marker_image(20.3, 25.6, 6.0)
    gray = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    Kp = np.array([[300.0, 0, 59.5], [0, 300.0, 59.5], [0, 0, 1]])
    exact = refine.refine_corners_undistorted(gray, truth + 0.3, Kp, np.zeros(5), False, 0.0)
    stated = refine.refine_corners_undistorted(gray, truth + 0.3, Kp, np.zeros(5), False, 0.25)
    added = stated.covariance - exact.covariance
    mean = np.tile(np.eye(2), 4).T / 4  # (8, 2): the corners' mean
    np.testing.assert_allclose(mean.T @ added @ mean, 0.25**2 * np.eye(2), rtol=1e-9)
    differences = np.kron(np.eye(4) - 0.25, np.eye(2))  # each corner less the mean
    np.testing.assert_allclose(differences @ added @ differences.T, 0.0, atol=1e-12)
    np.testing.assert_array_equal(stated.corners, exact.corners)

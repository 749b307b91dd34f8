"""Camera calibration files: OpenCV FileStorage YAML and ROS camera_info YAML, pinhole (plumb_bob,
k1 k2 p1 p2 [k3 ...]) and fisheye (equidistant, k1..k4). A malformed file is a one-line error."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from atlas_onboard.errors import AtlasError, read_failure

# The calibration's residual (px) assumed when its file does not state it (ROS camera_info has no field for
# it): a careful OpenCV calibration's RMS reprojection error is 0.1-0.3 px, the board's corner noise included.
DEFAULT_REPROJECTION_RMS_PX = 0.3
# Where a calibration file states its RMS reprojection error (px): OpenCV's calibration sample writes this key.
RMS_KEY = "avg_reprojection_error"


class CalibrationError(AtlasError):
    """A calibration file that cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class Calibration:
    width_px: int
    height_px: int
    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    fisheye: bool = False
    reprojection_rms_px: float | None = None  # the calibration's own residual, when its file states it

    @property
    def lens_residual_px(self) -> float:
        """How far (image px, RMS) the lens model may place a point from where the lens does: the
        calibration's RMS reprojection error when stated, else DEFAULT_REPROJECTION_RMS_PX."""
        rms = self.reprojection_rms_px
        return DEFAULT_REPROJECTION_RMS_PX if rms is None else rms

    def check_size(self, width_px: int, height_px: int, source: str) -> None:
        """Refuse frames of another size than the calibration's (a wrong file or a wrong mode)."""
        if self.width_px and (width_px, height_px) != (self.width_px, self.height_px):
            size = f"{self.width_px}x{self.height_px}"
            raise CalibrationError(f"{source}: frames are {width_px}x{height_px} but the calibration is for {size}")


def _matrix(value: object, shape: tuple[int, int], name: str, path: Path) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=float).reshape(shape)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: {name}: expected {shape[0]}x{shape[1]} numbers") from None
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{path}: {name}: expected finite numbers")
    return arr


def _validate(cal: Calibration, path: Path) -> Calibration:
    K = cal.K
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 or K[1, 0] or K[2, 0] or K[2, 1]:
        raise CalibrationError(f"{path}: camera_matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    if cal.width_px < 0 or cal.height_px < 0:
        raise CalibrationError(f"{path}: image size must not be negative")
    if cal.width_px and not (0 < K[0, 2] < cal.width_px and 0 < K[1, 2] < cal.height_px):
        raise CalibrationError(
            f"{path}: principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {cal.width_px}x{cal.height_px} image"
        )
    rms = cal.reprojection_rms_px
    if rms is not None and not (math.isfinite(rms) and rms >= 0):
        raise CalibrationError(f"{path}: {RMS_KEY}: expected a finite number >= 0, got {rms:g}")
    if cal.fisheye and cal.dist.size != 4:
        raise CalibrationError(f"{path}: fisheye (equidistant) needs 4 distortion coefficients, got {cal.dist.size}")
    if not cal.fisheye and cal.dist.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{path}: expected 4, 5, 8, 12 or 14 distortion coefficients, got {cal.dist.size}")
    return cal


def _load_ros(doc: dict, path: Path) -> Calibration:
    try:
        K = _matrix(doc["camera_matrix"]["data"], (3, 3), "camera_matrix", path)
        d = np.asarray(doc["distortion_coefficients"]["data"], dtype=float).ravel()
        model = str(doc.get("distortion_model", "plumb_bob"))
        w, h = int(doc.get("image_width", 0)), int(doc.get("image_height", 0))
        rms = None if doc.get(RMS_KEY) is None else float(doc[RMS_KEY])
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: not a valid camera_info file ({exc})") from None
    if model not in ("plumb_bob", "rational_polynomial", "equidistant", "fisheye"):
        raise CalibrationError(
            f"{path}: distortion_model {model!r} is not supported (plumb_bob, rational_polynomial, equidistant)"
        )
    return Calibration(w, h, K, d, fisheye=model in ("equidistant", "fisheye"), reprojection_rms_px=rms)


def _load_opencv(path: Path) -> Calibration:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise CalibrationError(f"{path}: cannot be read as an OpenCV FileStorage file")
        K = fs.getNode("camera_matrix").mat()
        d = fs.getNode("distortion_coefficients").mat()
        if K is None or d is None:
            raise CalibrationError(f"{path}: expected camera_matrix and distortion_coefficients")
        w = int(fs.getNode("image_width").real() or 0)
        h = int(fs.getNode("image_height").real() or 0)
        model = fs.getNode("distortion_model").string() or "plumb_bob"
        node = fs.getNode(RMS_KEY)
        rms = None if node.empty() else float(node.real())
    finally:
        fs.release()
    return Calibration(
        w,
        h,
        _matrix(K, (3, 3), "camera_matrix", path),
        np.asarray(d, float).ravel(),
        model in ("equidistant", "fisheye"),
        rms,
    )


def load(path: Path | str) -> Calibration:
    """A calibration from either format; CalibrationError names the file and what is wrong."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{p}: cannot read: {read_failure(exc)}") from None
    if text.lstrip().startswith("%YAML") or "!!opencv-matrix" in text:  # OpenCV writes %YAML:1.0 or 1.2
        cal = _load_opencv(p)
    else:
        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError:
            raise CalibrationError(f"{p}: not valid YAML") from None
        if not isinstance(doc, dict):
            raise CalibrationError(f"{p}: expected a mapping with camera_matrix and distortion_coefficients")
        cal = _load_ros(doc, p)
    return _validate(cal, p)


def write_opencv(path: Path, cal: Calibration) -> None:
    """Write an OpenCV FileStorage YAML calibration (what ``atlas-onboard calibrate`` produces)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", cal.width_px)
    fs.write("image_height", cal.height_px)
    fs.write("camera_matrix", cal.K)
    fs.write("distortion_coefficients", cal.dist.reshape(1, -1))
    fs.write("distortion_model", "equidistant" if cal.fisheye else "plumb_bob")
    if cal.reprojection_rms_px is not None:
        fs.write(RMS_KEY, float(cal.reprojection_rms_px))
    fs.release()

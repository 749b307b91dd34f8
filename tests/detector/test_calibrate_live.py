"""calibrate --device: views kept from a stream of rendered ChArUco frames (a fake camera): blurred,
moving and duplicate frames refused, coverage growing with each kept view, intrinsics recovered."""

import itertools
import os
import signal
import subprocess
import sys

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.detector.calibrate import board, calibrate
from atlas_onboard.detector.calibrate_live import Refusal, ViewSelector, collect_views
from atlas_onboard.detector.calibration import load as load_calibration

W, H = 640, 480
K_TRUE = np.array([[520.0, 0.0, 322.0], [0.0, 515.0, 236.0], [0.0, 0.0, 1.0]])
D_TRUE = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])
BLUR_SIGMA_PX = 1.4


def place(rvec, u_px, v_px, z_m):
    """The board's pose (rotation vector, origin in the camera frame, m) that puts its centre at
    pixel (u, v) at depth z."""
    R = Rotation.from_rotvec(rvec).as_matrix()
    centre = np.array([(u_px - K_TRUE[0, 2]) / K_TRUE[0, 0] * z_m, (v_px - K_TRUE[1, 2]) / K_TRUE[1, 1] * z_m, z_m])
    return np.asarray(rvec, float), centre - R @ np.array([0.14, 0.10, 0.0])


# What a user moving the board shows the camera: the centre and the four quarters of the image, the
# board facing the camera and tilted by about 29 degrees both ways (about x or y), then near and far.
POSES = [
    place(rvec, u, v, 0.45 if rvec == (0, 0, 0) else 0.5)
    for k, (u, v) in enumerate([(320, 240), (170, 120), (470, 120), (170, 360), (470, 360)])
    for rvec in ((0, 0, 0), (0.5, 0, 0) if k % 2 else (0, 0.5, 0), (-0.5, 0, 0.1) if k % 2 else (0, -0.5, -0.1))
] + [place((0, 0, 0), 320, 240, 0.3), place((0, 0, 0), 320, 240, 0.8)]


class Renderer:
    """The true camera (K_TRUE, D_TRUE) looking at the printed board from a pose."""

    def __init__(self, b):
        px = 100
        self.flat = b.generateImage((9 * px, 7 * px), marginSize=px)
        corners, ids, _, _ = cv2.aruco.CharucoDetector(b).detectBoard(self.flat)
        obj, img = b.matchImagePoints(corners, ids)
        self.H_flat_obj, _ = cv2.findHomography(obj.reshape(-1, 3)[:, :2], img.reshape(-1, 2))
        ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
        pts = np.stack([xs.ravel(), ys.ravel()], -1).reshape(-1, 1, 2)
        self.ideal = cv2.undistortPoints(pts, K_TRUE, D_TRUE, P=K_TRUE).reshape(H, W, 2)  # each pixel's pinhole point

    def __call__(self, rvec, tvec, blur=0.0, seed=0):
        R = Rotation.from_rotvec(rvec).as_matrix()
        H_cam_obj = K_TRUE @ np.column_stack([R[:, 0], R[:, 1], tvec])
        xy = cv2.perspectiveTransform(self.ideal, self.H_flat_obj @ np.linalg.inv(H_cam_obj))
        img = cv2.remap(self.flat, xy, None, cv2.INTER_LINEAR, borderValue=120)
        if blur:
            img = cv2.GaussianBlur(img, (0, 0), blur)
        cv2.setRNGSeed(seed)
        noise = np.empty(img.shape, np.int16)
        cv2.randn(noise, 0.0, 2.0)
        return np.clip(img + noise, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def b():
    return board(7, 5, 0.04, 0.03, "DICT_4X4_50")


@pytest.fixture(scope="module")
def stream(b):
    """Per pose: a frame on the way to it (moving), a blurred frame at it, then three sharp frames
    at it (the first still only if the blurred one showed the board; the last a duplicate of a kept
    one). Returns (frames, kind of each frame)."""
    render = Renderer(b)
    frames, kinds = [], []
    for k, (rvec, tvec) in enumerate(POSES):
        for kind, img in (
            ("moving", render(rvec + 0.03, tvec + 0.01, seed=5 * k)),
            ("blurred", render(rvec, tvec, blur=BLUR_SIGMA_PX, seed=5 * k + 1)),
            ("sharp", render(rvec, tvec, seed=5 * k + 2)),
            ("sharp", render(rvec, tvec, seed=5 * k + 3)),
            ("duplicate", render(rvec, tvec, seed=5 * k + 4)),
        ):
            frames.append(img)
            kinds.append(kind)
    return frames, kinds


def test_views_kept_only_sharp_still_and_new_and_coverage_grows(b, stream):
    frames, kinds = stream
    selector = ViewSelector(b)
    outcomes, coverage = [], []
    for img in frames:
        reason, _ = selector.offer(img)
        outcomes.append(reason)
        if reason is None:
            coverage.append(len(selector.coverage.cells) + len(selector.coverage.pose_bins))
    by_kind = {k: [o for o, kk in zip(outcomes, kinds, strict=True) if kk == k] for k in set(kinds)}
    assert all(o in (Refusal.BLURRED, Refusal.NO_BOARD) for o in by_kind["blurred"])
    assert by_kind["blurred"].count(Refusal.BLURRED) >= len(POSES) // 2  # found, and refused for blur
    assert all(o is not None for o in by_kind["moving"])
    assert by_kind["moving"].count(Refusal.MOVING) >= len(POSES) // 2
    assert all(o is Refusal.NOTHING_NEW for o in by_kind["duplicate"])
    assert by_kind["sharp"].count(None) == len(selector.kept)  # only sharp frames kept, one a pose at most
    assert len(selector.kept) <= len(POSES)
    assert len(selector.kept) >= len(POSES) - 2  # (nearly) every pose adds coverage
    assert all(b_ >= a for a, b_ in itertools.pairwise(coverage)) and coverage[-1] >= coverage[0] + 10
    assert selector.coverage.complete()

    cal, rms, used = calibrate(selector.kept, b)
    assert used == len(selector.kept) and rms < 0.5
    np.testing.assert_allclose([cal.K[0, 0], cal.K[1, 1]], [K_TRUE[0, 0], K_TRUE[1, 1]], rtol=0.01)
    np.testing.assert_allclose([cal.K[0, 2], cal.K[1, 2]], [K_TRUE[0, 2], K_TRUE[1, 2]], atol=4.0)
    assert abs(cal.dist[0] - D_TRUE[0]) < 0.03


def test_collect_stops_at_enough_views_and_reports(b, stream):
    lines = []
    selector = collect_views(iter(stream[0]), ViewSelector(b), views=5, report=lines.append)
    assert len(selector.kept) == 5
    assert sum(line.startswith("view ") for line in lines) == 5
    assert selector.frames < len(stream[0])  # it stopped once it had them


def test_calibrate_device_command_on_a_video_file(b, stream, tmp_path):
    """The CLI on a video file as the device: a calibration file close to the truth, and the coverage
    reported as it goes and at the end."""
    video = tmp_path / "camera.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 10, (W, H), False)
    assert writer.isOpened()
    for img in stream[0]:
        writer.write(img)
    writer.release()
    out = tmp_path / "cam.yaml"
    proc = subprocess.run(
        [sys.executable, "-m", "atlas_onboard", "calibrate", "--device", str(video), "--out", str(out)],
        check=False, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "view 1 kept" in proc.stdout and "coverage" in proc.stdout
    assert "refused" in proc.stdout and "blurred" in proc.stdout
    cal = load_calibration(out)
    np.testing.assert_allclose([cal.K[0, 0], cal.K[1, 1]], [K_TRUE[0, 0], K_TRUE[1, 1]], rtol=0.01)


def test_calibrate_device_that_cannot_be_opened_is_one_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "atlas_onboard", "calibrate", "--device", str(tmp_path / "none.avi"),
         "--out", str(tmp_path / "c.yaml")],
        check=False, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.realtime
def test_ctrl_c_ends_the_capture_and_calibrates_with_the_views_kept(b, stream, tmp_path):
    """Ctrl-C while the camera still delivers (here an image folder: the views, then a long stretch
    without the board): the command stops, calibrates with what it kept and writes the file (exit 0)."""
    folder = tmp_path / "camera"
    folder.mkdir()
    for k, img in enumerate(stream[0]):
        cv2.imwrite(str(folder / f"frame-{k:05d}.png"), img)
    blank = folder / f"frame-{len(stream[0]):05d}.png"
    cv2.imwrite(str(blank), np.full((H, W), 120, np.uint8))
    for k in range(len(stream[0]) + 1, len(stream[0]) + 3000):
        os.link(blank, folder / f"frame-{k:05d}.png")
    out = tmp_path / "cam.yaml"
    proc = subprocess.Popen(
        [sys.executable, "-m", "atlas_onboard", "calibrate", "--device", str(folder), "--out", str(out),
         "--views", "40", "--min-views", "40"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    kept = 0
    for line in proc.stdout:
        kept += line.startswith("view ")
        if kept >= len(POSES) - 2 or "frames: refused" in line:  # the views are in; blank frames follow
            break
    proc.send_signal(signal.SIGINT)
    rest, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "stopped (Ctrl-C)" in rest and "Traceback" not in err
    cal = load_calibration(out)
    np.testing.assert_allclose([cal.K[0, 0], cal.K[1, 1]], [K_TRUE[0, 0], K_TRUE[1, 1]], rtol=0.01)

"""ChArUco calibration recovers the intrinsics of a simulated camera from rendered views of the board."""

import subprocess
import sys

import cv2
import numpy as np

from atlas_onboard.detector.calibrate import board, calibrate

K_TRUE = np.array([[820.0, 0.0, 645.0], [0.0, 818.0, 355.0], [0.0, 0.0, 1.0]])
D_TRUE = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])


def views(b, n=12):
    """The printed board (as an image) seen by the true camera from n poses, with lens distortion."""
    px = 100
    board_img = b.generateImage((7 * px, 5 * px), marginSize=0)
    sq = b.getSquareLength()
    rng = np.random.default_rng(3)
    out = []
    h, w = 720, 1280
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    norm = cv2.undistortPoints(pts, K_TRUE, D_TRUE).reshape(h, w, 2)
    for _ in range(n):
        # The board faces the camera (rotation near identity keeps it unmirrored), tilted up to ~30 deg.
        rvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        z = rng.uniform(0.35, 0.6)
        tvec = np.array([-0.14 + rng.uniform(-0.15, 0.15) * z, -0.10 + rng.uniform(-0.1, 0.1) * z, z])
        R, _ = cv2.Rodrigues(rvec)
        # For each pixel, the ray hits the board plane (z = 0 in board coordinates): board x, y in metres.
        rays = np.concatenate([norm, np.ones((h, w, 1), np.float32)], axis=2) @ R  # R^T ray
        o = -R.T @ tvec
        lam = -o[2] / rays[..., 2]
        bx = o[0] + lam * rays[..., 0]
        by = o[1] + lam * rays[..., 1]
        # Board image: x right, y down from its top-left corner, px pixels a square.
        mx = (bx / sq * px - 0.5).astype(np.float32)
        my = (by / sq * px - 0.5).astype(np.float32)
        img = cv2.remap(board_img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=200)
        out.append(img)
    return out


def test_charuco_calibration_recovers_the_intrinsics():
    b = board(7, 5, 0.04, 0.03, "DICT_4X4_50")
    cal, rms, used = calibrate(views(b), b)
    assert used >= 8 and rms < 0.5
    np.testing.assert_allclose(np.diag(cal.K)[:2], np.diag(K_TRUE)[:2], rtol=0.01)
    np.testing.assert_allclose(cal.K[:2, 2], K_TRUE[:2, 2], atol=5.0)
    assert abs(cal.dist[0] - D_TRUE[0]) < 0.03


def test_calibrate_command_writes_a_board_and_refuses_too_few_views(tmp_path):
    run = [sys.executable, "-m", "atlas_onboard", "calibrate"]
    proc = subprocess.run([*run, "--board-image", str(tmp_path / "b.png")], capture_output=True, text=True, check=False)
    assert proc.returncode == 0 and cv2.imread(str(tmp_path / "b.png")) is not None
    (tmp_path / "views").mkdir()
    cv2.imwrite(str(tmp_path / "views" / "blank.png"), np.full((480, 640), 128, np.uint8))
    proc = subprocess.run([*run, "--images", str(tmp_path / "views"), "--out", str(tmp_path / "c.yaml")],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert proc.returncode == 2 and "found in 0 views" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1

"""The renderer's shortcuts are exact: blur restricted to the markers' regions equals blurring the
whole image there, the cached undistortion grid gives the image the direct computation gives, and
the analytic Jacobian of the camera-position sigma equals finite differences."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.detector import pose, render

K = np.array([[900.0, 0, 639.5], [0, 900.0, 359.5], [0, 0, 1]])
DIST = np.array([-0.05, 0.01, 0.001, -0.001, 0.0])
CAM = render.Camera(1280, 720, K, DIST)


def views(seed):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(4):
        T = RigidTransform.from_components(
            [rng.uniform(-1, 1), rng.uniform(-0.5, 0.5), rng.uniform(1.5, 3.0)],
            Rotation.from_euler("xyz", [180 + rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(0, 360)], True),
        )
        out.append(render.MarkerView("tag36h11", i, 0.18, T))
    return out


@pytest.mark.parametrize("blur", [(3.7, 0.5), (-0.8, -2.4), (1.2, 3.3)])
def test_blur_in_the_marker_regions_equals_blurring_the_whole_image(blur):
    vs = views(1)
    sharp = render.render(CAM, vs, supersample=2)
    got = render.render(CAM, vs, blur_px=blur, supersample=2)
    # The reference: the same kernel over the whole (unrounded) image, as the renderer did before.
    img = render.background(CAM)
    for v in sorted(vs, key=lambda v: -float(np.linalg.norm(v.T_camera_marker.translation))):
        render.draw_marker(img, CAM, v, 2)
    length = float(np.hypot(*blur))
    k = int(np.ceil(length)) * 2 + 1
    kernel = np.zeros((k, k), np.float32)
    for a in np.linspace(-0.5, 0.5, max(int(np.ceil(length * 4)), 2)):
        kernel[round(k // 2 + a * blur[1]), round(k // 2 + a * blur[0])] += 1.0
    ref = np.clip(np.rint(cv2.filter2D(img, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REPLICATE)), 0, 255)
    inside = np.zeros(sharp.shape, bool)
    for v in vs:
        box = render._marker_box(CAM, v)
        if box is not None:
            inside[box[1] : box[3] + 1, box[0] : box[2] + 1] = True
    assert inside.sum() > 10_000
    # Inside every marker's region the result is the whole-image blur (to float rounding).
    assert np.abs(got.astype(int) - ref.astype(int))[inside].max() <= 1
    # And the blur did something there.
    assert np.abs(got.astype(int) - sharp.astype(int))[inside].max() > 20


def test_cached_undistortion_grid_is_the_direct_undistortion():
    s = 3
    grid = render._undistorted_grid(CAM, s)
    rng = np.random.default_rng(2)
    rows = rng.integers(0, grid.shape[0] - 1, 50)
    cols = rng.integers(0, grid.shape[1] - 1, 50)
    px = np.stack([(cols * render.GRID_STEP + 0.5) / s - 0.5, (rows * render.GRID_STEP + 0.5) / s - 0.5], axis=-1)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
    direct = cv2.undistortPoints(px.reshape(-1, 1, 2), K, DIST, None, None, criteria=crit).reshape(-1, 2)
    np.testing.assert_allclose(grid[rows, cols], direct, atol=1e-12)
    # Projected again, each grid point lands on its sample's pixel position.
    back, _ = cv2.projectPoints(np.concatenate([direct, np.ones((50, 1))], 1), np.zeros(3), np.zeros(3), K, DIST)
    np.testing.assert_allclose(back.reshape(-1, 2), px, atol=1e-6)


def test_camera_position_sigma_jacobian_equals_finite_differences():
    rng = np.random.default_rng(3)
    for _ in range(50):
        rvec = rng.normal(size=3) * rng.uniform(0, 2)
        tvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0.5, 5)])
        obj = pose.object_corners(rng.uniform(0.05, 0.3))
        got = pose.camera_position_sigma(rvec, tvec, obj, K, 0.2, 0.1)
        # Reference: the same covariance, with dc/dx by central differences of c = -R^T t.
        _, J = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, None)
        cov = 0.2**2 * np.linalg.inv(J[:, :6].T @ J[:, :6])
        x0 = np.concatenate([rvec, tvec])

        def camera(x):
            return -Rotation.from_rotvec(x[:3]).inv().apply(x[3:])

        Jc = np.stack([(camera(x0 + d) - camera(x0 - d)) / 2e-6 for d in np.eye(6) * 1e-6], axis=1)
        ref = np.sqrt(np.linalg.eigvalsh(Jc @ cov @ Jc.T).max()) * np.sqrt(1 + (0.1 / 0.2) ** 2)
        assert got == pytest.approx(ref, rel=1e-6)


def test_concrete_background_has_the_edges_of_a_real_floor_and_keeps_the_tags_readable():
    """The concrete texture carries far more edge energy than the smooth one (joints, scuffs, speckle),
    is reproducible per seed, and a tag rendered over it is still found with its id."""
    from atlas_onboard.detector.backends import AprilTagBackend

    smooth = render.background(CAM, 3)
    concrete = render.background(CAM, 3, style="concrete")
    assert np.array_equal(concrete, render.concrete_texture(CAM.width_px, CAM.height_px, 3))
    assert not np.array_equal(concrete, render.concrete_texture(CAM.width_px, CAM.height_px, 4))

    def thin_dark_share(img):  # pixels well below their neighbourhood's median: joints, scuffs, cracks
        img = img.astype(np.uint8)
        return float(np.mean(img.astype(int) - cv2.medianBlur(img, 15) < -25))

    assert thin_dark_share(concrete) > 4.0 * thin_dark_share(smooth)
    assert 15.0 <= concrete.min() and concrete.max() <= 240.0
    view = render.MarkerView(
        "tag36h11", 7, 0.18, RigidTransform.from_components([0.1, 0.0, 2.0], Rotation.from_euler("x", 180, True))
    )
    img = render.render(CAM, [view], noise_sigma=2.0, background_style="concrete", background_seed=3)
    ids = [d.marker_id for d in AprilTagBackend(["tag36h11"]).detect(img)]
    assert ids == [7]
    with pytest.raises(ValueError, match="background style"):
        render.background(CAM, 3, style="marble")


def test_a_fisheye_calibration_is_refused_not_drawn_as_a_pinhole():
    """The renderer's camera is a calibration; it draws only the pinhole model, so a fisheye one is an error."""
    from atlas_onboard.detector.calibration import Calibration
    from atlas_onboard.errors import AtlasError

    fisheye = Calibration(1280, 720, K, np.array([0.1, 0.01, 0.0, 0.0]), fisheye=True)
    with pytest.raises(AtlasError, match="fisheye"):
        render.render(fisheye, views(0))
    assert render.render(CAM, views(0)).shape == (720, 1280)  # the same scene as a pinhole is drawn


# A rolling shutter: a camera panning and sliding sideways in front of a big marker, each row exposed at
# its own instant. The marker's left edge in each rendered row is where that row's own pose projects it.
RS_CAM = render.Camera(640, 480, np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]]), DIST)
RS_READOUT_S, RS_PAN, RS_SLIDE = 0.060, 1.0, 0.5  # s; rad/s about the camera's y axis; m/s along its x
RS_SIZE = 0.5
RS_WORLD_MARKER = RigidTransform.from_components([0.05, 0.0, 1.2], Rotation.from_euler("x", 180, degrees=True))


def _rs_camera_marker(t):
    """T_camera_marker at time t (s) of the moving camera (the world is its frame at t = 0)."""
    T_world_camera = RigidTransform.from_components([RS_SLIDE * t, 0.0, 0.0], Rotation.from_rotvec([0, RS_PAN * t, 0]))
    return T_world_camera.inv() * RS_WORLD_MARKER


def _rs_rows():
    times = (np.arange(RS_CAM.height_px) / (RS_CAM.height_px - 1) - 0.5) * RS_READOUT_S
    return np.stack([_rs_camera_marker(t).as_matrix() for t in times]), times


def _left_edge_at_row(T_camera_marker, row):
    """Pixel x where the marker's left edge (x = -size/2) crosses pixel row ``row`` under one pose."""
    from scipy.optimize import brentq

    def project(s):
        p = T_camera_marker.apply([-RS_SIZE / 2, s, 0.0])
        return render._project(RS_CAM, p[None, :])[0]

    s = brentq(lambda s: project(s)[1] - row, -RS_SIZE / 2, RS_SIZE / 2, xtol=1e-12)
    return project(s)[0]


def _measured_left_edge(img, row, start):
    """The sub-pixel x of the white-to-black step of the marker's quiet zone into its border in ``row``,
    searched from ``start`` (a pixel of the quiet zone, a cell wide): from the area the black covers in
    a window across the step (pixel k covers [k - 0.5, k + 0.5]), exact for an area-sampled step."""
    prof = img[row].astype(float)
    dark = start + int(np.argmax(prof[start:] < 60))  # a pixel inside the black border
    white, black = prof[dark - 8 : dark - 5].mean(), prof[dark + 3 : dark + 6].mean()
    window = prof[dark - 4 : dark + 3]
    return (dark + 2 + 0.5) - float(np.sum((white - window) / (white - black)))


def test_rolling_shutter_rows_are_drawn_with_their_own_pose():
    rows, _times = _rs_rows()
    view = render.MarkerView("tag36h11", 3, RS_SIZE, _rs_camera_marker(0.0), rows)
    img = render.render(RS_CAM, [view], supersample=3)
    box = render._marker_box(RS_CAM, view)
    errors, shear = [], []
    for row in range(box[1] + 40, box[3] - 40, 7):  # rows through the border, away from its corners
        truth = _left_edge_at_row(RigidTransform.from_matrix(rows[row]), row)
        errors.append(_measured_left_edge(img, row, int(truth) - 12) - truth)  # the quiet zone is ~20 px wide
        shear.append(_left_edge_at_row(_rs_camera_marker(0.0), row) - truth)  # where a global shutter draws it
    assert len(errors) >= 10
    assert np.abs(errors).max() < 0.02, np.round(errors, 3)
    assert np.abs(shear).max() > 2.0  # the motion during the readout moves the edge by pixels


def test_rolling_shutter_at_constant_pose_is_the_global_shutter_image():
    T = _rs_camera_marker(0.0)
    rows = np.tile(T.as_matrix(), (RS_CAM.height_px, 1, 1))
    still = render.render(RS_CAM, [render.MarkerView("tag36h11", 3, RS_SIZE, T)], supersample=3)
    rolled = render.render(RS_CAM, [render.MarkerView("tag36h11", 3, RS_SIZE, T, rows)], supersample=3)
    assert np.abs(still.astype(int) - rolled.astype(int)).max() <= 1  # the same image, to float rounding

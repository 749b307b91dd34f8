"""A moving camera's corners moved to the frame's stamp before the pose solve (:mod:`atlas_onboard.detector.motion`):
single poses within their sigma, and markers where the world file has them never disagree nor move."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import WORLD, CameraConfig, SensorConfig
from atlas_onboard.core.attitude import AttitudeHistory
from atlas_onboard.core.shutter import (
    GYRO_SIGMA_RAD_S,
    BodyRate,
    BodyVelocity,
    RowClock,
    timing_covariance,
    timing_pose_covariance,
)
from atlas_onboard.detector import pose
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.camera import CameraWorker
from atlas_onboard.detector.joint import JointSolve
from atlas_onboard.detector.motion import DEAD_RECKONING_ACCEL_M_S2, VISION_GRACE_US, CameraMotionModel, SeenSquare
from atlas_onboard.detector.pipeline import FrameReport
from atlas_onboard.detector.records import SingleSolve
from atlas_onboard.detector.sources import Frame
from atlas_onboard.detector.worldcheck import WorldCheck
from tests.detector.scenes import SIZE, H, K, W, moved_marker_world

READOUT_MS = 25.0
NOISE_PX = 0.05
IDS = [1, 2, 3, 5]


def rolling_corners(
    T_cam_marker: RigidTransform, size_m: float, omega: np.ndarray, v: np.ndarray, tau_s: float = 0.0
) -> np.ndarray:
    """A square's corners as a rolling shutter sees them (undistorted camera ``K``): each projected at its
    own row's instant, found by iterating ``t = dt(row(projection at t))``; the camera turns at ``omega``
    and moves at ``v`` (camera frame at the stamp, rad/s and m/s); the frame's true middle instant is
    ``tau_s`` after its stamp."""
    clock = RowClock(READOUT_MS * 1e-3, H)
    out = []
    for P in T_cam_marker.apply(pose.object_corners(size_m)):
        t = 0.0
        for _ in range(50):
            Pt = Rotation.from_rotvec(-omega * (t + tau_s)).apply(P - v * (t + tau_s))
            uv = (K @ Pt)[:2] / Pt[2]
            t_new = float(clock.dt_s(np.array([uv[1]]))[0])
            if abs(t_new - t) < 1e-12:
                break
            t = t_new
        out.append(uv)
    return np.array(out)


def _model(stamp_sigma_ms: float = 0.0) -> CameraMotionModel:
    camera = CameraConfig(readout_ms=READOUT_MS, stamp_sigma_ms=stamp_sigma_ms)
    return CameraMotionModel(camera, RigidTransform.identity(), H)


def _solve(
    img: np.ndarray, model: CameraMotionModel | None, rate: BodyRate | None, t_us: int = 0, v_known: bool = False
) -> SingleSolve:
    """The square's pose from its corners, moved to the stamp by ``model`` (None: left as they are);
    ``v_known``: the camera's velocity known to be zero within 0.05 m/s (else the model's own)."""
    cov = NOISE_PX**2 * np.eye(8)
    corners, motion_px = img, 0.0
    if model is not None:
        motion = model.at(t_us, rate)
        if v_known:
            motion = replace(motion, velocity=np.zeros(3), velocity_cov=0.05**2 * np.eye(3), velocity_known=True)
        moved = model.correct(motion, img, img, cov, K, SIZE)
        corners, cov, motion_px = moved.corners, moved.covariance, moved.shear_px
    mp = pose.solve(corners, SIZE, K, pose.SIGMA_PX_APRILTAG, None, float(np.sqrt(np.trace(cov) / 8)), cov)
    assert mp is not None and mp.covariance is not None
    if model is not None:  # the frame's timing, as the detector adds it to the frame's poses
        timing = timing_pose_covariance(mp.p_m, Rotation.from_quat(mp.q_xyzw).as_matrix(), motion)
        mp = replace(mp, covariance=mp.covariance + timing)
    return SingleSolve(mp, corners, None, float(np.sqrt(np.trace(cov) / 8)), cov, motion_px)


def _seen(T_world_marker: RigidTransform, img: np.ndarray) -> SeenSquare:
    """A square as found (no distortion), for the model's own motion history."""
    return SeenSquare(
        T_world_marker, img, img, NOISE_PX, NOISE_PX**2 * np.eye(8), None, SIZE, pose.SIGMA_PX_APRILTAG, K
    )


def _nees(mp: pose.MarkerPose, truth: RigidTransform) -> float:
    d = np.concatenate([mp.p_m - truth.translation, (truth.rotation.inv() * Rotation.from_quat(mp.q_xyzw)).as_rotvec()])
    return float(d @ np.linalg.solve(mp.covariance, d))


def _random_view(rng: np.random.Generator) -> RigidTransform:
    """A 15 cm tag 0.5-0.9 m ahead, tilted, in view."""
    R = Rotation.from_euler("xyz", rng.uniform(-0.4, 0.4, 3)) * Rotation.from_euler("x", np.pi)
    p = [rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), rng.uniform(0.5, 0.9)]
    return RigidTransform.from_components(p, R)


def test_single_poses_of_a_turning_camera_are_within_their_sigma() -> None:
    """Monte Carlo: a camera turning at up to 60 deg/s through a 25 ms readout, the autopilot's rate with
    noise and bias (its covariance said), the stamp off by its sigma (``stamp_sigma_ms`` 2), a small
    velocity, corner noise: the pose NEES (6 dof) has a mean no more than three standard errors above 6
    and above 3 (the solver's own chi-square scaling of a 2-dof fit keeps a still camera's near 5.4); the
    same frames left uncorrected are far outside theirs."""
    rng = np.random.default_rng(21)
    rate_sigma = np.radians(1.5)
    stamp_sigma = 2e-3
    nees, raw = [], []
    for _ in range(400):
        truth = _random_view(rng)
        omega = rng.uniform(-1.0, 1.0, 3)
        tau = rng.normal(0.0, stamp_sigma)
        v = rng.normal(0.0, 0.05, 3)  # the velocity known to be zero within 0.05 m/s
        img = rolling_corners(truth, SIZE, omega, v, tau) + rng.normal(0.0, NOISE_PX, (4, 2))
        measured = BodyRate(omega + rng.normal(0.0, rate_sigma, 3), rate_sigma**2 * np.eye(3))
        nees.append(_nees(_solve(img, _model(2.0), measured, v_known=True).pose, truth))
        raw.append(_nees(_solve(img, None, None).pose, truth))
    nees_a = np.array(nees)
    se = nees_a.std() / np.sqrt(len(nees_a))
    # Never over-confident; at most as conservative as the solver's own fit scaling makes a still camera.
    assert 3.0 < nees_a.mean() < 6.0 + 3.0 * se, (nees_a.mean(), se)
    assert np.mean(raw) > 30.0


def test_without_rates_the_sigma_covers_the_shear() -> None:
    """No rate from the autopilot nor from recent poses: the corners stay sheared and the rate bound's
    covariance covers what that does to the pose: >= 99 % of positions within 3 sigma on every axis."""
    rng = np.random.default_rng(4)
    bound = np.radians(30.0)
    inside = []
    for _ in range(400):
        truth = _random_view(rng)
        omega = rng.normal(0.0, bound, 3)
        v = rng.normal(0.0, 0.05, 3)  # the velocity known to be zero within 0.05 m/s
        img = rolling_corners(truth, SIZE, omega, v) + rng.normal(0.0, NOISE_PX, (4, 2))
        mp = _solve(img, _model(), None, v_known=True).pose
        sigma = np.sqrt(np.diag(mp.covariance)[:3])
        inside.append(np.abs(mp.p_m - truth.translation) <= 3.0 * sigma)
    assert np.mean(inside, axis=0).min() >= 0.99, np.mean(inside, axis=0)


def _joint_and_check(world) -> tuple[JointSolve, WorldCheck]:
    sensor = world.sensors[1]
    markers = [m for m in world.markers.values() if m.entity != sensor.entity]
    joint = JointSolve(
        sensor, world, Calibration(W, H, K, np.zeros(5)), {m.id: m.T_entity_marker for m in markers},
        {m.id: m.size_m for m in markers}, Counter(),
    )  # fmt: skip
    world_markers = {m: T for m, T in joint.marker_pose.items() if world.markers[m].entity == WORLD}
    return joint, WorldCheck(joint.sensor, joint.marker_pose, world_markers, joint.counters, joint)


def _fly(correct: bool) -> tuple[JointSolve, WorldCheck]:
    """Thirty frames of four correctly placed floor tags from a camera turning at 30-60 deg/s and moving
    at 0.5 m/s with a 25 ms rolling shutter, through the joint solve and the world check."""
    world, spots = moved_marker_world(None, 0.0)
    joint, check = _joint_and_check(world)
    model = _model()
    omega = np.radians([40.0, -30.0, 35.0])
    v = np.array([0.5, 0.1, 0.0])
    T_wc0 = RigidTransform.from_components(
        [-0.3, -0.2, 1.3], Rotation.from_euler("xyz", [200, 6, 4], degrees=True)
    ).inv()
    for k in range(30):
        t = k / 30.0
        # Frame k's camera: moved at v, turned along a slower path (the markers stay in view).
        R_wc = T_wc0.rotation * Rotation.from_rotvec(0.2 * omega * t)
        T_cam_world = RigidTransform.from_components(T_wc0.translation + T_wc0.rotation.apply(v * t), R_wc).inv()
        rng = np.random.default_rng(k)
        t_us = 1_000_000 + round(t * 1e6)
        rate = BodyRate(omega, np.radians(1.0) ** 2 * np.eye(3))
        singles, found = {}, {}
        for i, (x, y) in spots.items():
            T_cam_marker = T_cam_world * RigidTransform.from_translation([x, y, 0.0])
            img = rolling_corners(T_cam_marker, SIZE, omega, v) + rng.normal(0.0, NOISE_PX, (4, 2))
            singles[i] = _solve(img, model if correct else None, rate, t_us)
            found[i] = _seen(joint.marker_pose[i], img)
        ids = sorted(singles)
        check.gather_places(ids, singles, t_us)
        check.consistency_evidence(WORLD, ids, singles, t_us)
        check.offsets = {}
        result = joint.robust(ids, singles, t_us)
        check.take_joint(WORLD, ids, result, singles, t_us, FrameReport())
        assert result.used == IDS and result.md is not None, (k, result.used)
        check.check(WORLD, ids, t_us)
        if correct:
            model.observe(t_us, [found[i] for i in ids])
    return joint, check


def test_a_turning_rolling_shutter_camera_never_makes_a_correct_marker_disagree() -> None:
    joint, check = _fly(correct=True)
    assert not check.disagreements
    assert not check.moved
    assert joint.counters["joint_misfit"] == 0


def test_the_timing_pose_covariance_is_the_corners_timing_covariance_carried_through_the_solve() -> None:
    """The frame's timing moves every corner as the view an instant later: carried through the pose's
    generalised least squares it is the pose covariance added to the frame's poses (same convention)."""
    rng = np.random.default_rng(9)
    model = _model(3.0)
    for _ in range(20):
        truth = _random_view(rng)
        img = rolling_corners(truth, SIZE, np.zeros(3), np.zeros(3))
        motion = replace(
            model.at(0, BodyRate(rng.uniform(-1, 1, 3), 1e-4 * np.eye(3))),
            velocity=rng.uniform(-1, 1, 3), velocity_cov=0.01 * np.eye(3), velocity_known=True,
        )  # fmt: skip
        x = (img - K[:2, 2]) / K[0, 0]
        z = truth.apply(pose.object_corners(SIZE))[:, 2]
        fit = pose.CornerFit(truth.rotation.as_matrix(), truth.translation, pose.object_corners(SIZE), K)
        noise = 1e-4 * np.eye(8)
        C0 = pose.pose_covariance_from_corners(fit, noise)
        C1 = pose.pose_covariance_from_corners(fit, noise + timing_covariance(x, z, motion, K[0, 0], K[1, 1]))
        expected = timing_pose_covariance(truth.translation, truth.rotation.as_matrix(), motion)
        assert C0 is not None and C1 is not None
        np.testing.assert_allclose(C1 - C0, expected, atol=0.02 * np.abs(expected).max())


def test_a_travelling_camera_s_velocity_does_not_feed_on_itself() -> None:
    """A camera travelling at 0.5 m/s over one tag with a 25 ms rolling shutter, every other frame of a
    30 Hz camera detected (a node that falls behind), its velocity from its own recent poses: a velocity
    error shears the next corners, and a single square's pose moves far for a little shear; fed back into
    the next velocity fit, that loop grows. The velocity stays within 3 of its sigmas of the truth, the
    poses within 3 of theirs, and their sigma below what an unknown velocity (the speed bound) gives."""
    v = np.array([0.5, 0.2, 0.0])  # camera frame, m/s
    T_wm = RigidTransform.from_translation([0.1, -0.05, 0.0])  # on the floor, facing up
    down = Rotation.from_euler("x", 180, degrees=True)
    model, bound = _model(), _model()
    rate = BodyRate(np.zeros(3), GYRO_SIGMA_RAD_S**2 * np.eye(3))
    rng = np.random.default_rng(7)
    v_inside, p_inside, below = [], [], []
    for k in range(0, 80, 2):
        t = k / 30.0
        # Looking down from 0.8 m, moving along its own axes.
        T_world_cam = RigidTransform.from_components([-0.1, 0.05, 0.8], down) * RigidTransform.from_translation(v * t)
        truth = T_world_cam.inv() * T_wm
        img = rolling_corners(truth, SIZE, np.zeros(3), v) + rng.normal(0.0, NOISE_PX, (4, 2))
        t_us = 1_000_000 + round(t * 1e6)
        motion = model.at(t_us, rate)
        solved = _solve(img, model, rate, t_us)
        model.observe(t_us, [_seen(T_wm, img)])
        if k < 10:
            continue
        assert motion.velocity_known
        v_inside.append(np.all(np.abs(motion.velocity - v) <= 3.0 * np.sqrt(np.diag(motion.velocity_cov))))
        sd = np.sqrt(np.diag(solved.pose.covariance)[:3])
        p_inside.append(np.all(np.abs(solved.pose.p_m - truth.translation) <= 3.0 * sd))
        below.append(solved.pose.sigma_m < _solve(img, bound, rate, t_us).pose.sigma_m)  # bound: never observes
    assert np.mean(v_inside) >= 0.95 and np.mean(p_inside) >= 0.95 and all(below), (v_inside, p_inside, below)


class _Recorder:
    """A detector that keeps the body rate each frame was handed."""

    def __init__(self) -> None:
        self.sensor = SensorConfig(name="front", id=1, entity="drone", T_entity_sensor=RigidTransform.identity())
        self.rates: list[BodyRate | None] = []

    def detect(self, gray: np.ndarray, t_us: int, R_prev_now: object = None, body_rate: BodyRate | None = None,
               body_velocity: object = None) -> list:  # fmt: skip
        self.rates.append(body_rate)
        return []


def test_a_camera_with_attitudes_but_no_gyro_rates_is_never_handed_a_wrong_rate() -> None:
    """An autopilot that streams its attitude (25 Hz, each 15 ms late, 0.5 deg of noise on roll and pitch)
    but no gyro rates, the body turning at 0.5 rad/s: each frame's detector gets, at the frame's stamp
    (before the attitudes after it have come), either no rate (the image left as it is, the shear bounded)
    or one within 3 sigma of the truth on every axis."""
    rng = np.random.default_rng(5)
    omega = np.array([0.3, -0.2, 0.5])
    history = AttitudeHistory()
    recorder = _Recorder()
    worker = CameraWorker("front", CameraConfig(), recorder)
    worker.attitude_at = history.attitude_at
    truths = []
    for k in range(100):
        t_s = k * 0.04
        noise = Rotation.from_rotvec(np.r_[rng.normal(0.0, np.radians(0.5), 2), 0.0])
        history.add(round((t_s + 0.015) * 1e6), Rotation.from_rotvec(omega * t_s) * noise)
        stamp_us = round((t_s + 0.015 + rng.uniform(0.0, 0.04)) * 1e6)
        worker._detect(Frame(np.zeros((8, 8), np.uint8), stamp_us), lambda found: None)
        truths.append(omega)
    for rate, truth in zip(recorder.rates, truths, strict=True):
        if rate is not None:
            assert np.all(np.abs(rate.omega_flu - truth) <= 3.0 * np.sqrt(np.diag(rate.cov))), rate
    assert len(recorder.rates) == 100


def test_a_camera_seen_again_after_a_short_gap_keeps_its_velocity_with_its_age_in_the_covariance() -> None:
    """The camera's last two poses 170-240 ms before a frame (frames missed, the marker out of view
    meanwhile), travelling at 0.4 m/s: the velocity is still known from them, within 3 sigma of the truth,
    and less certain than a velocity from poses just before the frame."""
    v = np.array([0.4, -0.1, 0.05])
    T_wm = RigidTransform.from_translation([0.05, 0.0, 0.0])
    down = Rotation.from_euler("x", 180, degrees=True)
    rng = np.random.default_rng(11)

    def seen_at(t: float) -> SeenSquare:
        T_world_cam = RigidTransform.from_components([0.0, 0.0, 0.7], down) * RigidTransform.from_translation(v * t)
        img = rolling_corners(T_world_cam.inv() * T_wm, SIZE, np.zeros(3), v) + rng.normal(0.0, NOISE_PX, (4, 2))
        return _seen(T_wm, img)

    rate = BodyRate(np.zeros(3), GYRO_SIGMA_RAD_S**2 * np.eye(3))
    late, fresh = _model(), _model()
    for t in (0.0, 1 / 30, 2 / 30):
        late.observe(1_000_000 + round(t * 1e6), [seen_at(t)])
    for t in (0.17, 0.17 + 1 / 30, 0.17 + 2 / 30):
        fresh.observe(1_000_000 + round(t * 1e6), [seen_at(t)])
    at_us = 1_000_000 + round(0.3 * 1e6)
    gap, near = late.at(at_us, rate), fresh.at(at_us, rate)
    assert gap.velocity_known and near.velocity_known
    assert np.all(np.abs(gap.velocity - v) <= 3.0 * np.sqrt(np.diag(gap.velocity_cov)))
    assert gap.velocity_cov[0, 0] > near.velocity_cov[0, 0]


def test_a_frames_squares_corrected_together_are_each_corrected_alone_and_land_on_the_truth() -> None:
    """Several squares of one rolling-shutter frame, the camera turning and moving (rate and velocity
    known), corrected in one call: each square's corners, covariance and shear as the square corrected on
    its own, and its corners where the camera saw them at the stamp (the truth) far within the noise."""
    rng = np.random.default_rng(8)
    model = _model()
    omega, v = np.radians([25.0, -40.0, 15.0]), np.array([0.3, -0.2, 0.1])
    motion = replace(
        model.at(0, None), omega=omega, omega_cov=np.zeros((3, 3)), omega_known=True,
        velocity=v, velocity_cov=0.01**2 * np.eye(3), velocity_known=True,
    )  # fmt: skip
    views = [_random_view(rng) for _ in range(6)]
    seen = [rolling_corners(T, SIZE, omega, v) for T in views]
    truth = [(K @ T.apply(pose.object_corners(SIZE)).T).T for T in views]
    covs = [NOISE_PX**2 * (1.0 + k) * np.eye(8) for k in range(len(views))]
    together = model.correct_all(motion, seen, seen, covs, K, [SIZE] * len(views))
    assert len(together) == len(views)
    for img, cov, P, moved in zip(seen, covs, truth, together, strict=True):
        alone = model.correct(motion, img, img, cov, K, SIZE)
        assert np.allclose(moved.corners, alone.corners, rtol=0.0, atol=1e-9)
        assert np.allclose(moved.covariance, alone.covariance, rtol=1e-12, atol=0.0)
        assert moved.shear_px == pytest.approx(alone.shear_px, rel=1e-12)
        assert moved.shear_px > 0.0
        assert np.abs(moved.corners - P[:, :2] / P[:, 2:]).max() < 0.2 * NOISE_PX
        assert np.abs(img - P[:, :2] / P[:, 2:]).max() > 10 * NOISE_PX  # the shutter moved them far


def test_a_global_shutter_frames_squares_are_left_as_they_are() -> None:
    """A frame read at one instant: every square's corners where they were found (to rounding), its
    covariance unchanged, no shear, whatever the camera's motion."""
    rng = np.random.default_rng(9)
    model = CameraMotionModel(CameraConfig(readout_ms=0.0), RigidTransform.identity(), H)
    motion = replace(
        model.at(0, None), omega=np.radians([30.0, 10.0, -20.0]), omega_cov=0.1 * np.eye(3), omega_known=True,
        velocity=np.array([0.5, 0.0, 0.2]), velocity_cov=0.1 * np.eye(3), velocity_known=True,
    )  # fmt: skip
    views = [_random_view(rng) for _ in range(4)]
    imgs = [(K @ T.apply(pose.object_corners(SIZE)).T).T for T in views]
    imgs = [P[:, :2] / P[:, 2:] for P in imgs]
    covs = [NOISE_PX**2 * (1.0 + k) * np.eye(8) for k in range(len(views))]
    for img, cov, moved in zip(imgs, covs, model.correct_all(motion, imgs, imgs, covs, K, [SIZE] * 4), strict=True):
        assert np.allclose(moved.corners, img, rtol=0.0, atol=1e-9)
        assert np.array_equal(moved.covariance, cov)
        assert moved.shear_px == 0.0


MOUNT = RigidTransform.from_components([0.10, 0.0, -0.03], Rotation.from_euler("xyz", [-90.0, 0.0, -90.0], degrees=True)
                                       * Rotation.from_euler("x", 65.0, degrees=True))  # fmt: skip


def _camera_velocity_truth(v_body: np.ndarray, w_body: np.ndarray, dt: float = 1e-6) -> np.ndarray:
    """The camera's velocity in its own axes, differentiated from the body's rigid motion (body at the origin
    with identity attitude at t = 0, moving at ``v_body`` and turning at ``w_body`` in its own axes)."""

    def p_world_camera(t: float) -> np.ndarray:
        return v_body * t + Rotation.from_rotvec(w_body * t).apply(MOUNT.translation)

    v_world = (p_world_camera(dt) - p_world_camera(-dt)) / (2 * dt)
    return MOUNT.rotation.inv().apply(v_world)


def test_the_autopilots_velocity_is_a_rolling_cameras_velocity_prior() -> None:
    """With no poses of its own yet (the first frame after a gap), a rolling-shutter camera takes the
    autopilot's velocity: the body's, swung over the mount's lever arm by the rate, in the camera's axes,
    its covariance turned likewise."""
    model = CameraMotionModel(CameraConfig(readout_ms=READOUT_MS), MOUNT, H)
    v_body, w_body = np.array([0.5, -0.2, 0.1]), np.array([0.2, -0.1, 0.8])
    rate = BodyRate(w_body, 0.01**2 * np.eye(3))
    velocity = BodyVelocity(v_body, np.diag([0.05, 0.04, 0.03]) ** 2)
    motion = model.at(1_000_000, rate, velocity)
    assert motion.velocity_known
    np.testing.assert_allclose(motion.velocity, _camera_velocity_truth(v_body, w_body), atol=1e-6)
    M = MOUNT.rotation.inv().as_matrix()
    added = motion.velocity_cov - M @ velocity.cov @ M.T  # the rate's error swung over the lever arm
    assert np.linalg.eigvalsh(added).min() > -1e-15
    assert np.trace(added) == pytest.approx(2.0 * 0.01**2 * float(MOUNT.translation @ MOUNT.translation))
    without = model.at(1_000_000, rate)
    assert not without.velocity_known  # nothing else to correct by: bounds only
    no_rate = model.at(1_000_000, None, velocity)  # the turn unknown: its bound's swing is an error
    np.testing.assert_allclose(no_rate.velocity, M @ v_body, atol=1e-12)
    bound = no_rate.omega_second_moment()
    swing = np.trace(bound) * float(MOUNT.translation @ MOUNT.translation) - float(
        MOUNT.rotation.inv().apply(MOUNT.translation) @ bound @ MOUNT.rotation.inv().apply(MOUNT.translation)
    )  # trace of [p]x S [p]x^T
    assert np.trace(no_rate.velocity_cov - M @ velocity.cov @ M.T) == pytest.approx(swing)


def test_the_autopilots_velocity_is_less_certain_after_a_gap_in_the_markers() -> None:
    """The autopilot dead-reckons while the camera sees no world marker: its velocity, taken 1.2 s after the
    camera's last marker, is less certain than the same velocity a frame after it, by the drift's rate over
    the gap beyond what an EKF bridges."""
    T_wm = RigidTransform.from_translation([0.05, 0.0, 0.0])
    T_world_cam = RigidTransform.from_components([0.0, 0.0, 0.7], Rotation.from_euler("x", 180, degrees=True))
    img = rolling_corners(T_world_cam.inv() * T_wm, SIZE, np.zeros(3), np.zeros(3))
    velocity = BodyVelocity(np.array([0.3, 0.0, 0.0]), 0.05**2 * np.eye(3))
    model = _model()
    model.observe(1_000_000, [_seen(T_wm, img)])
    after_frame = model.at(1_033_000, None, velocity)
    after_gap = model.at(2_200_000, None, velocity)
    grown = (DEAD_RECKONING_ACCEL_M_S2 * (1.2 - VISION_GRACE_US * 1e-6)) ** 2
    np.testing.assert_allclose(after_gap.velocity_cov - after_frame.velocity_cov, grown * np.eye(3), atol=1e-15)


def test_a_global_shutter_leaves_the_autopilots_velocity_unused() -> None:
    """A frame read at one instant needs no velocity to move its corners: its motion is the same with or
    without the autopilot's (the history's or the bounds, as before)."""
    model = CameraMotionModel(CameraConfig(readout_ms=0.0, exposure_ms=8.0), MOUNT, H)
    rate = BodyRate(np.array([0.1, 0.0, 0.3]), 0.01**2 * np.eye(3))
    with_v = model.at(1_000_000, rate, BodyVelocity(np.array([0.5, 0.0, 0.0]), 0.05**2 * np.eye(3)))
    without = model.at(1_000_000, rate)
    for name in ("omega", "omega_cov", "velocity", "velocity_cov"):
        assert np.array_equal(getattr(with_v, name), getattr(without, name))
    assert (with_v.velocity_known, with_v.timing_sigma_s) == (without.velocity_known, without.timing_sigma_s)


def test_a_frame_s_own_pose_of_a_square_whose_corners_stayed_is_the_history_s() -> None:
    """A camera travelling at 0.4 m/s over one tag, its squares' corners with noise, each handed with the
    detector's pose of its corners (here the exact pose, solved from the noise-free corners): a global
    shutter moved no corner, so that pose is the camera's history and its velocity is the truth (to the
    solver's convergence); a moving rolling shutter's corners were moved, so the history solves the corners as found
    (open loop): its velocity within 3 sigma of the truth, not exact."""
    v = np.array([0.4, -0.1, 0.05])
    T_wm = RigidTransform.from_translation([0.05, 0.0, 0.0])
    down = Rotation.from_euler("x", 180, degrees=True)
    rate = BodyRate(np.zeros(3), GYRO_SIGMA_RAD_S**2 * np.eye(3))
    rng = np.random.default_rng(12)
    global_shutter = CameraMotionModel(CameraConfig(readout_ms=0.0), RigidTransform.identity(), H)
    rolling = _model()
    for model, readout_s, given_rate in ((global_shutter, 0.0, None), (rolling, READOUT_MS * 1e-3, rate)):
        for k in range(5):
            t = k / 30.0
            T_world_cam = RigidTransform.from_components([0.0, 0.0, 0.7], down) * RigidTransform.from_translation(v * t)
            truth = T_world_cam.inv() * T_wm
            exact = rolling_corners(truth, SIZE, np.zeros(3), v) if readout_s else None
            if exact is None:
                P = truth.apply(pose.object_corners(SIZE)) @ K.T
                exact = P[:, :2] / P[:, 2:]
            solved = pose.solve(exact, SIZE, K, pose.SIGMA_PX_APRILTAG, None, NOISE_PX, NOISE_PX**2 * np.eye(8))
            t_us = 1_000_000 + round(t * 1e6)
            seen = replace(_seen(T_wm, exact + rng.normal(0.0, NOISE_PX, (4, 2))), solved=solved)
            model.observe(t_us, [seen], model.at(t_us, given_rate))
        motion = model.at(1_000_000 + round(5 / 30.0 * 1e6), given_rate)
        assert motion.velocity_known
        error = np.abs(motion.velocity - v)
        if model is global_shutter:
            assert np.all(error < 1e-5), error  # the solver's convergence; the noise moves it by 1e-3
        else:
            assert np.all(error <= 3.0 * np.sqrt(np.diag(motion.velocity_cov))) and np.any(error > 1e-4), error

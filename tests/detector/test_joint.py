"""The joint solve as a collaborator of its own (:class:`JointSolve`): made from the detector's parts, it
solves an entity's squares without a detector, and its leave-one-out leaves out the marker that the world
file misplaces, telling the world check by how much."""

from __future__ import annotations

from collections import Counter

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import WORLD
from atlas_onboard.detector import pose
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.joint import JointSolve, entity_in_camera
from atlas_onboard.detector.records import FrameReport, SingleSolve
from atlas_onboard.detector.worldcheck import WorldCheck
from tests.detector.scenes import SIZE, H, K, W, moved_marker_world

T_CAM_WORLD = RigidTransform.from_components([-0.3, -0.2, 1.6], Rotation.from_euler("xyz", [200, 6, 4], degrees=True))
IDS = [1, 2, 3, 5]


def _singles(spots: dict[int, tuple[float, float]], noise_px: float, seed: int) -> dict[int, SingleSolve]:
    """Each square's own solve from its true corners (an undistorted camera) with corner noise."""
    rng = np.random.default_rng(seed)
    out = {}
    for i, (x, y) in spots.items():
        P = (T_CAM_WORLD * RigidTransform.from_translation([x, y, 0.0])).apply(pose.object_corners(SIZE))
        img = (P @ K.T)[:, :2] / P[:, 2:] + rng.normal(0.0, noise_px, (4, 2))
        mp = pose.solve(img, SIZE, K, pose.SIGMA_PX_APRILTAG)
        assert mp is not None
        out[i] = SingleSolve(mp, img, None, 0.0)
    return out


def _joint_solve(world) -> JointSolve:
    sensor = world.sensors[1]
    markers = [m for m in world.markers.values() if m.entity != sensor.entity]
    return JointSolve(
        sensor, world, Calibration(W, H, K, np.zeros(5)), {m.id: m.T_entity_marker for m in markers},
        {m.id: m.size_m for m in markers}, Counter(),
    )  # fmt: skip


def test_the_joint_solve_alone_places_the_anchor_marker_at_the_truth():
    world, spots = moved_marker_world(None, 0.0)
    joint = _joint_solve(world)
    md, misfit = joint.solve(IDS, _singles(spots, 0.05, seed=1), 1_000_000)
    assert not misfit and md is not None and md.marker_id == 1
    # Marker 1 sits at the world's origin: its pose in the camera is T_cam_world's.
    np.testing.assert_allclose(md.p_sensor_marker_m, T_CAM_WORLD.translation, atol=0.002)
    w, x, y, z = md.q_sensor_marker_wxyz
    assert (Rotation.from_quat([x, y, z, w]).inv() * T_CAM_WORLD.rotation).magnitude() < np.radians(0.2)
    assert joint.counters == Counter(joint=1) and md.covariance  # the covariance of the joint fit travels


def test_the_leave_one_out_drops_the_misplaced_marker_and_tells_the_world_check():
    world, spots = moved_marker_world(5, 0.10)  # the world file puts marker 5 10 cm off along x
    joint = _joint_solve(world)
    world_markers = {m: T for m, T in joint.marker_pose.items() if world.markers[m].entity == WORLD}
    check = WorldCheck(joint.sensor, joint.marker_pose, world_markers, joint.counters, joint)
    report = FrameReport()
    singles = _singles(spots, 0.05, seed=2)
    result = joint.robust(IDS, singles, 1_000_000)
    check.take_joint(WORLD, IDS, result, singles, 1_000_000, report)
    md, used = result.md, result.used
    assert used == [1, 2, 3] and md is not None
    np.testing.assert_allclose(md.p_sensor_marker_m, T_CAM_WORLD.translation, atol=0.002)
    # Marker 5's own square is 10 cm short of where the world file has it, along the world's x.
    np.testing.assert_allclose(check.offsets[5], [-0.10, 0.0, 0.0], atol=0.005)
    assert check.disagreements == Counter({5: 1}) and "marker 5 disagrees" in report.dropped[5]
    assert joint.counters["joint_misfit"] == 1 and joint.counters["joint_without_disagreeing"] == 1


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_the_entity_in_the_camera_is_the_marker_pose_composed_with_the_inverse_of_its_place(seed: int):
    rng = np.random.default_rng(seed)
    R_cm, R_em = Rotation.random(2, rng=rng)
    p_cm, p_em = rng.normal(0.0, 2.0, (2, 3))
    rotvec, tvec = entity_in_camera(p_cm, R_cm.as_quat(), R_em.as_matrix(), p_em)
    expected = RigidTransform.from_components(p_cm, R_cm) * RigidTransform.from_components(p_em, R_em).inv()
    np.testing.assert_allclose(tvec, expected.translation, atol=1e-12)
    assert (Rotation.from_rotvec(rotvec).inv() * expected.rotation).magnitude() < 1e-12
    # The entity's origin and axes seen from the camera put the marker back where the camera saw it.
    np.testing.assert_allclose(Rotation.from_rotvec(rotvec).apply(p_em) + tvec, p_cm, atol=1e-12)

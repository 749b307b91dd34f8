"""The live world-file check in the detector: a marker the world file puts 10 cm off is
named after many images, with its offset, and is then no longer used on its own; one that fits is
never named."""

from __future__ import annotations

import functools
import logging
from collections import Counter

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import covariance
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.refine.sampling import PerMarkerSchedule
from atlas_onboard.core.worldcheck import MIN_VIEWS
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.pose import MarkerPose
from atlas_onboard.detector.records import SingleSolve
from atlas_onboard.detector.worldcheck import WorldCheck
from tests.detector.scenes import DIST, H, K, W, moved_marker_image, moved_marker_world

FRAME_US = 100_000


@functools.cache
def _image(k: int, alone: bool = False) -> np.ndarray:
    """The k-th image of a slow turn over the four markers (or of marker 5 alone), rendered once."""
    _, spots = moved_marker_world(None, 0.0)
    return moved_marker_image({5: spots[5]} if alone else spots, yaw_deg=2.0 + 0.25 * k)[0]


def _fly(det: Detector, frames: range) -> None:
    for k in frames:
        det.detect(_image(k), 1_000_000 + k * FRAME_US)


def _camera_error(world, md) -> tuple[np.ndarray, np.ndarray]:
    """Where a world marker's observation puts the camera by eq. 1 with the world file's pose of the marker
    (the camera sensor's pose in its entity is the identity here), and its (3,) 1-sigma per axis."""
    T_world_marker = world.markers[md.marker_id].T_entity_marker
    R = Rotation.from_quat([*md.q_sensor_marker_wxyz[1:], md.q_sensor_marker_wxyz[0]]).as_matrix()
    p = np.array(md.p_sensor_marker_m)
    p_world_cam = T_world_marker.apply(-R.T @ p)
    Ji = covariance.inverse_jacobian(p, R)
    R_wm = T_world_marker.rotation.as_matrix()
    C = R_wm @ covariance.transform(Ji, md.covariance_matrix())[:3, :3] @ R_wm.T
    return p_world_cam, np.sqrt(np.diag(C))


def test_a_marker_off_in_the_world_file_is_named_and_then_used_at_its_measured_place(caplog):
    world, _ = moved_marker_world(5, 0.10)  # the world file puts marker 5 10 cm off its true place
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    # Before the check has seen enough, marker 5 alone is reported (nothing yet says it moved).
    (md,) = det.detect(_image(0, alone=True), 500_000)
    assert md.marker_id == 5
    det.take_status()
    with caplog.at_level(logging.WARNING, logger="atlas_onboard.detector"):
        _fly(det, range(MIN_VIEWS - 1))
        assert det.counters["markers_moved"] == 0  # one image short of the evidence it needs
        _fly(det, range(MIN_VIEWS - 1, MIN_VIEWS + 5))
        assert det.counters["markers_moved"] == 1 and list(det.moved) == [("world", 5)]
        np.testing.assert_allclose(det.moved[("world", 5)].offset_m, [-0.10, 0.0, 0.0], atol=0.02)
        assert sum("world marker 5 has moved" in r.getMessage() for r in caplog.records) == 1
        assert [t for t in det.take_status() if "moved" in t] == ["atlas: marker 5 moved -10 +0 +0 cm"]
        # Now marker 5 alone is used where it really is: the camera at the truth within 3 sigma per axis,
        # where the world file's place would put it 10 cm off; as close as the same square gives with a
        # world file that has it right (a lone 15 cm square at 1.6 m), and less certain by the place's sigma.
        world_right, spots = moved_marker_world(None, 0.0)
        img, T_cam_world = moved_marker_image({5: spots[5]}, yaw_deg=2.0)
        right = Detector(world_right.sensors[1], world_right, Calibration(W, H, K, DIST), decimate=1.0, track=False)
        p_right, sigma_right = _camera_error(world_right, right.detect(img, 9_000_000)[0])
        for t_us in (9_000_000, 9_100_000):
            (md,) = det.detect(img, t_us)
            p_world_cam, sigma = _camera_error(world, md)
            err = p_world_cam - T_cam_world.inv().translation
            assert md.marker_id == 5 and np.all(np.abs(err) <= 3 * sigma), (err, sigma)
            assert np.linalg.norm(p_world_cam - p_right) < 0.01 and np.all(sigma >= sigma_right)
    assert det.counters["placed_used"] == 2 and det.counters["places_measured"] == 1
    assert det.counters["dropped_moved"] == 0
    assert sum("using its measured place" in r.getMessage() for r in caplog.records) == 1


def test_a_pair_with_a_placed_marker_uses_it_at_its_place_beside_the_other():
    """A moved marker whose place has been measured, seen beside one trusted marker: the pair misfits as
    the world file has them, but the moved one is used at its place (the camera at the truth within its
    sigma) as well as the other, not dropped leaving the other alone."""
    world, spots = moved_marker_world(5, 0.10)
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    _fly(det, range(MIN_VIEWS + 5))
    assert ("world", 5) in det.moved
    det.detect(_image(0, alone=True), 8_900_000)  # seen alone: its place is measured and used
    assert det.counters["places_measured"] == 1
    img, T_cam_world = moved_marker_image({1: spots[1], 5: spots[5]}, yaw_deg=6.0)
    by_id = {md.marker_id: md for md in det.detect(img, 9_000_000)}
    assert sorted(by_id) == [1, 5] and det.counters["placed_used"] == 2, det.report.explain()
    for md in by_id.values():
        p_world_cam, sigma = _camera_error(world, md)
        err = p_world_cam - T_cam_world.inv().translation
        assert np.all(np.abs(err) <= 3 * sigma), (md.marker_id, err, sigma)


def test_markers_where_the_world_file_has_them_are_never_named():
    world, _ = moved_marker_world(None, 0.0)
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    _fly(det, range(MIN_VIEWS + 10))
    assert det.counters["markers_moved"] == 0 and not det.moved and not det.disagreements


PAIR_FRAME_US = 200_000  # far enough apart that only the pairs seen together are compared


def test_a_pair_that_disagrees_uses_the_marker_others_agree_with_and_a_put_back_marker_is_used_again():
    world, spots = moved_marker_world(5, 0.10)  # the world file puts marker 5 10 cm off its true place
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    pair_15 = {1: spots[1], 5: spots[5]}
    t = iter(range(1_000_000, 100_000_000, PAIR_FRAME_US))
    # Markers 1 and 5 together: they disagree, and nothing says which of them moved: neither is used.
    assert det.detect(moved_marker_image(pair_15)[0], next(t)) == []
    # Markers 1 and 2 together agree (twice: one image is no relation).
    for yaw in (3.0, 5.0):
        (md,) = det.detect(moved_marker_image({1: spots[1], 2: spots[2]}, yaw)[0], next(t))
    # Now 1 and 5 again: 5 disagrees with a marker that others agree with: 1 alone is used, 5 is not.
    img, T_cam_world = moved_marker_image(pair_15, 6.0)
    (md,) = det.detect(img, next(t))
    assert md.marker_id == 1
    np.testing.assert_allclose(md.p_sensor_marker_m, T_cam_world.translation, atol=0.01)
    # Marker 5 alone is suspect, but two views (the pair images 0.6 s apart, placed by 1, which others agree
    # with) have measured its place: used there, not where the world file has it (which would move the pose
    # 10 cm): the camera at the truth within the sigma the place adds.
    (md,) = det.detect(moved_marker_image({5: spots[5]}, 6.0)[0], next(t))
    p_world_cam, sigma = _camera_error(world, md)
    err = p_world_cam - T_cam_world.inv().translation
    assert md.marker_id == 5 and np.all(np.abs(err) <= 3 * sigma), (err, sigma)
    assert det.counters["placed_used"] == 1 and det.counters["dropped_suspect"] == 0
    # Put back where the world file has it: it agrees with 1 again, and is cleared after a few images.
    back = {1: spots[1], 5: (spots[5][0] + 0.10, spots[5][1])}
    for yaw in (4.0, 4.5, 5.0):
        det.detect(moved_marker_image(back, yaw)[0], next(t))
    (md,) = det.detect(moved_marker_image({5: back[5]}, 6.0)[0], next(t))
    assert md.marker_id == 5


def test_a_marker_seen_only_in_pairs_is_named_once_the_pairs_evidence_is_sound(caplog):
    """No three markers together (a hangar's scene): pairs alone name the marker, with its offset."""
    world, spots = moved_marker_world(5, 0.10)
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    trusted = moved_marker_image({1: spots[1], 2: spots[2]})[0]
    pair, T_cam_world = moved_marker_image({1: spots[1], 5: spots[5]})
    t_us = 1_000_000
    for _ in range(2):
        det.detect(trusted, t_us)
        t_us += FRAME_US
    with caplog.at_level(logging.WARNING, logger="atlas_onboard.detector"):
        poses = []
        for _ in range(MIN_VIEWS + 1):
            poses.append([md.p_sensor_marker_m for md in det.detect(pair, t_us) if md.marker_id == 1])
            t_us += FRAME_US
    assert list(det.moved) == [("world", 5)]
    np.testing.assert_allclose(det.moved[("world", 5)].offset_m, [-0.10, 0.0, 0.0], atol=0.02)
    assert sum("world marker 5 has moved" in r.getMessage() for r in caplog.records) == 1
    assert [t for t in det.take_status() if "moved" in t] == ["atlas: marker 5 moved -10 +0 +0 cm"]
    # Marker 1 was never named; it gave the pose, at the truth, in every pair image but the first (one
    # disagreement is no relation yet, so neither member is used then).
    assert det.counters["markers_moved"] == 1
    assert [len(p) for p in poses] == [0] + [1] * MIN_VIEWS
    np.testing.assert_allclose(poses[-1][0], T_cam_world.translation, atol=0.01)


def test_per_marker_images_report_a_moved_marker_only_beside_two_others():
    """Live refinement's per-marker images: a marker named moved is reported on its own when two or more
    others are seen with it (the evidence to refine it; the graph weighs it against them); alone, only at
    its measured place, and not at all once the node's map has its refined pose instead."""
    world, _ = moved_marker_world(5, 0.10)
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    _fly(det, range(MIN_VIEWS + 5))
    assert ("world", 5) in det.moved
    det.per_marker = PerMarkerSchedule(frozenset(m.id for m in world.entity("world").markers), period_us=0)
    assert 5 not in {md.marker_id for md in det.detect(_image(0), 8_900_000)}  # joint: the moved one left out
    ids = sorted(md.marker_id for md in det.detect(_image(0), 9_000_000))  # the next image, marker by marker
    assert 5 in ids and len(ids) >= 3, ids
    (md,) = det.detect(_image(0, alone=True), 9_100_000)
    assert md.marker_id == 5 and det.counters["placed_used"] == 1
    # The listener now holds a refined pose of marker 5: correcting for the world file's would count twice.
    det.map_pose_changed(5)
    assert det.detect(_image(0, alone=True), 9_200_000) == []
    assert det.counters["dropped_moved"] == 1


def test_a_suspect_marker_without_a_measured_place_is_not_used_alone():
    """As above, but every image within one view (refine's view gap): one burst cannot show its own shared
    error, so no place is measured, and marker 5 seen alone is dropped as suspect, counted and explained,
    rather than used where the world file has it (which would move the pose 10 cm)."""
    world, spots = moved_marker_world(5, 0.10)
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    pair_15 = {1: spots[1], 5: spots[5]}
    t = iter(range(1_000_000, 100_000_000, 50_000))
    assert det.detect(moved_marker_image(pair_15)[0], next(t)) == []
    for yaw in (3.0, 5.0):
        det.detect(moved_marker_image({1: spots[1], 2: spots[2]}, yaw)[0], next(t))
    (md,) = det.detect(moved_marker_image(pair_15, 6.0)[0], next(t))
    assert md.marker_id == 1
    assert det.detect(moved_marker_image({5: spots[5]}, 6.0)[0], next(t)) == []
    assert det.counters["dropped_suspect"] == 1 and det.counters["placed_used"] == 0
    assert det.counters["places_measured"] == 0
    assert "suspect" in det.report.dropped[5]


class _Sensor:
    name, id = "down", 1


# Where each world marker's own square puts the camera (WorldCheck._sightings, the consistency check's
# evidence) for a frame's markers at once, against the camera's position from the poses (scipy), and the
# covariance against the first-order propagation of each pose's 6x6 by finite differences of its error
# vector [dp, dtheta] (dp in the camera frame, dtheta about the marker's axes).


def _camera_in_entity(T_em: RigidTransform, p: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Where the camera is in the entity: T_entity_marker (T_camera_marker)^-1, its translation."""
    return (T_em * RigidTransform.from_components(p, Rotation.from_matrix(R)).inv()).translation


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 6))
def test_each_markers_sighting_is_where_its_pose_puts_the_camera(seed: int, n: int):
    rng = np.random.default_rng(seed)
    marker_pose = {
        m: RigidTransform.from_components(rng.uniform(-3, 3, 3), Rotation.random(random_state=rng.integers(1 << 31)))
        for m in range(n)
    }
    check = WorldCheck(_Sensor(), marker_pose, dict(marker_pose), Counter(), None)  # type: ignore[arg-type]
    singles, truth = {}, {}
    for m in range(n):
        p = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.5, 4)])
        R = Rotation.random(random_state=rng.integers(1 << 31))
        A = rng.normal(0, 1e-3, (6, 6))
        cov = None if m == 1 else A @ A.T
        ambiguity = 0.9 if m == 2 else 0.1  # maybe the mirrored solution: no sighting
        mp = MarkerPose(p, R.as_quat(), 0.1, None, None, ambiguity, 0.01, cov)
        singles[m] = SingleSolve(mp, np.zeros((4, 2)), None, 0.1)
        truth[m] = (p, R.as_matrix(), cov)
    got = check._sightings(list(range(n)), singles, 123)
    assert sorted(got) == [m for m in range(n) if m != 1 and not (m == 2 and 0.9 > AMBIGUITY_THRESHOLD)]
    for m, s in got.items():
        p, R, cov = truth[m]
        assert s.capture_time_us == 123
        np.testing.assert_allclose(s.p_m, _camera_in_entity(marker_pose[m], p, R), rtol=0, atol=1e-12)
        J = np.empty((3, 6))  # the camera's position with respect to [dp, dtheta], central differences
        h = 1e-6
        for i in range(6):
            d = np.zeros(6)
            d[i] = h
            plus = _camera_in_entity(marker_pose[m], p + d[:3], R @ Rotation.from_rotvec(d[3:]).as_matrix())
            minus = _camera_in_entity(marker_pose[m], p - d[:3], R @ Rotation.from_rotvec(-d[3:]).as_matrix())
            J[:, i] = (plus - minus) / (2 * h)
        expected = J @ cov @ J.T
        np.testing.assert_allclose(s.cov_m2, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
        np.testing.assert_array_equal(s.cov_m2, s.cov_m2.T)

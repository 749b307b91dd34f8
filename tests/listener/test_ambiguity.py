"""A follower's single view of its leader's tag, face on at 2-2.5 m where IPPE's two solutions fit
almost equally: the follower's autopilot attitude and the leader's estimated attitude pick the right
one, and what they cannot tell apart is refused (rendered images, the real detector) unless its two
solutions lie within the detection's covariance: then it is used as their mixture, its covariance
holding the truth and both (the detector's solve of projected corners)."""

import math
from dataclasses import replace

import cv2
import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.core import ambiguity
from atlas_onboard.core.attitude import up_in_body
from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import AltState, MarkerData, Rejection, matrix_to_upper
from atlas_onboard.detector import pose
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import Camera, MarkerView, render
from atlas_onboard.listener import EdgeUpdate, Listener
from atlas_onboard.node.setup import make_graph

K = np.array([[320.0, 0.0, 319.5], [0.0, 320.0, 239.5], [0.0, 0.0, 1.0]])
CAM = Camera(640, 480, K, np.zeros(5))
SIZE_M = 0.20
FLIP_DEG = 8.0
AUTOPILOT_NOISE_DEG = 0.5


def scene():
    # The leader's tag on its back, facing backwards; the follower's camera looking forwards.
    tag = {"id": 50, "size_m": SIZE_M, "pose": {"pos": [-0.12, 0, 0], "rpy_deg": [90, 0, -90]}}
    cam = {"name": "front", "id": 2, "pose": {"pos": [0.12, 0, 0], "rpy_deg": [-90, 0, -90]}}
    world = parse_world({"entities": {"leader": {"markers": [tag]}, "follower": {"sensors": [cam]}}})
    det = Detector(world.sensors[2], world, Calibration(640, 480, K, np.zeros(5)), decimate=1.0, track=False)
    return world, det


def angle_deg(a: Rotation, b: Rotation) -> float:
    return float(np.degrees((a.inv() * b).magnitude()))


def leader_estimate(T_wl: RigidTransform, capture_us: int) -> EntityPose:
    cov = np.diag([1e-6] * 3 + [math.radians(0.2) ** 2] * 3)
    return EntityPose("leader", T_wl.translation, T_wl.rotation.as_quat(), 1, 1, 3, 1e-3, capture_us, "world", cov)


def views(seed: int, n: int):
    """n views of the leader's tag from 2-2.5 m, within 8 deg of face on, both drones tilted a little."""
    world, det = scene()
    T_es = world.sensors[2].T_entity_sensor
    T_lm = world.markers[50].T_entity_marker
    rng = np.random.default_rng(seed)
    for k in range(n):
        T_wl = RigidTransform.from_components(
            [3.0, 0.5, 1.3], Rotation.from_euler("ZYX", [rng.uniform(-180, 180), *rng.normal(0, 4, 2)], degrees=True)
        )
        T_wm = T_wl * T_lm
        # The camera 2-2.5 m in front of the tag, within 8 deg of its normal, looking at it.
        off = Rotation.from_rotvec(
            np.radians(rng.uniform(4, 10)) * np.r_[np.cos(a := rng.uniform(0, 6.3)), np.sin(a), 0.0]
        )
        T_ms = RigidTransform.from_components(
            off.apply([0, 0, rng.uniform(2.0, 2.5)]), off * Rotation.from_euler("x", 180, degrees=True)
        )
        T_ms = T_ms * RigidTransform.from_rotation(Rotation.from_euler("z", rng.uniform(-20, 20), degrees=True))
        T_sm = T_ms.inv()
        T_wf = T_wm * T_ms * T_es.inv()
        img = render(CAM, [MarkerView("tag36h11", 50, SIZE_M, T_sm)], noise_sigma=6.0, seed=k)
        err = Rotation.from_rotvec(np.r_[rng.normal(0, AUTOPILOT_NOISE_DEG, 2), 0.0] * math.pi / 180)
        up = up_in_body(err * T_wf.rotation)
        yield world, det, img, k, T_wl, T_wf, T_sm, up


def flipped(md, swap: bool):
    """The record as a near-equal fit (ratio 0.95) with its solutions exchanged when ``swap`` (IPPE's
    wrong pick); the detection's covariance describes its own pick, so none is carried."""
    if not swap:
        return replace(md, ambiguity_ratio=0.95, covariance=())
    return replace(
        md, p_sensor_marker_m=md.p_sensor_marker_alt_m, q_sensor_marker_wxyz=md.q_sensor_marker_alt_wxyz,
        p_sensor_marker_alt_m=md.p_sensor_marker_m, q_sensor_marker_alt_wxyz=md.q_sensor_marker_wxyz,
        ambiguity_ratio=0.95, covariance=(),
    )  # fmt: skip


def edge_is_right(listener, md, T_wf, T_wl) -> bool:
    """The edge made of ``md`` is nearer the true T_follower_leader than the other solution's would be."""
    edge = listener.edge_from(md)
    assert isinstance(edge, EdgeUpdate)
    truth = (T_wf.inv() * T_wl).rotation
    R_sm = Rotation.from_quat(np.r_[md.q_sensor_marker_wxyz[1:], md.q_sensor_marker_wxyz[0]])
    R_alt = Rotation.from_quat(md.q_sensor_marker_alt_xyzw())
    gap = angle_deg(R_sm, R_alt)  # the two solutions' difference carries into the edge's rotation
    return angle_deg(Rotation.from_quat(edge.q_a_b_xyzw), truth) < 0.5 * gap


def test_near_equal_views_of_the_leaders_tag_are_decided_by_both_attitudes():
    """Each view as both picks (the right one first, and exchanged): with the follower's autopilot
    attitude and the leader's estimate, every decided edge is the right solution, and most are decided."""
    decided = wrong = total = swapped = 0
    for world, det, img, k, T_wl, T_wf, _T_sm, up in views(3, 30):
        for md0 in det.detect(img, capture_time_us=1_000 + k):
            if md0.alt_state() is not AltState.VALID:
                continue
            for swap in (False, True):
                listener = Listener(world, make_graph(world, "follower"))
                listener.set_attitude("follower", lambda t_us, up=up: up)
                listener.set_estimates({"leader": leader_estimate(T_wl, 1_000 + k)})
                md = flipped(md0, swap)
                total += 1
                if listener.accept_many([(md, k * 1_000_000)])[0] is not None:
                    continue  # refused: never a wrong edge
                decided += 1
                swapped += listener.counters["attitude_alt"]
                wrong += not edge_is_right(listener, md, T_wf, T_wl)
    assert wrong == 0
    assert total >= 50 and decided >= 0.8 * total and swapped >= 0.3 * total


def test_without_the_leaders_estimate_a_near_equal_view_is_refused_not_guessed():
    refused = total = 0
    for world, det, img, k, _T_wl, _T_wf, _T_sm, up in views(4, 15):
        for md0 in det.detect(img, capture_time_us=1_000 + k):
            if md0.alt_state() is not AltState.VALID:
                continue
            for swap in (False, True):
                listener = Listener(world, make_graph(world, "follower"))
                listener.set_attitude("follower", lambda t_us, up=up: up)
                total += 1
                refused += listener.accept_many([(flipped(md0, swap), k * 1_000_000)])[0] is not None
    assert total >= 20 and refused == total


# A relay drone's view of its leader's 20 cm tag at 1.1-1.4 m, nearly face on, with 0.3 px of corner
# noise: the detector's solve (Levenberg-Marquardt refined, its covariance) of projected corners.
K_RELAY = np.array([[457.0, 0.0, 319.5], [0.0, 457.0, 239.5], [0.0, 0.0, 1.0]])
NOISE_PX = 0.3


def solved(T_sm: RigidTransform, seed: int, capture_us: int):
    """The detector's record of the leader's tag seen at ``T_sm`` (its two solutions, its covariance)."""
    obj = pose.object_corners(SIZE_M)
    img, _ = cv2.projectPoints(obj, T_sm.rotation.as_rotvec(), T_sm.translation, K_RELAY, None)
    img = img.reshape(-1, 2) + np.random.default_rng(seed).normal(0.0, NOISE_PX, (4, 2))
    mp = pose.solve(img, SIZE_M, K_RELAY, pose.SIGMA_PX_APRILTAG, measured_sigma_px=NOISE_PX)
    if mp is None or mp.p_alt_m is None or mp.q_alt_xyzw is None or mp.covariance is None:
        return None
    x, y, z, w = mp.q_xyzw
    ax, ay, az, aw = mp.q_alt_xyzw
    return MarkerData(
        2, 50, mp.sigma_m, tuple(mp.p_m), (w, x, y, z), capture_us, mp.reprojection_error_px, mp.ambiguity,
        p_sensor_marker_alt_m=tuple(mp.p_alt_m), q_sensor_marker_alt_wxyz=(aw, ax, ay, az),
        covariance=matrix_to_upper(mp.covariance),
    )  # fmt: skip


def relay_views(seed: int, n: int, tilt_deg: float, ambiguous: bool = True):
    """n of the relay drone's records of the leader's tag tilted about ``tilt_deg`` from face on (only
    the ambiguous ones, ratio above the threshold, when ``ambiguous``), with the true poses: (world,
    record, T_world_leader, T_world_follower)."""
    world, _ = scene()
    T_es, T_lm = world.sensors[2].T_entity_sensor, world.markers[50].T_entity_marker
    rng = np.random.default_rng(seed)
    for k in range(20 * n):
        axis = rng.uniform(0, 2 * math.pi)
        tilt = Rotation.from_rotvec(math.radians(tilt_deg + rng.normal(0, 2)) * np.r_[np.cos(axis), np.sin(axis), 0])
        T_sm = RigidTransform.from_components(
            [*rng.uniform(-0.1, 0.1, 2), rng.uniform(1.1, 1.4)], tilt * Rotation.from_euler("x", 180, degrees=True)
        )
        T_wl = RigidTransform.from_components(
            [3.0, 0.5, 1.3], Rotation.from_euler("ZYX", [rng.uniform(-180, 180), *rng.normal(0, 4, 2)], degrees=True)
        )
        T_wf = T_wl * T_lm * T_sm.inv() * T_es.inv()
        md = solved(T_sm, seed * 100_000 + k, 1_000 + k)
        if md is not None and (md.ambiguity_ratio > ambiguity.AMBIGUITY_THRESHOLD or not ambiguous):
            yield world, md, T_wl, T_wf
            n -= 1
            if n == 0:
                return


def pair_r2(md: MarkerData) -> float:
    """The other solution's offset from the chosen one in the detection's covariance, d^T C^-1 d."""
    R_a, R_b = Rotation.from_quat(md.q_sensor_marker_xyzw()), Rotation.from_quat(md.q_sensor_marker_alt_xyzw())
    d = np.r_[np.subtract(md.p_sensor_marker_alt_m, md.p_sensor_marker_m), (R_a.inv() * R_b).as_rotvec()]
    return float(d @ np.linalg.solve(md.covariance_matrix(), d))


def edge_error(edge: EdgeUpdate, T_ab: RigidTransform) -> np.ndarray:
    """The true T_a_b's offset from the edge, [dp in a, dtheta about b's axes] (core.covariance)."""
    R = Rotation.from_quat(edge.q_a_b_xyzw)
    return np.r_[T_ab.translation - edge.p_a_b, (R.inv() * T_ab.rotation).as_rotvec()]


def test_face_on_solutions_within_the_detections_covariance_are_used_covering_both():
    """Undecided by the estimates (taken at the truth: they sit between the two mirror tilts), a pair
    within the detection's covariance is used, its covariance covering the truth and both solutions."""
    nees, used, total = [], 0, 0
    for world, md, T_wl, T_wf in relay_views(5, 60, 0.0):
        if pair_r2(md) > ambiguity.COVER_R2:
            continue
        listener = Listener(world, make_graph(world, "follower"))
        own = EntityPose(
            "follower", T_wf.translation, T_wf.rotation.as_quat(), 1, 1, 3, 1e-3, md.capture_time_us, "world"
        )
        listener.set_estimates({"leader": leader_estimate(T_wl, md.capture_time_us), "follower": own})
        total += 1
        edge = listener.edge_from(md)
        if not isinstance(edge, EdgeUpdate):
            continue
        used += 1
        C = edge.cov_a_b
        e = edge_error(edge, T_wf.inv() * T_wl)
        nees.append(float(e @ np.linalg.solve(C, e)))
        for which in (md, flipped(md, True)):  # each solution's own edge lies within one sigma of it
            bare = Listener(world, make_graph(world, "follower"), ambiguity_threshold=1.0).edge_from(which)
            T_sol = RigidTransform.from_components(bare.p_a_b, Rotation.from_quat(bare.q_a_b_xyzw))
            d = edge_error(edge, T_sol)
            assert d @ np.linalg.solve(C, d) <= 1.0
    assert total >= 30 and used == total
    assert np.mean(nees) <= 6.0 * 1.25 and np.mean(np.array(nees) <= 16.81) >= 0.95  # chi2(6): mean 6, 0.99 at 16.81


def test_a_far_apart_undecided_pair_is_still_refused():
    """A tag tilted 25 degrees, its record made a near-equal fit (ratio 0.95, its covariance kept): no
    estimate decides it and its two solutions lie far apart in its covariance, so it is refused."""
    refused = total = 0
    for world, md0, _T_wl, _T_wf in relay_views(6, 20, 25.0, ambiguous=False):
        md = replace(md0, ambiguity_ratio=0.95)
        listener = Listener(world, make_graph(world, "follower"))
        assert pair_r2(md) > ambiguity.COVER_R2
        total += 1
        refused += listener.accept_many([(md, 1_000_000)])[0] is Rejection.AMBIGUITY_UNRESOLVED
    assert total >= 10 and refused == total

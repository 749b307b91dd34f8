"""Live map refinement (core/refine.py): leave-one-out evidence, its robust mean, the gates of an update.

Synthetic scenes: markers on a floor seen by a camera flying above it; each square's pose in the camera
is the truth perturbed by noise drawn from the covariance the sighting carries (so the covariances are
honest, as the detector's are meant to be).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.refine import MapRefiner, RefineOptions, Sighting
from atlas_onboard.core.refine.records import Image

FPS = 5  # slower than a camera: successive frames share their errors anyway (views count, not frames)
FRAME_US = 1_000_000 // FPS
SIGMA_P_M = 0.002  # a square's position noise in the camera (m), per axis
SIGMA_R_RAD = np.radians(0.5)


def _floor(n: int = 8, spacing_m: float = 0.6) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Markers on a line on the floor, their z axes up, each turned about z by its own angle."""
    out = {}
    for i in range(n):
        R = Rotation.from_euler("z", 20.0 * i, degrees=True).as_matrix()
        out[i] = (np.array([spacing_m * i, 0.1 * (i % 2), 0.0]), R)
    return out


def _camera(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The camera at time t: 1.5 m above the floor, looking down, sweeping along the line and sideways."""
    p = np.array([2.1 + 1.2 * np.sin(0.3 * t_s) + 0.3 * np.sin(1.7 * t_s), 0.6 * np.sin(1.3 * t_s), 1.5])
    # optical z down (-world z), turned a little as it goes
    tilt = Rotation.from_euler("xy", [8 * np.sin(t_s), 6 * np.cos(t_s)], degrees=True)
    R = Rotation.from_euler("x", 180.0, degrees=True) * tilt
    return p, R.as_matrix()


def _sightings(truth, ids, t_s, rng, flips=()) -> list[Sighting]:
    p_ws, R_ws = _camera(t_s)
    cov = np.diag([SIGMA_P_M**2] * 3 + [SIGMA_R_RAD**2] * 3)
    out = []
    for mid in ids:
        p_wm, R_wm = truth[mid]
        p_sm = R_ws.T @ (p_wm - p_ws)
        R_sm = R_ws.T @ R_wm
        p_sm = p_sm + rng.normal(0, SIGMA_P_M, 3)
        R_sm = R_sm @ Rotation.from_rotvec(rng.normal(0, SIGMA_R_RAD, 3)).as_matrix()
        if mid in flips:  # a mirrored square: tilted far off, as a planar flip is
            R_sm = R_sm @ Rotation.from_euler("x", 40, degrees=True).as_matrix()
            p_sm = p_sm + np.array([0.05, -0.04, 0.02])
        out.append(Sighting(mid, p_sm, R_sm, cov))
    return out


def _feed(refiner, truth, seconds=30.0, ids=None, rng=None, flip_every=0, camera="cam") -> None:
    rng = rng or np.random.default_rng(0)
    ids = list(truth) if ids is None else ids
    for k in range(int(seconds * FPS)):
        t = k / FPS
        # The camera sees four neighbouring markers at a time, a window that moves along the line.
        first = round((np.sin(0.3 * t) + 1) / 2 * (len(ids) - 4))
        seen = ids[first : first + 4]
        flips = (seen[k % len(seen)],) if flip_every and k % flip_every == 0 else ()
        refiner.add_image(camera, k * FRAME_US, _sightings(truth, seen, t, rng, flips))


def _moved(truth, mid, dp):
    out = dict(truth)
    p, R = truth[mid]
    out[mid] = (p + np.asarray(dp), R)
    return out


def _converge(refiner: MapRefiner, max_steps: int = 20) -> list:
    updates = []
    for _ in range(max_steps):
        step = refiner.step()
        if not step:
            break
        updates += step
    return updates


def test_a_marker_10_cm_off_is_refined_to_the_truth_and_the_others_stay():
    truth = _floor()
    refiner = MapRefiner(_moved(truth, 3, [0.1, 0.0, 0.0]))
    _feed(refiner, truth)
    updates = _converge(refiner)
    assert {u.marker_id for u in updates} == {3}
    p, R, cov = refiner.pose(3)
    err = np.linalg.norm(p - truth[3][0])
    sigma = np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])
    assert err < 0.003, err
    assert err < 4 * sigma + 1e-4  # the claimed sigma covers the error
    assert np.degrees(Rotation.from_matrix(R.T @ truth[3][1]).magnitude()) < 0.5
    for mid in truth:  # nobody else moved
        if mid != 3:
            np.testing.assert_array_equal(refiner.pose(mid)[0], truth[mid][0])


def test_each_update_moves_at_most_the_step_bound():
    truth = _floor()
    opts = RefineOptions(max_step_m=0.03)
    refiner = MapRefiner(_moved(truth, 2, [0.0, 0.1, 0.0]), options=opts)
    _feed(refiner, truth)
    updates = _converge(refiner)
    assert len(updates) >= 4  # 10 cm in steps of 3 cm
    assert all(u.step_m <= 0.03 + 1e-12 for u in updates)
    assert np.linalg.norm(refiner.pose(2)[0] - truth[2][0]) < 0.003


def test_a_good_map_is_never_moved():
    truth = _floor()
    for seed in range(2):
        refiner = MapRefiner(truth)
        _feed(refiner, truth, rng=np.random.default_rng(seed))
        assert refiner.step() == []
        assert refiner.counters["evidence"] > 500


def test_leave_one_out_a_marker_never_confirms_itself():
    """Where the map puts a marker does not change its own evidence: only the others place the camera."""
    truth = _floor()
    a, b = MapRefiner(truth), MapRefiner(_moved(truth, 3, [0.3, -0.2, 0.1]))
    rng_a, rng_b = np.random.default_rng(5), np.random.default_rng(5)
    _feed(a, truth, seconds=3, rng=rng_a)
    _feed(b, truth, seconds=3, rng=rng_b)
    ea, eb = a.evidence(3), b.evidence(3)
    assert len(ea) == len(eb) > 0
    for x, y in zip(ea, eb, strict=True):
        np.testing.assert_allclose(x.p_world_marker_m, y.p_world_marker_m, atol=1e-12)
    # ...whereas the others' evidence from those images is refused: the moved one disagrees with them.
    assert b.counters["rejected_inconsistent"] > 0 and a.counters["rejected_inconsistent"] == 0


def test_outliers_are_rejected_and_counted():
    truth = _floor()
    refiner = MapRefiner(_moved(truth, 3, [0.1, 0.0, 0.0]))
    _feed(refiner, truth, flip_every=5, rng=np.random.default_rng(2))  # one flipped square in 5 images
    est = refiner.estimate(3)
    assert est is not None and est.outliers > 0
    _converge(refiner)
    assert np.linalg.norm(refiner.pose(3)[0] - truth[3][0]) < 0.004
    assert refiner.counters["rejected_inconsistent"] > 0  # flipped others refuse their image


def test_anchors_are_never_moved():
    truth = _floor()
    wrong = _moved(truth, 3, [0.1, 0.0, 0.0])
    refiner = MapRefiner(wrong, anchors=[3])
    _feed(refiner, truth)
    assert refiner.step() == []
    np.testing.assert_array_equal(refiner.pose(3)[0], wrong[3][0])
    assert refiner.counters["rejected_anchor"] > 0 and refiner.estimate(3) is None


def test_never_from_a_single_image_nor_from_one_direction():
    truth = _floor()
    wrong = _moved(truth, 1, [0.1, 0.0, 0.0])
    one = MapRefiner(wrong)
    rng = np.random.default_rng(3)
    for k in range(200):  # the same image, 200 times
        one.add_image("cam", k * FRAME_US, _sightings(truth, [0, 1, 2, 3], 0.0, np.random.default_rng(7)))
    assert one.step() == []
    est = one.estimate(1)
    assert est is not None and ("views" in one.verdict(est) or "direction" in one.verdict(est))
    # Many images from one place, but the camera never moves: seen from one direction only.
    still = MapRefiner(wrong, options=RefineOptions(view_gap_s=0.0))
    for k in range(200):
        still.add_image("cam", k * FRAME_US, _sightings(truth, [0, 1, 2, 3], 0.0, rng))
    assert still.step() == []
    assert "one direction" in still.verdict(still.estimate(1))


def test_an_image_with_too_few_markers_gives_no_evidence():
    truth = _floor()
    refiner = MapRefiner(truth)
    rng = np.random.default_rng(4)
    assert refiner.add_image("cam", 0, _sightings(truth, [0, 1], 0.0, rng)) == 0
    assert refiner.add_image("cam", 1, _sightings(truth, [0, 0, 1], 0.0, rng)) == 0  # an id twice
    assert refiner.counters["rejected_few_markers"] == 1 and refiner.counters["rejected_duplicate"] == 1
    assert refiner.add_image("cam", 2, _sightings(truth, [0, 1, 2], 0.0, rng)) == 3


@settings(max_examples=6)
@given(
    mid=st.integers(2, 5),  # seen in enough images of the scene in 30 s
    dp=st.tuples(*[st.floats(-0.15, 0.15)] * 3).filter(lambda v: np.linalg.norm(v) > 0.03),
    seed=st.integers(0, 2**16),
)
def test_any_misplaced_marker_converges_within_its_sigma(mid, dp, seed):
    truth = _floor()
    refiner = MapRefiner(_moved(truth, mid, dp))
    _feed(refiner, truth, seconds=30, rng=np.random.default_rng(seed))
    _converge(refiner, max_steps=30)
    p, _, cov = refiner.pose(mid)
    err = p - truth[mid][0]
    assert np.linalg.norm(err) < 0.004
    assert float(err @ np.linalg.solve(cov[:3, :3], err)) < 30.0  # chi2(3) tail 1e-6: the covariance is honest
    assert refiner.moved == {mid}


@pytest.mark.parametrize("n_cameras", [2])
def test_two_cameras_count_their_views_apart(n_cameras):
    truth = _floor()
    refiner = MapRefiner(_moved(truth, 3, [0.1, 0, 0]))
    for c in range(n_cameras):
        _feed(refiner, truth, seconds=5, rng=np.random.default_rng(c), camera=f"cam{c}")
    est = refiner.estimate(3)
    assert est is not None
    single = MapRefiner(_moved(truth, 3, [0.1, 0, 0]))
    _feed(single, truth, seconds=5, rng=np.random.default_rng(0), camera="cam0")
    assert est.views > single.estimate(3).views


def test_images_added_at_once_give_the_evidence_of_each_in_turn():
    """add_images over a mix of images (2 to 5 markers, an unknown id, a duplicate, one marker alone, a
    flipped square, a singular covariance): every evidence item and counter bit for bit those of
    add_image on each image in turn; and for one marker alone (``marker_id``), its items the same."""
    truth = _floor()
    rng = np.random.default_rng(7)
    images = []
    for k in range(60):
        ids = list(rng.choice(8, size=int(rng.integers(1, 6)), replace=False))
        seen = _sightings(truth, ids, k / FPS, rng, flips=ids[:1] if k % 11 == 3 else ())
        if k % 13 == 5:
            seen.append(Sighting(99, seen[0].p_sensor_marker_m, seen[0].R_sensor_marker, seen[0].cov))
        if k % 17 == 6:
            seen.append(seen[0])
        if k % 19 == 7 and len(seen) > 2:
            seen[1] = Sighting(seen[1].marker_id, seen[1].p_sensor_marker_m, seen[1].R_sensor_marker, np.zeros((6, 6)))
        images.append(Image("cam" if k % 2 else "other", k * FRAME_US, tuple(seen)))
    one, many = (MapRefiner(truth, options=RefineOptions(min_others=1)) for _ in range(2))
    added = sum(one.add_image(im.camera, im.capture_time_us, im.sightings) for im in images)
    assert many.add_images(images) == added > 0
    assert many.counters == one.counters
    assert one.counters["rejected_singular"] > 0 and one.counters["rejected_duplicate"] > 0
    for m in truth:
        got, want = many.evidence(m), one.evidence(m)
        assert len(got) == len(want)
        for a, b in zip(got, want, strict=True):
            assert (a.camera, a.capture_time_us, a.others) == (b.camera, b.capture_time_us, b.others)
            for f in ("p_world_marker_m", "R_world_marker", "cov", "direction"):
                assert np.array_equal(getattr(a, f), getattr(b, f))
    for m in truth:
        alone = MapRefiner(truth, options=RefineOptions(min_others=1))
        assert alone.add_images(images, m) == len(one.evidence(m))
        assert all(not alone.evidence(k) for k in truth if k != m)
        for a, b in zip(alone.evidence(m), one.evidence(m), strict=True):
            assert (a.capture_time_us, a.others) == (b.capture_time_us, b.others)
            for f in ("p_world_marker_m", "R_world_marker", "cov", "direction"):
                assert np.array_equal(getattr(a, f), getattr(b, f))

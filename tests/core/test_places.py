"""A moved world marker's measured place (core/places.py MeasuredPlaces): from images in which trusted
markers placed the camera, with an honest covariance; never from itself or from doubted markers; withdrawn
when it keeps moving."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation
from scipy.special import chdtri

from atlas_onboard.core import covariance
from atlas_onboard.core.places import (
    PLACE_MIN_VIEWS,
    RECHECK_LAST,
    RECHECK_MISFITS,
    MeasuredPlace,
    MeasuredPlaces,
    place_covariance,
)
from atlas_onboard.core.refine import MapRefiner, RefineOptions, Sighting, residuals

FRAME_US = 33_333
SIGMA_M = 0.001
SIGMA_RAD = np.radians(0.2)
COV = np.diag([SIGMA_M**2] * 3 + [SIGMA_RAD**2] * 3)
FILE = {1: [0.0, 0.0, 0.0], 2: [0.6, 0.0, 0.0], 3: [0.6, 0.4, 0.0], 5: [0.0, 0.4, 0.0]}  # floor tags, ENU
MOVED = np.array([-0.10, 0.0, 0.0])  # marker 2 is really here from its world-file place
VIEW_GAP_S = RefineOptions().view_gap_s


def _places() -> MeasuredPlaces:
    return MeasuredPlaces({m: (np.array(p), np.eye(3)) for m, p in FILE.items()})


def _image(rng, t_s: float, ids, true: dict[int, np.ndarray], bias=None) -> list[Sighting]:
    """Sightings of ``ids`` from a camera 1.5 m above the tags, drifting with ``t_s``; each square's own pose
    noisy by ``COV`` (position in the camera frame, rotation about the marker's axes), plus, for the markers
    in ``bias`` (id -> (dp (3,) m, dtheta (3,) rad)), an error its covariance does not show."""
    R_ws = Rotation.from_euler("xyz", [180 + 5 * np.sin(t_s), 4 * np.cos(t_s), 10 * t_s], degrees=True).as_matrix()
    p_ws = np.array([0.3 + 0.1 * np.sin(t_s), 0.2, 1.5])
    out = []
    for m in ids:
        dp, dtheta = (bias or {}).get(m, (np.zeros(3), np.zeros(3)))
        p_sm = R_ws.T @ (true[m] - p_ws) + dp + rng.normal(0.0, SIGMA_M, 3)
        R_sm = R_ws.T @ Rotation.from_rotvec(dtheta + rng.normal(0.0, SIGMA_RAD, 3)).as_matrix()
        out.append(Sighting(m, p_sm, R_sm, COV))
    return out


def _truth(moved: np.ndarray = MOVED) -> dict[int, np.ndarray]:
    true = {m: np.array(p) for m, p in FILE.items()}
    true[2] = true[2] + moved
    return true


def _fly(places, rng, t0_s, seconds, ids, true, trusted):
    withdrawn = []
    for k in range(round(seconds * 1e6 / FRAME_US)):
        t_us = round(t0_s * 1e6) + k * FRAME_US
        withdrawn += places.add_image("cam", t_us, _image(rng, t_us / 1e6, ids, true), trusted)
    return withdrawn, t_us


def _not_2(others: frozenset[int]) -> bool:
    return 2 not in others


def test_a_moved_marker_is_placed_where_it_is_with_an_honest_covariance():
    rng = np.random.default_rng(4)
    places = _places()
    _, t_us = _fly(places, rng, 0.0, VIEW_GAP_S - 0.05, (1, 2, 5), _truth(), _not_2)
    # One view (frames within refine's view gap, from about one place) is one burst, however many images:
    # it cannot show the error its images share, nor a marker still moving. Not enough.
    assert isinstance(places.establish(2, t_us, _not_2), str)
    _, t_us = _fly(places, rng, 1.0, 2.0, (1, 2, 3), _truth(), _not_2)
    place = places.establish(2, t_us, _not_2)
    assert isinstance(place, MeasuredPlace) and place.views >= PLACE_MIN_VIEWS
    err = place.p_world_marker_m - _truth()[2]
    sigma = np.sqrt(np.diag(place.cov)[:3])
    assert np.all(np.abs(err) <= 3 * sigma), (err, sigma)
    assert np.linalg.norm(err) < 0.003 and place.max_sigma_m < 0.003
    np.testing.assert_allclose(place.offset_m, MOVED, atol=0.003)
    assert places.place(2) is place


def test_a_place_from_two_views_whose_images_share_their_errors_covers_the_truth_at_its_nominal_rate():
    """Monte Carlo: marker 2 seen in two views 1 s apart, ten images each; in each view its square's pose has
    an error of its own that every image of the view shares (the same geometry), unknown to its covariance
    and as large as three of its images' noise. The place is used from those two views, and its covariance
    says how far off it is: NEES over the 6 components no larger than a chi-square's, in the mean and in the
    99 % tail (nominal rate, with the Monte Carlo's allowance)."""
    rng = np.random.default_rng(11)
    trials, nees = 200, []
    for _ in range(trials):
        places = _places()
        for t0_s in (0.0, 1.0):
            bias = {2: (rng.normal(0.0, 3 * SIGMA_M, 3), rng.normal(0.0, 3 * SIGMA_RAD, 3))}
            for k in range(10):
                t_us = round(t0_s * 1e6) + k * FRAME_US
                places.add_image("cam", t_us, _image(rng, t_us / 1e6, (1, 2, 3), _truth(), bias), _not_2)
        place = places.establish(2, t_us, _not_2)
        if isinstance(place, MeasuredPlace):
            assert place.views == 2
            e = residuals(place.p_world_marker_m[None], place.R_world_marker[None], _truth()[2], np.eye(3))[0]
            nees.append(float(e @ np.linalg.solve(place.cov, e)))
    # Most trials give a place (views that disagree beyond what images can show are refused, rightly).
    assert len(nees) >= trials // 2, len(nees)
    nees = np.array(nees)
    beyond = float(np.mean(nees > chdtri(6, 0.01)))
    assert nees.mean() <= 6.0 and beyond <= 0.01 + 3 * np.sqrt(0.01 * 0.99 / len(nees)), (nees.mean(), beyond)


def test_a_marker_still_moving_is_refused_when_its_views_show_it_and_withdrawn_when_they_cannot():
    """Marker 2 on something that moves. At 5 cm/s its views (refine's view gap apart) disagree by several of
    their sigmas: never placed, from one burst or from many views. Creeping at 1-2 cm/s, within what two
    views can tell from their noise: each place it gets is withdrawn as it keeps moving (at most the newest
    stands)."""
    for speed_m_s, placed_ok in ((0.05, False), (0.02, True), (0.01, True)):
        rng = np.random.default_rng(12)
        places = _places()
        placed = withdrawn = 0
        for k in range(round(3.0 * 1e6 / FRAME_US)):
            t_us = k * FRAME_US
            true = _truth(MOVED + np.array([speed_m_s, 0.0, 0.0]) * t_us / 1e6)
            withdrawn += len(places.add_image("cam", t_us, _image(rng, t_us / 1e6, (1, 2, 3), true), _not_2))
            if k % 3 == 0 and places.place(2) is None:
                placed += isinstance(places.establish(2, t_us, _not_2), MeasuredPlace)
        assert placed == 0 or placed_ok, (speed_m_s, placed)
        assert withdrawn >= placed - 1, (speed_m_s, placed, withdrawn)


def test_evidence_placed_by_doubted_markers_or_by_the_marker_itself_never_places_it():
    rng = np.random.default_rng(5)
    places = _places()

    # Marker 2 seen only beside marker 5, which the caller does not trust (suspect or moved itself).
    def untrusted_5(others: frozenset[int]) -> bool:
        return 5 not in others and 2 not in others

    _, t_us = _fly(places, rng, 0.0, 3.0, (2, 5), _truth(), untrusted_5)
    assert places.establish(2, t_us, untrusted_5) == "too little evidence from trusted markers"
    # Alone, a marker gives no evidence of itself (leave-one-out: the camera must be placed by others).
    places = _places()
    _, t_us = _fly(places, rng, 0.0, 3.0, (2,), _truth(), _not_2)
    assert places.establish(2, t_us, _not_2) == "too little evidence from trusted markers"
    # The same images with a trusted marker beside it: placed.
    _, t_us = _fly(places, rng, 3.0, 3.0, (2, 1), _truth(), _not_2)
    assert isinstance(places.establish(2, t_us, _not_2), MeasuredPlace)


def test_a_marker_that_keeps_moving_is_withdrawn_and_placed_again_only_from_what_was_seen_since():
    rng = np.random.default_rng(6)
    places = _places()
    _, t_us = _fly(places, rng, 0.0, 2.5, (1, 2, 3), _truth(), _not_2)
    first = places.establish(2, t_us, _not_2)
    assert isinstance(first, MeasuredPlace)
    # Bumped another 4 cm: a few trusted images later its place is withdrawn (once).
    bumped = _truth(MOVED + np.array([0.0, 0.04, 0.0]))
    withdrawn, t_us = _fly(places, rng, 3.0, RECHECK_LAST * FRAME_US / 1e6 + 0.01, (1, 2, 3), bumped, _not_2)
    assert [w.marker_id for w in withdrawn] == [2] and places.place(2) is None
    # Placed again from the new evidence only: at the new place, not between the two.
    _, t_us = _fly(places, rng, 4.0, 2.5, (1, 2, 3), bumped, _not_2)
    again = places.establish(2, t_us, _not_2)
    assert isinstance(again, MeasuredPlace)
    np.testing.assert_allclose(again.p_world_marker_m, bumped[2], atol=0.003)


def test_a_marker_that_stays_keeps_its_place():
    rng = np.random.default_rng(7)
    places = _places()
    _, t_us = _fly(places, rng, 0.0, 2.5, (1, 2, 3), _truth(), _not_2)
    place = places.establish(2, t_us, _not_2)
    withdrawn, _ = _fly(places, rng, 3.0, 3.0, (1, 2, 3), _truth(), _not_2)
    assert withdrawn == [] and places.place(2) is place
    assert RECHECK_MISFITS <= RECHECK_LAST


def file_pose(p_file, R_file):
    return RigidTransform.from_components(p_file, Rotation.from_matrix(R_file))


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=9, max_size=9),
    st.lists(st.floats(-3.0, 3.0), min_size=9, max_size=9),
)
def test_a_sighting_corrected_for_the_file_pose_places_the_sensor_where_the_measured_place_does(p, r):
    """eq. 1 with the file pose and the corrected sighting == the measured place and the raw sighting."""
    p_place, p_file, p_sm = (np.array(p[i : i + 3]) for i in (0, 3, 6))
    R_place, R_file, R_sm = (Rotation.from_rotvec(r[i : i + 3]).as_matrix() for i in (0, 3, 6))
    place = MeasuredPlace(2, p_place, R_place, COV, p_place - p_file, 1.0, 10, 3, 0)
    p_new, R_new, cov, C_sensor = place.correct(p_sm, R_sm, COV, file_pose(p_file, R_file))

    def sensor_in_world(p_wm, R_wm, p_sm_, R_sm_):
        return p_wm - R_wm @ R_sm_.T @ p_sm_, R_wm @ R_sm_.T

    a = sensor_in_world(p_file, R_file, p_new, R_new)
    b = sensor_in_world(p_place, R_place, p_sm, R_sm)
    np.testing.assert_allclose(a[0], b[0], atol=1e-9)
    np.testing.assert_allclose(a[1], b[1], atol=1e-9)
    assert np.all(np.linalg.eigvalsh(cov) > 0) and np.all(np.linalg.eigvalsh(C_sensor) > -1e-12)


def test_the_corrected_sightings_covariance_is_the_sightings_and_the_places_together():
    """Monte Carlo: the sensor's position through the file pose and the corrected sighting's covariance
    spreads as sampling the sighting's and the place's errors does."""
    rng = np.random.default_rng(8)
    p_place, R_place = np.array([0.5, 0.0, 0.01]), Rotation.from_rotvec([0.02, -0.01, 0.3]).as_matrix()
    p_file, R_file = np.array([0.6, 0.0, 0.0]), Rotation.from_rotvec([0.0, 0.0, 0.3]).as_matrix()
    p_sm, R_sm = np.array([0.2, -0.1, 1.4]), Rotation.from_euler("x", 170, degrees=True).as_matrix()
    C_place = np.diag([0.002**2, 0.001**2, 0.003**2] + [np.radians(0.5) ** 2] * 3)
    place = MeasuredPlace(2, p_place, R_place, C_place, p_place - p_file, 1.0, 10, 3, 0)
    p_new, R_new, cov, C_sensor = place.correct(p_sm, R_sm, COV, file_pose(p_file, R_file))
    # Predicted: the sensor's position p_file - R_file R'^T p' with T' = (p', R') uncertain by ``cov``.
    Ji = covariance.inverse_jacobian(p_new, R_new)
    predicted = R_file @ covariance.transform(Ji, cov)[:3, :3] @ R_file.T
    n = 20000
    e, f = rng.multivariate_normal(np.zeros(6), COV, n), rng.multivariate_normal(np.zeros(6), C_place, n)
    p_s, R_s = p_sm + e[:, :3], R_sm @ Rotation.from_rotvec(e[:, 3:]).as_matrix()
    p_w, R_w = p_place + f[:, :3], R_place @ Rotation.from_rotvec(f[:, 3:]).as_matrix()
    sampled = np.cov((p_w - (R_w @ np.swapaxes(R_s, 1, 2) @ p_s[..., None])[..., 0]).T)
    np.testing.assert_allclose(np.sqrt(np.diag(predicted)), np.sqrt(np.diag(sampled)), rtol=0.05)
    # The place's share alone is smaller than the whole and larger than nothing.
    assert np.all(np.diag(C_sensor) < np.diag(predicted)) and np.all(np.diag(C_sensor) > 0)


def test_evidence_waits_until_a_place_is_sought_and_is_then_what_every_image_at_once_gives():
    """A marker's evidence is computed only when its place is sought or re-checked (an image shows it
    with a place), and the place is the one from the same images fed to the evidence one at a time, every
    item the same; images more than the window before the newest are forgotten unused (the estimate would
    not take them)."""
    rng = np.random.default_rng(5)
    places = _places()
    reference = MapRefiner({m: (np.array(p), np.eye(3)) for m, p in FILE.items()}, options=RefineOptions(min_others=1))
    fed = []
    for t0_s, seconds in ((0.0, 2.0), (places.window_us / 1e6 + 1.0, 2.5)):  # the first flight leaves the window
        for k in range(round(seconds * 1e6 / FRAME_US)):
            t_us = round(t0_s * 1e6) + k * FRAME_US
            image = _image(rng, t_us / 1e6, (1, 2, 3, 5), _truth(np.zeros(3)))
            assert places.add_image("cam", t_us, image, _not_2) == []
            reference.add_image("cam", t_us, image)
            fed.append(t_us)
    assert all(not places.refiner.evidence(m) for m in FILE)  # nothing computed yet
    place = places.establish(2, t_us, _not_2)
    assert isinstance(place, MeasuredPlace)
    since = t_us - places.window_us
    est = reference.estimate(2, accept=lambda e: e.capture_time_us >= since and _not_2(e.others))
    assert est is not None and est.items < len(fed)  # the first flight is outside the window
    assert np.array_equal(place.p_world_marker_m, est.p_world_marker_m)
    assert np.array_equal(place.R_world_marker, est.R_world_marker)
    assert np.array_equal(place.cov, place_covariance(est))
    assert (place.items, place.views) == (est.items - est.outliers, est.views)
    kept = [e.capture_time_us for e in places.refiner.evidence(2)]
    assert kept == [t for t in fed if t >= since]
    assert not places.refiner.evidence(1)
    t_us += FRAME_US  # an image showing the marker that has a place: its evidence, to re-check the place
    image = _image(rng, t_us / 1e6, (1, 2, 3, 5), _truth(np.zeros(3)))
    places.add_image("cam", t_us, image, _not_2)
    reference.add_image("cam", t_us, image)
    assert places.refiner.latest(2).capture_time_us == t_us and not places.refiner.evidence(1)
    assert isinstance(places.establish(1, t_us, lambda others: True), MeasuredPlace)
    for m in (1, 2):
        got = places.refiner.evidence(m)
        want = [e for e in reference.evidence(m) if e.capture_time_us >= since]
        assert [e.capture_time_us for e in got] == [e.capture_time_us for e in want] and len(got) > 60
        for a, b in zip(got, want, strict=True):
            assert np.array_equal(a.p_world_marker_m, b.p_world_marker_m) and np.array_equal(a.cov, b.cov)
            assert np.array_equal(a.R_world_marker, b.R_world_marker) and a.others == b.others

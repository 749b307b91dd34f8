"""The AprilTag backend: one library detector per process serves every decimation and camera, with the
results of a detector made for each decimation."""

import threading

import numpy as np
import pytest

from atlas_onboard.detector.backends import AprilTagBackend, _library_detector
from tests.detector.test_finder import frame, view_at

# The AprilTag library's detectors live as long as the process (backends._library_detector), with
# decoding tables of tens to hundreds of MB: one worker makes them all, not each.
pytestmark = pytest.mark.xdist_group("apriltag_library")

VIEWS = [view_at(3, 200, 150, 1.2), view_at(11, 430, 160, 2.0), view_at(25, 320, 360, 3.0), view_at(40, 90, 400, 4.0)]


def _corners(found) -> dict[int, np.ndarray]:
    return {d.marker_id: d.corners_px for d in found}


def test_every_decimation_gives_what_a_detector_made_for_it_gives():
    img = frame(VIEWS, seed=2)
    backend = AprilTagBackend(["tag36h11"], decimate=2.0, extra=(3.0,))
    for d in (2.0, 1.0, 3.0, 2.0, 1.5, 1.0):  # interleaved: the decimation is set for each search
        own = _library_detector("tag36h11", 1, d)
        expected = {int(r.tag_id): np.asarray(r.corners, float)[[3, 2, 1, 0]] - 0.5 for r in own.detect(img)}
        got = _corners(backend.detect(img, d))
        assert got.keys() == expected.keys() and len(got) >= 2
        for i in got:
            np.testing.assert_array_equal(got[i], expected[i])


def test_backends_of_a_process_share_one_library_detector():
    a = AprilTagBackend(["tag36h11"], decimate=2.0, extra=(3.0,))
    b = AprilTagBackend(["tag36h11"], decimate=1.0)
    c = AprilTagBackend(["tag36h11", "tag25h9"], decimate=2.0)
    assert a._library is b._library  # one decoding table for every decimation and camera
    assert c._library is not a._library  # other families: a detector of their own


def test_cameras_searching_at_once_get_their_own_results():
    imgs = [frame(VIEWS[:2], seed=3), frame(VIEWS[2:], seed=4)]
    backends = [AprilTagBackend(["tag36h11"], decimate=2.0) for _ in imgs]
    results: list[list] = [[], []]

    def search(k: int) -> None:
        for _ in range(15):
            results[k].append(_corners(backends[k].detect(imgs[k], 1.0 + k)))

    threads = [threading.Thread(target=search, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k in range(2):
        alone = _corners(backends[k].detect(imgs[k], 1.0 + k))
        assert len(alone) >= 1
        for r in results[k]:
            assert r.keys() == alone.keys()
            for i in r:
                np.testing.assert_array_equal(r[i], alone[i])

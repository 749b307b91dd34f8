"""Every AprilTag 3 family of the C library: its layout as the library states it, a rendered marker
detected with the right id, corners and pose, the markers command at size, the config accepting it."""

import re

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import MARKER_FAMILIES
from atlas_onboard.detector import pose
from atlas_onboard.detector.backends import MarkerFinder, correction_bits
from atlas_onboard.detector.families import APRILTAG3_LAYOUT, family, library_family
from atlas_onboard.detector.images import marker_svg
from atlas_onboard.detector.render import MarkerView, render
from tests.detector.test_conventions import CAM, K, true_corners

# The AprilTag library's detectors live as long as the process (backends._library_detector), with
# decoding tables of tens to hundreds of MB: one worker makes them all, not each.
pytestmark = pytest.mark.xdist_group("apriltag_library")

NEW = list(APRILTAG3_LAYOUT)


@pytest.mark.parametrize("name", NEW)
def test_layout_is_the_librarys(name):
    fam = library_family(name)
    assert APRILTAG3_LAYOUT[name] == (fam.width_at_border, fam.total_width)
    assert name in MARKER_FAMILIES
    assert family(name).bitmap(0, cell_px=1).shape == (fam.total_width + 2,) * 2


@pytest.mark.parametrize(
    ("name", "marker_id"), [("tagStandard41h12", 7), ("tagStandard41h12", 2000), *((n, 5) for n in NEW[1:])]
)
def test_rendered_marker_is_detected_with_its_id_and_pose(name, marker_id):
    distance = 1.2
    T = RigidTransform.from_components(
        [0.1, -0.06, distance], Rotation.from_euler("xyz", [180 + 30, 0, 20], degrees=True)
    )
    img = render(CAM, [MarkerView(name, marker_id, 0.15, T)], noise_sigma=1.0, seed=marker_id)
    found = MarkerFinder({marker_id: name}).find(img, 1.0)
    assert [(d.marker_id, d.family) for d in found] == [(marker_id, name)]
    assert np.abs(found[0].corners_px - true_corners(T, 0.15)).max() < 0.15  # size_m: the detected square
    mp = pose.solve(found[0].corners_px, 0.15, K, pose.SIGMA_PX_APRILTAG)
    assert np.linalg.norm(mp.p_m - T.translation) < 0.01 * distance
    assert np.degrees((Rotation.from_quat(mp.q_xyzw).inv() * T.rotation).magnitude()) < 1.0


def test_markers_prints_41h12_at_size():
    svg = marker_svg("tagStandard41h12", 7, 0.1)
    cell_mm = 100.0 / 5  # the detected square (5 cells) is size_m; the pattern is 9 cells, plus the margin
    width = float(re.search(r'width="([0-9.]+)mm"', svg).group(1))
    assert width == pytest.approx((9 + 2) * cell_mm)
    rects = re.findall(r'<rect x="([0-9.]+)" y="([0-9.]+)" width="([0-9.]+)"', svg)
    assert all(float(w) == pytest.approx(cell_mm) for _, _, w in rects)
    bmp = family("tagStandard41h12").bitmap(7, cell_px=1, quiet_zone_cells=0)
    assert len(rects) == int((bmp < 128).sum())  # one square a black cell of the library's image


def test_several_apriltag_families_in_one_image_are_all_found():
    """pupil-apriltags adds only the first family it recognises; the detector adds the others."""
    flip = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))
    views = [
        MarkerView("tag36h11", 3, 0.15, RigidTransform.from_components([-0.25, 0, 1.0], flip)),
        MarkerView("tag25h9", 4, 0.15, RigidTransform.from_components([0.0, 0, 1.0], flip)),
        MarkerView("tagStandard41h12", 5, 0.15, RigidTransform.from_components([0.25, 0, 1.0], flip)),
    ]
    img = render(CAM, views, noise_sigma=1.0, seed=3)
    found = MarkerFinder({3: "tag36h11", 4: "tag25h9", 5: "tagStandard41h12"}).find(img, 1.0)
    assert sorted((d.marker_id, d.family) for d in found) == [(3, "tag36h11"), (4, "tag25h9"), (5, "tagStandard41h12")]


def test_large_families_get_fewer_correction_bits():
    """2-bit correction for tagStandard52h13 is a decoding table of about 67 million entries (6 GB
    measured): the families whose table would pass MAX_DECODE_ENTRIES get 1 bit, or none."""
    bits = {n: correction_bits(n) for n in ("tag36h11", "tag25h9", "tag16h5", *NEW)}
    assert bits == {
        "tag36h11": 2, "tag25h9": 2, "tag16h5": 2, "tagCircle21h7": 2, "tagStandard41h12": 1,
        "tagStandard52h13": 1, "tagCustom48h12": 1, "tagCircle49h12": 0,
    }  # fmt: skip

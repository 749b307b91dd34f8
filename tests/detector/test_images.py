"""A marker as an SVG file to print: exact, and decoded back to its id."""

import re

import numpy as np

from atlas_onboard.detector.backends import MarkerFinder
from atlas_onboard.detector.families import family
from atlas_onboard.detector.images import marker_svg


def test_markers_svg_is_exact_and_decodes(tmp_path):
    svg = marker_svg("tag36h11", 42, 0.18)
    w_mm = float(re.search(r'width="([\d.]+)mm"', svg).group(1))
    assert w_mm == 180.0 + 2 * 180.0 / 8  # the black square plus a one-cell quiet zone on each side
    # Paint the rectangles at 10 px/mm and detect the result with the AprilTag library.
    scale = 4.0
    h_mm = float(re.search(r'height="([\d.]+)mm"', svg).group(1))
    img = np.full((int(h_mm * scale) + 40, int(w_mm * scale) + 40), 255, np.uint8)
    for x, y, w, h in re.findall(r'<rect x="([\d.]+)" y="([\d.]+)" width="([\d.]+)" height="([\d.]+)"/>', svg):
        x0, y0 = round(float(x) * scale) + 20, round(float(y) * scale) + 20
        img[y0 : y0 + round(float(h) * scale), x0 : x0 + round(float(w) * scale)] = 0
    found = MarkerFinder({42: "tag36h11"}).find(img, 1.0)
    assert [d.marker_id for d in found] == [42]
    side_px = np.linalg.norm(found[0].corners_px[1] - found[0].corners_px[0])
    assert abs(side_px - 180.0 * scale) < 1.5
    assert family("tag36h11").cells == 8

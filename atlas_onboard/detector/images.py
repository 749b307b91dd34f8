"""Images of markers for people: a marker's SVG at its exact printed size, a frame annotated with the
markers found in it, and an image file read as the detector takes it (grey)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.detector.families import family
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.errors import AtlasError


def read_gray(path: Path) -> NDArray[np.uint8] | None:
    """The image file at ``path`` in grey levels, or None if it is not a readable image."""
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None


def marker_svg(family_name: str, marker_id: int, size_m: float) -> str:
    """One marker at its exact physical size (print at 100 %): the black square is ``size_m`` wide,
    inside a white quiet zone of one cell, with the id and family printed below. (For the AprilTag 3
    families whose data bits lie outside that square, the printed pattern is larger than it.)"""
    fam = family(family_name)
    bmp = fam.bitmap(marker_id, cell_px=1, quiet_zone_cells=0)  # one pixel a cell, black border included
    cells = bmp.shape[0]
    cell_mm = size_m * 1000 / fam.cells
    quiet = cell_mm
    side = cells * cell_mm + 2 * quiet
    height = side + 12
    cell = f'width="{cell_mm:.4f}" height="{cell_mm:.4f}"'
    rects = [
        f'<rect x="{quiet + c * cell_mm:.4f}" y="{quiet + r * cell_mm:.4f}" {cell}/>'
        for r in range(cells) for c in range(cells) if bmp[r, c] < 128
    ]  # fmt: skip
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{side:.4f}mm" height="{height:.4f}mm"'
        f' viewBox="0 0 {side:.4f} {height:.4f}">\n'
        f'<rect width="{side:.4f}" height="{height:.4f}" fill="white"/>\n'
        f'<g fill="black" shape-rendering="crispEdges">\n' + "\n".join(rects) + "\n</g>\n"
        f'<text x="{quiet:.2f}" y="{side + 8:.2f}" font-family="sans-serif" font-size="5">'
        f"{family_name} id {marker_id} - {size_m * 1000:g} mm - print at 100 %</text>\n</svg>\n"
    )


def write_annotated(path: Path, gray: np.ndarray, found: list[MarkerData], detector: Detector) -> None:
    """``gray`` with each found marker's axes and id drawn, written to ``path`` (an AtlasError if it cannot be)."""
    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    K, dist = detector.calibration.K, detector.calibration.dist
    for md in found:
        w, x, y, z = md.q_sensor_marker_wxyz
        rvec = Rotation.from_quat([x, y, z, w]).as_rotvec()
        size = detector.sizes[md.marker_id]
        cv2.drawFrameAxes(img, K, dist, rvec, np.array(md.p_sensor_marker_m), size * 0.75, 2)
        px, _ = cv2.projectPoints(np.zeros((1, 3)), rvec, np.array(md.p_sensor_marker_m), K, dist)
        cv2.putText(
            img, str(md.marker_id), tuple(int(v) for v in px.ravel()), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 255, 255), 2
        )
    if not cv2.imwrite(str(path), img):
        raise AtlasError(f"cannot write the annotated image {path}")

"""Marker families: their bitmaps (as printed) and how each backend reports their corners.

Conventions, locked by tests against rendered markers of known pose:

- A marker's bitmap is the printed pattern: the black square of ``cells`` x ``cells`` (border
  included) that ``size_m`` measures, inside a white quiet zone one cell wide.
- AprilTag families are printed as the AprilTag library draws them (its official images). OpenCV's
  ``DICT_APRILTAG_*`` bitmaps are the same codes rotated by 180 degrees, so we rotate them back.
- Corners are always returned in OpenCV's order (top-left, top-right, bottom-right, bottom-left of
  the printed marker) and OpenCV's pixel-centre convention (the centre of the top-left pixel is 0, 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.errors import AtlasError

APRILTAG_OPENCV = {"tag36h11": "DICT_APRILTAG_36h11", "tag25h9": "DICT_APRILTAG_25h9", "tag16h5": "DICT_APRILTAG_16h5"}
APRILTAG_CELLS = {"tag36h11": 8, "tag25h9": 7, "tag16h5": 6}


@dataclass(frozen=True)
class Family:
    name: str
    is_apriltag: bool
    cells: int  # cells across the black square, border included

    def bitmap(self, marker_id: int, cell_px: int = 16, quiet_zone_cells: int = 1) -> NDArray[np.uint8]:
        """The printed marker, ``cell_px`` pixels a cell, with its white quiet zone."""
        dictionary = opencv_dictionary(self.name)
        if marker_id >= dictionary.bytesList.shape[0]:
            raise AtlasError(f"marker id {marker_id} does not exist in {self.name}")
        img = cv2.aruco.generateImageMarker(dictionary, marker_id, self.cells * cell_px, borderBits=1)
        if self.is_apriltag:
            img = np.ascontiguousarray(img[::-1, ::-1])  # OpenCV's AprilTag bitmaps are upside down
        q = quiet_zone_cells * cell_px
        return cv2.copyMakeBorder(img, q, q, q, q, cv2.BORDER_CONSTANT, value=255)


def opencv_dictionary(name: str) -> cv2.aruco.Dictionary:
    key = APRILTAG_OPENCV.get(name, name)
    if not hasattr(cv2.aruco, key):
        raise AtlasError(f"marker family {name!r} cannot be rendered or detected by OpenCV")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))


def family(name: str) -> Family:
    """The family called ``name`` (an AprilTag family, or an OpenCV ArUco dictionary)."""
    if name in APRILTAG_CELLS:
        return Family(name, True, APRILTAG_CELLS[name])
    if name.startswith("tag"):
        raise AtlasError(f"AprilTag family {name!r} is not supported (tag36h11, tag25h9 and tag16h5 are)")
    d = opencv_dictionary(name)
    return Family(name, False, int(d.markerSize) + 2)

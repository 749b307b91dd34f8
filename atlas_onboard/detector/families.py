"""Marker families: their bitmaps (as printed) and how each backend reports their corners.

Conventions, locked by tests against rendered markers of known pose:

- A marker's bitmap is the printed pattern: the black square of ``cells`` x ``cells`` (border
  included) that ``size_m`` measures, inside a white quiet zone one cell wide.
- AprilTag families are printed as the AprilTag library draws them (its official images). OpenCV's
  ``DICT_APRILTAG_*`` bitmaps are the same codes rotated by 180 degrees, so we rotate them back.
- The AprilTag 3 families OpenCV does not have (tagStandard41h12, tagStandard52h13, tagCircle21h7,
  tagCircle49h12, tagCustom48h12) are drawn by the C library pupil-apriltags ships
  (``apriltag_to_image``), from the family's own code table and bit layout: their data bits lie
  partly outside the border the detector finds, so ``size_m`` (the detected square, ``cells``
  across) is smaller than the printed pattern (``total_cells`` across). Cells outside every bit
  (a circle family's corners) are black, as the library draws them.
- Corners are always returned in OpenCV's order (top-left, top-right, bottom-right, bottom-left of
  the printed marker) and OpenCV's pixel-centre convention (the centre of the top-left pixel is 0, 0).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.errors import AtlasError

APRILTAG_OPENCV = {"tag36h11": "DICT_APRILTAG_36h11", "tag25h9": "DICT_APRILTAG_25h9", "tag16h5": "DICT_APRILTAG_16h5"}
APRILTAG_CELLS = {"tag36h11": 8, "tag25h9": 7, "tag16h5": 6}
# The AprilTag 3 families only the C library draws: (cells across the detected square, across the
# printed pattern), as its family tables give them (width_at_border, total_width; tested equal).
APRILTAG3_LAYOUT = {
    "tagStandard41h12": (5, 9),
    "tagStandard52h13": (6, 10),
    "tagCircle21h7": (5, 9),
    "tagCircle49h12": (5, 11),
    "tagCustom48h12": (6, 10),
}
APRILTAG_FAMILIES = (*APRILTAG_CELLS, *APRILTAG3_LAYOUT)


@dataclass(frozen=True)
class Family:
    name: str
    is_apriltag: bool
    cells: int  # cells across the black square the detector finds (what size_m measures), border included
    total_cells: int = 0  # cells across the printed pattern without its quiet zone (0: the same as cells)

    @property
    def printed_cells(self) -> int:
        """Cells across the printed marker with its white quiet zone of one cell."""
        return (self.total_cells or self.cells) + 2

    def bitmap(self, marker_id: int, cell_px: int = 16, quiet_zone_cells: int = 1) -> NDArray[np.uint8]:
        """The printed marker, ``cell_px`` pixels a cell, with its white quiet zone."""
        if self.name in APRILTAG3_LAYOUT:
            img = library_image(self.name, marker_id)
            img = cv2.resize(img, None, fx=cell_px, fy=cell_px, interpolation=cv2.INTER_NEAREST)
        else:
            dictionary = opencv_dictionary(self.name)
            if marker_id >= dictionary.bytesList.shape[0]:
                raise AtlasError(f"marker id {marker_id} does not exist in {self.name}")
            img = cv2.aruco.generateImageMarker(dictionary, marker_id, self.cells * cell_px, borderBits=1)
            if self.is_apriltag:
                img = np.ascontiguousarray(img[::-1, ::-1])  # OpenCV's AprilTag bitmaps are upside down
        q = quiet_zone_cells * cell_px
        return cv2.copyMakeBorder(img, q, q, q, q, cv2.BORDER_CONSTANT, value=255)


_library: dict[str, object] = {}


def _apriltag_library() -> ctypes.CDLL:
    """The AprilTag C library that pupil-apriltags ships (the detector's own)."""
    lib = _library.get("lib")
    if lib is None:
        try:
            import pupil_apriltags
        except ImportError as exc:  # pragma: no cover - a dependency of the package
            raise AtlasError(f"AprilTag 3 families need pupil-apriltags: {exc}") from None
        found = sorted(Path(pupil_apriltags.__file__).parent.glob("lib*/libapriltag.so*"))
        found += sorted(Path(pupil_apriltags.__file__).parent.glob("lib*/apriltag*.dll"))
        if not found:
            raise AtlasError(f"no AprilTag C library in {Path(pupil_apriltags.__file__).parent}")
        lib = _library["lib"] = ctypes.CDLL(str(found[0]))
    return lib  # type: ignore[return-value]


def library_family_type() -> Any:
    """pupil-apriltags' ctypes structure of the C library's ``apriltag_family_t``."""
    from pupil_apriltags.bindings import _ApriltagFamily

    return _ApriltagFamily


def library_family(name: str) -> Any:
    """The C library's ``apriltag_family_t`` of ``name`` (created once, never freed)."""
    key = f"family:{name}"
    if key not in _library:
        from pupil_apriltags.bindings import _ApriltagFamily

        create = getattr(_apriltag_library(), f"{name}_create")
        create.restype = ctypes.POINTER(_ApriltagFamily)
        _library[key] = create().contents
    return _library[key]


def library_image(name: str, marker_id: int) -> NDArray[np.uint8]:
    """Marker ``marker_id`` of family ``name`` as the C library draws it (``apriltag_to_image``):
    ``total_width`` x ``total_width`` pixels, one a cell, 0 black and 255 white."""
    from pupil_apriltags.bindings import _ImageU8

    fam = library_family(name)
    if not 0 <= marker_id < fam.ncodes:
        raise AtlasError(f"marker id {marker_id} does not exist in {name} (ids 0 to {fam.ncodes - 1})")
    lib = _apriltag_library()
    lib.apriltag_to_image.restype = ctypes.POINTER(_ImageU8)
    ptr = lib.apriltag_to_image(ctypes.byref(fam), ctypes.c_uint32(marker_id))
    im = ptr.contents
    img = np.ctypeslib.as_array(im.buf, shape=(im.height, im.stride))[:, : im.width].copy()
    lib.image_u8_destroy(ptr)
    return img


def opencv_dictionary(name: str) -> cv2.aruco.Dictionary:
    key = APRILTAG_OPENCV.get(name, name)
    if not hasattr(cv2.aruco, key):
        raise AtlasError(f"marker family {name!r} cannot be rendered or detected by OpenCV")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))


def family(name: str) -> Family:
    """The family called ``name`` (an AprilTag family, or an OpenCV ArUco dictionary)."""
    if name in APRILTAG_CELLS:
        return Family(name, True, APRILTAG_CELLS[name])
    if name in APRILTAG3_LAYOUT:
        return Family(name, True, *APRILTAG3_LAYOUT[name])
    if name.startswith("tag"):
        raise AtlasError(f"AprilTag family {name!r} is not supported ({', '.join(APRILTAG_FAMILIES)} are)")
    d = opencv_dictionary(name)
    return Family(name, False, int(d.markerSize) + 2)

"""Detection backends: corners of the configured markers in a grey image.

AprilTag families go through the AprilTag 3 C library (pupil-apriltags), ArUco dictionaries through
OpenCV's ``ArucoDetector`` (with sub-pixel corner refinement). Both return corners in OpenCV's order
(top-left, top-right, bottom-right, bottom-left of the printed marker) and pixel-centre convention;
only ids present in the world file are returned (the others are counted and dropped).
"""

from __future__ import annotations

import ctypes
import threading
from collections import Counter
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector import edge_sampling, refine
from atlas_onboard.detector.families import family, library_family, library_family_type, opencv_dictionary
from atlas_onboard.errors import AtlasError

LIBRARY_SAMPLES_PER_SIDE = 12  # refine_corners's (the OpenCV backend's corners in the distorted image)


def refine_corners(gray: NDArray[np.uint8], corners: NDArray[np.float64]) -> NDArray[np.float64]:
    """Corners (4, 2), pixel-centre convention, refined on ``gray``; unchanged where a fit fails."""
    img = gray.astype(np.float32)
    lines = []
    offsets = np.arange(-edge_sampling.HALF_WIDTH_PX, edge_sampling.HALF_WIDTH_PX + 1e-9, edge_sampling.STEP_PX)
    sides = refine.sides(corners)
    if sides is None:
        return corners
    for a, d, n in sides:
        ts = np.linspace(0.15, 0.85, LIBRARY_SAMPLES_PER_SIDE)
        base = a[None, :] + ts[:, None] * d[None, :]
        pts = base[:, None, :] + offsets[None, :, None] * n[None, None, :]
        xs = pts[..., 0].astype(np.float32)
        ys = pts[..., 1].astype(np.float32)
        prof = cv2.remap(img, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        # Dark (the black border) to bright (the quiet zone) outwards: the signed gradient, so that the
        # edge of a white data cell inside the border (the other polarity) is never taken for it.
        grad = np.maximum(np.diff(prof, axis=1), 0.0)  # between consecutive samples along the normal
        k = np.argmax(grad, axis=1)
        ok = (k > 0) & (k < grad.shape[1] - 1)
        edge = []
        for row in np.flatnonzero(ok):
            g0, g1, g2 = grad[row, k[row] - 1], grad[row, k[row]], grad[row, k[row] + 1]
            denom = g0 - 2 * g1 + g2
            frac = 0.5 * (g0 - g2) / denom if denom < 0 else 0.0
            off = offsets[0] + (k[row] + 0.5 + frac) * edge_sampling.STEP_PX
            edge.append(base[row] + off * n)
        if len(edge) < 4:
            return corners
        e = np.array(edge)
        mean = e.mean(axis=0)
        _, _, vt = np.linalg.svd(e - mean)
        lines.append((mean, vt[0]))
    out = refine.crossings(lines, corners)
    return corners if out is None else out  # no fit: keep OpenCV's


@dataclass(frozen=True)
class Detection:
    """A marker found in an image: id, family, corners (4, 2) in OpenCV order and convention."""

    marker_id: int
    family: str
    corners_px: NDArray[np.float64]
    decision_margin: float = float("nan")


def _library_detector(families: str, threads: int, decimate: float) -> object:
    """A new AprilTag library detector that is never destroyed.

    pupil-apriltags 1.0.4 can crash (SIGSEGV) when a detector is destroyed after it has found tags,
    which would take the node down with it: they live as long as the process. Each holds its families'
    decoding tables (tens of MB for tag36h11), so the backends of a process share one per families and
    threads (:func:`shared_library`).

    pupil-apriltags adds every family with 2-bit error correction, whose decoding table grows with
    codes x bits^2: gigabytes for tagStandard52h13. Families whose table would pass
    MAX_DECODE_ENTRIES are added here with fewer bits (:func:`correction_bits`).
    """
    try:
        import pupil_apriltags
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise AtlasError(f"AprilTag detection needs pupil-apriltags: {exc}") from None

    class _Kept(pupil_apriltags.Detector):  # type: ignore[misc]
        def __del__(self) -> None:  # never destroyed: see above
            pass

    # pupil-apriltags 1.0.4 adds only the first family it recognises (an if/elif chain): the others,
    # and every family that needs fewer correction bits, are added here through its C library.
    names = families.split()
    first = names[0] if names and correction_bits(names[0]) == 2 else "tag16h5"
    det = _Kept(families=first, nthreads=threads, quad_decimate=decimate, refine_edges=1)
    det.atlas_families = []  # the families added here, kept alive with the detector
    if first not in names:
        det.libc.apriltag_detector_remove_family(det.tag_detector_ptr, det.tag_families[first])
    for name in names:
        if name == first:
            continue
        create = getattr(det.libc, f"{name}_create")
        create.restype = ctypes.POINTER(library_family_type())
        ptr = create()
        det.libc.apriltag_detector_add_family_bits(det.tag_detector_ptr, ptr, correction_bits(name))
        det.atlas_families.append(ptr)
    return det


@dataclass(frozen=True)
class SharedLibrary:
    """A library detector and the lock its callers hold: it is not thread-safe, and its decimation is
    set for each call."""

    detector: object
    lock: threading.Lock


_LIBRARIES: dict[tuple[str, int], SharedLibrary] = {}
_LIBRARIES_LOCK = threading.Lock()


def shared_library(families: str, threads: int) -> SharedLibrary:
    """The process's library detector of ``families`` with ``threads`` threads, made on first use.

    One for every decimation and every camera of the process: a detector's decimation is a field read
    by each search (the same results as a detector made with it), while its decoding tables (35 MB for
    tag36h11 with 2-bit correction) would otherwise be built again for each."""
    with _LIBRARIES_LOCK:
        shared = _LIBRARIES.get((families, threads))
        if shared is None:
            shared = SharedLibrary(_library_detector(families, threads, 1.0), threading.Lock())
            _LIBRARIES[(families, threads)] = shared
        return shared


MAX_DECODE_ENTRIES = 500_000
"""Largest decoding table (codes x error patterns) a family gets 2-bit correction with; beyond it 1
bit, and beyond 6 times it none (about 50 bytes an entry in the C library)."""


def correction_bits(name: str) -> int:
    """Bits of error correction the detector uses for the AprilTag family ``name``: 2 (the library's
    default) unless its decoding table would exceed MAX_DECODE_ENTRIES (tagStandard41h12: 1;
    tagStandard52h13, tagCircle49h12, tagCustom48h12: 1 or 0)."""
    fam = library_family(name)
    n, bits = int(fam.ncodes), int(fam.nbits)
    if n * (1 + bits + bits * (bits - 1) // 2) <= MAX_DECODE_ENTRIES:
        return 2
    return 1 if n * (1 + bits) <= 6 * MAX_DECODE_ENTRIES else 0


def accepted_bit_errors(name: str) -> int:
    """Bit errors a marker of family ``name`` may be read with and still be reported: an AprilTag family's
    correction bits, none for those whose codes lie close together (16h5, 21h7: bit errors give false ids)
    and none for ArUco dictionaries."""
    if not family(name).is_apriltag or _min_hamming(name) < 9:
        return 0
    return correction_bits(name)


def _min_hamming(name: str) -> int:
    """The family's minimum Hamming distance between codes, from its name (tag36h11: 11)."""
    digits = name.rpartition("h")[2]
    return int(digits) if digits.isdigit() else 0


class AprilTagBackend:
    """The AprilTag 3 library. ``decimate`` > 1 is faster and misses small markers."""

    def __init__(
        self, families: list[str], decimate: float = 1.0, threads: int = 1, extra: tuple[float, ...] = ()
    ) -> None:
        """``extra``: other decimations it will be asked for (one library detector serves them all)."""
        self.families = families
        self.decimate = float(decimate)
        self._library = shared_library(" ".join(families), threads)

    def detect(self, gray: NDArray[np.uint8], decimate: float | None = None) -> list[Detection]:
        d = float(decimate or self.decimate)
        library = self._library
        with library.lock:
            det = library.detector
            det.tag_detector_ptr.contents.quad_decimate = d  # type: ignore[attr-defined]
            found = det.detect(np.ascontiguousarray(gray))  # type: ignore[attr-defined]
        out = []
        for r in found:
            fam = r.tag_family.decode() if isinstance(r.tag_family, bytes) else str(r.tag_family)
            if r.hamming > accepted_bit_errors(fam):
                continue  # families of small code distance (16h5, 21h7) give false ids with bit errors
            # The library's corners start at the tag's bottom-left and use the pixel-corner origin.
            corners = np.asarray(r.corners, dtype=float)[[3, 2, 1, 0]] - 0.5
            out.append(Detection(int(r.tag_id), fam, corners, float(r.decision_margin)))
        return out


class ArucoBackend:
    """OpenCV's ArucoDetector for one ArUco dictionary."""

    def __init__(self, family_name: str) -> None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = 3
        self.family = family_name
        self._detector = cv2.aruco.ArucoDetector(opencv_dictionary(family_name), params)

    def detect(self, gray: NDArray[np.uint8], decimate: float | None = None) -> list[Detection]:
        corners, ids, _ = self._detector.detectMarkers(gray)
        if ids is None:
            return []
        return [
            Detection(int(i), self.family, refine_corners(gray, np.asarray(c, dtype=float).reshape(4, 2)))
            for c, i in zip(corners, ids.ravel(), strict=True)
        ]


def apriltag_families(wanted: dict[int, str]) -> list[str]:
    """The AprilTag families of ``wanted`` (marker id -> family), sorted: those of its library detector."""
    return [f for f in sorted(set(wanted.values())) if family(f).is_apriltag]


class MarkerFinder:
    """All backends a world file's markers need, filtered to the configured ids."""

    def __init__(self, wanted: dict[int, str], decimate: float = 1.0, extra: tuple[float, ...] = ()) -> None:
        """``wanted`` maps each configured marker id to its family."""
        self.wanted = wanted
        fams = sorted(set(wanted.values()))
        april = apriltag_families(wanted)
        self.backends: list[AprilTagBackend | ArucoBackend] = []
        if april:
            self.backends.append(AprilTagBackend(april, decimate, extra=extra))
        self.backends += [ArucoBackend(f) for f in fams if not family(f).is_apriltag]
        self.dropped: Counter[str] = Counter()
        self.foreign: list[Detection] = []  # the last search's tags that are not configured

    def find(self, gray: NDArray[np.uint8], decimate: float | None = None) -> list[Detection]:
        """The configured markers in ``gray``; the other tags decoded are in :attr:`foreign` until the next call."""
        out = []
        self.foreign = []
        for backend in self.backends:
            for d in backend.detect(gray, decimate):
                if self.wanted.get(d.marker_id) == d.family:
                    out.append(d)
                else:
                    self.dropped["unknown_id"] += 1
                    self.foreign.append(d)
        return out

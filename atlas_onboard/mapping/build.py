"""From frames to a marker map: detect corners, initialise, bundle-adjust, check, report.

1. Every frame of every input (recordings, videos, image folders) is searched at full resolution for
   the world file's world markers; a frame keeps the markers it shows once (an id seen twice in one
   image is dropped there and counted).
2. Markers seen in fewer than ``min_frames`` frames with another marker are left out (too rarely);
   the rest must form one co-visible set with the anchors, else the map cannot be built.
3. Initialisation: from the anchors outwards (a spanning tree of co-visible markers), each frame that
   shows mapped markers gives the camera's pose (PnP on all their corners) and, through the IPPE pose
   of each unmapped marker in it, a candidate pose for that marker; the robust mean of a marker's
   candidates maps it.
4. Bundle adjustment (:mod:`atlas_onboard.mapping.ba`) over every frame that shows two or more markers.
5. Checks, each marker against the others: the camera's pose in every frame is solved again without
   the marker, and the marker's own corners then say whether it stayed in one place (moved: two
   consistent groups in time; a duplicated id: two places, interleaved), and whether its size is
   right (its corners fitted with a free scale). A marker that fails is left out and the map solved
   again; it is named in the report.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, WorldConfig
from atlas_onboard.detector.backends import MarkerFinder
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.calibration import load as load_calibration
from atlas_onboard.detector.sources import IMAGE_SUFFIXES, SourceError
from atlas_onboard.errors import AtlasError
from atlas_onboard.mapping import ba
from atlas_onboard.mapping.recording import RecordingError, is_recording, read_frames, read_info

_logger = logging.getLogger(__name__)

MIN_FRAMES = 5  # a marker seen with another in fewer frames is not mapped
MOVE_MIN_M = 0.03  # a marker whose two groups in time lie farther apart than this has moved
MOVE_Z = 8.0  # ... and farther apart than this many standard errors
DUPLICATE_MIN_M = 0.10  # two places of one id at least this far apart: a duplicated id
MIN_CHECK_FRAMES = 8  # a marker seen with others in fewer frames is not checked
MIN_GROUP = 4  # frames in each of two groups (before and after a move, or two places)
SPLIT_GAIN = 4.0  # two poses must fit the corners this many times better (squared error) than one
MISFIT_PX = 1.0  # ... and one pose must misfit the second group by more than this (median RMS)
SIZE_GAIN = 1.5  # a free scale must fit this many times better than the world file's size
SIZE_MIN_REL = 0.03  # a marker whose fitted scale is off by more than this has the wrong size
SIZE_Z = 6.0  # ... and off by more than this many standard errors
DEGENERATE_SPREAD_DEG = 10.0  # views of a marker all within this angle of each other: a weak depth
MAX_CHECK_ROUNDS = 4
MAX_LAG_FRAMES = 30  # the residuals' autocorrelation is summed over at most this many frames


class MapError(AtlasError):
    """A map that cannot be built from the input; the message says why in one line."""


@dataclass(frozen=True)
class FrameInfo:
    """One input frame that showed at least one marker."""

    source: int  # index of the input
    index: int  # frame number within its input
    capture_time_us: int
    lens: int  # index into the inputs' lenses
    q_level_body_wxyz: tuple[float, float, float, float] | None = None


@dataclass
class Observations:
    """Every marker detection of the inputs.

    Attributes:
        frames: the frames that showed markers; lenses: one calibration per input.
        obs_frame, obs_marker_id: (N,) frame (index into ``frames``) and marker id of each detection.
        corners_px: (N, 4, 2) raw corners (distorted pixels, OpenCV order).
        sources: a name per input; mountings: the camera's pose on the body per input (or None).
        duplicates: per marker id, how many frames showed it more than once.
        unknown: per id of a marker the world file does not list (in a family it uses), how many frames
            showed it.
        detect_s: time spent reading and detecting.
    """

    frames: list[FrameInfo] = field(default_factory=list)
    lenses: list[Calibration] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)
    mountings: list[NDArray[np.float64] | None] = field(default_factory=list)
    obs_frame: list[int] = field(default_factory=list)
    obs_marker_id: list[int] = field(default_factory=list)
    corners_px: list[NDArray[np.float64]] = field(default_factory=list)
    duplicates: Counter[int] = field(default_factory=Counter)
    unknown: Counter[int] = field(default_factory=Counter)
    frames_read: int = 0
    detect_s: float = 0.0


def _input_frames(
    path: Path, calibration: Path | None, fps: float
) -> tuple[Calibration, NDArray[np.float64] | None, Iterator[tuple[int, NDArray[np.uint8], int, tuple | None]]]:
    """The lens, the camera's mounting (4x4 T_body_camera, or None) and the frames of one input."""
    if is_recording(path):
        info = read_info(path)
        mount = None
        if info.p_body_camera_m is not None and info.q_body_camera_wxyz is not None:
            w, x, y, z = info.q_body_camera_wxyz
            mount = np.eye(4)
            mount[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
            mount[:3, 3] = info.p_body_camera_m
        frames = ((f.index, f.gray, f.capture_time_us, f.q_level_body_wxyz) for f in read_frames(path))
        return info.calibration, mount, frames
    if path.is_dir() and not any(path.iterdir()):
        raise MapError(f"{path}: empty directory (no recording, no images)")
    if calibration is None:
        raise MapError(f"{path}: not a recording; a video or image folder needs --calibration")
    cal = load_calibration(calibration)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise MapError(f"{path}: no recording ({'recording.json'}) and no images in it")

        def folder() -> Iterator[tuple[int, NDArray[np.uint8], int, None]]:
            for k, f in enumerate(files):
                img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
                if img is None:
                    raise MapError(f"{f}: not a readable image")
                yield k, img, round(k * 1e6 / fps), None

        return cal, None, folder()
    if not path.is_file():
        raise MapError(f"{path}: no such file or directory")

    def video() -> Iterator[tuple[int, NDArray[np.uint8], int, None]]:
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise MapError(f"{path}: not a readable video, image folder or recording")
        rate = cap.get(cv2.CAP_PROP_FPS) or fps
        k = 0
        try:
            while True:
                ok, img = cap.read()
                if not ok or img is None:
                    break
                gray = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                yield k, gray, round(k * 1e6 / rate), None
                k += 1
        finally:
            cap.release()

    return cal, None, video()


def collect(
    inputs: list[Path],
    world: WorldConfig,
    calibration: Path | None = None,
    fps: float = 30.0,
    stride: int = 1,
    progress: Callable[[str], None] | None = None,
) -> Observations:
    """Detect the world file's world markers in every ``stride``-th frame of every input."""
    t0 = time.perf_counter()
    wanted = {m.id: m.family for m in world.markers.values() if m.entity == WORLD}
    if not wanted:
        raise MapError("the world file has no markers on the world entity to map")
    # Every configured id is searched (a drone's marker seen by chance is not taken for another).
    wanted_all = {m.id: m.family for m in world.markers.values()}
    obs = Observations()
    for s, path in enumerate(inputs):
        path = Path(path)
        try:
            cal, mount, frames = _input_frames(path, calibration, fps)
            obs.lenses.append(cal)
            obs.sources.append(str(path))
            obs.mountings.append(mount)
            finder = MarkerFinder(wanted_all, 1.0)
            n = 0
            for k, gray, stamp, q in frames:
                n += 1
                if (n - 1) % stride:
                    continue
                cal.check_size(gray.shape[1], gray.shape[0], str(path))
                found = []
                for backend in finder.backends:  # the finder's own filter, counting the ids it drops
                    for d in backend.detect(gray, 1.0):
                        if wanted_all.get(d.marker_id) == d.family:
                            found.append(d)
                        else:
                            obs.unknown[d.marker_id] += 1
                ids = Counter(d.marker_id for d in found)
                dets = []
                for d in found:
                    if ids[d.marker_id] > 1:
                        continue
                    if d.marker_id in wanted:
                        dets.append(d)
                for mid, c in ids.items():
                    if c > 1 and mid in wanted:
                        obs.duplicates[mid] += 1
                if not dets:
                    continue
                obs.frames.append(FrameInfo(s, k, stamp, s, q))
                for d in dets:
                    obs.obs_frame.append(len(obs.frames) - 1)
                    obs.obs_marker_id.append(d.marker_id)
                    obs.corners_px.append(np.asarray(d.corners_px, dtype=float).reshape(4, 2))
            obs.frames_read += n
        except (RecordingError, SourceError) as exc:
            raise MapError(str(exc)) from None
        if n == 0:
            raise MapError(f"{path}: no frames")
        if progress:
            progress(f"{path}: {n} frames read, {sum(1 for f in obs.frames if f.source == s)} with markers")
    obs.detect_s = time.perf_counter() - t0
    return obs


@dataclass(frozen=True)
class MapOptions:
    """How to anchor and solve.

    Attributes:
        anchors: ids of surveyed markers whose world-file pose is known (fixed, or held by a prior).
        anchor_sigma_m, anchor_sigma_deg: the survey's 1-sigma; 0: the anchors are fixed.
        gravity_anchor: instead of surveyed anchors, this marker defines the world frame (origin at its
            centre, heading from its axes) and the autopilot's attitude defines up.
        loss_scale_px: the robust loss's scale: residuals beyond it count less than squared.
        min_frames: a marker seen with another in fewer frames is not mapped.
    """

    anchors: tuple[int, ...] = ()
    anchor_sigma_m: float = 0.0
    anchor_sigma_deg: float = 0.0
    gravity_anchor: int | None = None
    loss_scale_px: float = 1.0
    min_frames: int = MIN_FRAMES


@dataclass
class MarkerReport:
    """What the map says of one marker (lengths in metres, angles in degrees)."""

    id: int
    size_m: float
    frames: int
    status: str  # mapped, anchor, too_rare, degenerate, moved, duplicated, wrong_size, not_seen
    M_world_marker: NDArray[np.float64] | None = None
    sigma_m: tuple[float, float, float] | None = None
    sigma_deg: tuple[float, float, float] | None = None
    rms_px: float = math.nan
    view_spread_deg: float = math.nan
    detail: str = ""


@dataclass
class MapResult:
    markers: dict[int, MarkerReport]
    frame_rms_px: NDArray[np.float64]  # per adjusted frame
    frame_names: list[str]
    solution: ba.Solution | None
    sigma0_px: float
    timings_s: dict[str, float]
    unknown_ids: dict[int, int]
    frames_read: int
    frames_used: int
    observations: int

    def mapped(self) -> dict[int, NDArray[np.float64]]:
        """The marker poses the map gives (anchors and mapped markers), 4x4 T_world_marker by id."""
        return {
            m.id: m.M_world_marker
            for m in self.markers.values()
            if m.status in ("mapped", "anchor", "degenerate") and m.M_world_marker is not None
        }


def _pose(R: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, np.ravel(t)
    return M


def _inv(M: NDArray[np.float64]) -> NDArray[np.float64]:
    return _pose(M[:3, :3].T, -M[:3, :3].T @ M[:3, 3])


class _Geometry:
    """Undistorted corners and per-detection IPPE poses, computed once."""

    def __init__(self, obs: Observations, sizes: dict[int, float]) -> None:
        self.obs = obs
        self.sizes = sizes
        n = len(obs.obs_frame)
        self.frame = np.array(obs.obs_frame, dtype=np.int64)
        self.mid = np.array(obs.obs_marker_id, dtype=np.int64)
        self.corners = np.array(obs.corners_px).reshape(n, 4, 2)
        self.und = np.empty_like(self.corners)
        frame_lens = np.array([f.lens for f in obs.frames], dtype=np.int64)
        lens_of = frame_lens[self.frame]
        for k, cal in enumerate(obs.lenses):
            sel = np.flatnonzero(lens_of == k)
            if not len(sel):
                continue
            pts = self.corners[sel].reshape(-1, 1, 2)
            if cal.fisheye:
                und = cv2.fisheye.undistortPoints(pts, cal.K, cal.dist, P=cal.K)
            elif np.any(cal.dist):
                crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
                und = cv2.undistortPoints(pts, cal.K, cal.dist, None, cal.K, criteria=crit)
            else:
                und = pts
            self.und[sel] = und.reshape(-1, 4, 2)
        self.lens_of = lens_of
        self.by_frame: dict[int, list[int]] = defaultdict(list)
        for i, f in enumerate(self.frame):
            self.by_frame[int(f)].append(i)
        self.ippe: list[NDArray[np.float64] | None] = [self._ippe(i) for i in range(n)]

    def K(self, i: int) -> NDArray[np.float64]:
        return self.obs.lenses[int(self.lens_of[i])].K

    def _ippe(self, i: int) -> NDArray[np.float64] | None:
        obj = ba.marker_corners(self.sizes[int(self.mid[i])])
        ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj, self.und[i].reshape(-1, 1, 2), self.K(i), None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        if not ok or not len(rvecs):
            return None
        return _pose(cv2.Rodrigues(rvecs[0])[0], np.ravel(tvecs[0]))

    def camera_pose(self, dets: list[int], M_world: dict[int, NDArray[np.float64]], guess: NDArray[np.float64] | None):
        """T_cam_world from the corners of ``dets`` (markers with known poses), or None."""
        obj = np.vstack([
            ba.marker_corners(self.sizes[int(self.mid[i])]) @ M_world[int(self.mid[i])][:3, :3].T
            + M_world[int(self.mid[i])][:3, 3]
            for i in dets
        ])  # fmt: skip
        img = np.vstack([self.und[i] for i in dets])
        K = self.K(dets[0])
        if guess is None:
            best = None
            for i in dets:
                if self.ippe[i] is not None:
                    cand = self.ippe[i] @ _inv(M_world[int(self.mid[i])])
                    err = _reproj(cand, obj, img, K)
                    if best is None or err < best[0]:
                        best = (err, cand)
            if best is None:
                return None
            guess = best[1]
        rvec = cv2.Rodrigues(guess[:3, :3])[0]
        tvec = guess[:3, 3].reshape(3, 1).copy()
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            return None
        return _pose(cv2.Rodrigues(rvec)[0], tvec)


def _reproj(M_cw: NDArray[np.float64], obj: NDArray[np.float64], img: NDArray[np.float64], K) -> float:
    P = obj @ M_cw[:3, :3].T + M_cw[:3, 3]
    if np.any(P[:, 2] <= 0):
        return math.inf
    px = (P[:, :2] / P[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return float(np.sqrt(np.mean(np.sum((px - img) ** 2, axis=1))))


def _robust_pose_mean(cands: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The mean of candidate poses after dropping those far from the median (IPPE flips, bad frames)."""
    P = np.array([c[:3, 3] for c in cands])
    R = Rotation.from_matrix(np.array([c[:3, :3] for c in cands]))
    med = np.median(P, axis=0)
    d = np.linalg.norm(P - med, axis=1)
    r0 = R.mean()
    ang = (r0.inv() * R).magnitude()
    keep = (d <= max(3 * np.median(d), 0.01)) & (ang <= max(3 * np.median(ang), np.radians(2)))
    if keep.sum() < 1:
        keep[:] = True
    return _pose(R[keep].mean().as_matrix(), P[keep].mean(axis=0))


def _components(pairs: set[tuple[int, int]], nodes: set[int]) -> list[set[int]]:
    adj: dict[int, set[int]] = {n: set() for n in nodes}
    for a, b in pairs:
        if a in adj and b in adj:
            adj[a].add(b)
            adj[b].add(a)
    out, seen = [], set()
    for n in sorted(nodes):
        if n in seen:
            continue
        comp, stack = set(), [n]
        while stack:
            x = stack.pop()
            if x in comp:
                continue
            comp.add(x)
            stack.extend(adj[x] - comp)
        seen |= comp
        out.append(comp)
    return out


def _initialise(
    geo: _Geometry, anchors: dict[int, NDArray[np.float64]], active: set[int]
) -> dict[int, NDArray[np.float64]]:
    """Marker poses from the anchors outwards, one ring of co-visible markers at a time."""
    known = dict(anchors)
    while True:
        cands: dict[int, list[NDArray[np.float64]]] = defaultdict(list)
        for dets in geo.by_frame.values():
            dets = [i for i in dets if int(geo.mid[i]) in active]
            have = [i for i in dets if int(geo.mid[i]) in known]
            new = [i for i in dets if int(geo.mid[i]) not in known and geo.ippe[i] is not None]
            if not have or not new:
                continue
            M_cw = geo.camera_pose(have, known, None)
            if M_cw is None:
                continue
            for i in new:
                cands[int(geo.mid[i])].append(_inv(M_cw) @ geo.ippe[i])
        if not cands:
            return known
        for mid, c in cands.items():
            known[mid] = _robust_pose_mean(c)


def build_map(obs: Observations, world: WorldConfig, options: MapOptions) -> MapResult:
    """Solve the map; MapError (one line) when the input cannot give one."""
    t_start = time.perf_counter()
    cfg = {m.id: m for m in world.markers.values() if m.entity == WORLD}
    anchor_ids = (options.gravity_anchor,) if options.gravity_anchor is not None else tuple(options.anchors)
    if not anchor_ids:
        raise MapError("no anchor: give --anchor ID (a surveyed marker) or --gravity-anchor ID")
    for a in anchor_ids:
        if a not in cfg:
            raise MapError(f"anchor {a}: no such marker on the world entity of the world file")
    if not obs.obs_frame:
        raise MapError(f"no marker of the world file was seen in {obs.frames_read} frames of the input")
    sizes = {i: m.size_m for i, m in cfg.items()}
    seen_ids = set(obs.obs_marker_id)
    missing = [a for a in anchor_ids if a not in seen_ids]
    if len(missing) == len(anchor_ids):
        raise MapError(
            f"no anchor seen: marker {', '.join(map(str, missing))} is in none of the {obs.frames_read} frames"
        )
    geo = _Geometry(obs, sizes)
    # Co-visibility counts: frames in which a marker is seen with another.
    with_other: Counter[int] = Counter()
    pairs: set[tuple[int, int]] = set()
    for dets in geo.by_frame.values():
        ids = sorted({int(geo.mid[i]) for i in dets})
        if len(ids) > 1:
            with_other.update(ids)
            pairs.update((a, b) for k, a in enumerate(ids) for b in ids[k + 1 :])
    reports: dict[int, MarkerReport] = {}
    total = Counter(int(m) for m in geo.mid)
    for mid, m in cfg.items():
        reports[mid] = MarkerReport(mid, m.size_m, total.get(mid, 0), "not_seen" if mid not in total else "mapped")
    active = {mid for mid in total if with_other[mid] >= options.min_frames or mid in anchor_ids}
    for mid in set(total) - active:
        reports[mid].status = "too_rare"
        reports[mid].detail = f"seen with another marker in {with_other[mid]} frames (need {options.min_frames})"
    seen_anchors = [a for a in anchor_ids if a in active]
    comps = _components(pairs, active)
    main = next(c for c in comps if seen_anchors[0] in c)
    others = [c for c in comps if c is not main]
    if others:
        groups = "; ".join("{" + ", ".join(map(str, sorted(c))) + "}" for c in [main, *others])
        raise MapError(f"disconnected markers: the groups {groups} are never seen together (fly between them)")
    # Anchors' poses: the world file's (surveyed), or the identity for the gravity anchor (rotated at the end).
    anchor_pose = {a: (np.eye(4) if options.gravity_anchor is not None else cfg[a].T_entity_marker.as_matrix())
                   for a in seen_anchors}  # fmt: skip
    excluded: dict[int, tuple[str, str]] = {}
    timings = {"detect_s": obs.detect_s}
    sol: ba.Solution | None = None
    for _round in range(MAX_CHECK_ROUNDS):
        use = active - set(excluded)
        t0 = time.perf_counter()
        init = _initialise(geo, anchor_pose, use)
        timings["init_s"] = timings.get("init_s", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        problem, frame_ids, marker_ids = _problem(geo, init, use, anchor_pose, options)
        sol = ba.solve(problem, f_scale_px=options.loss_scale_px)
        timings["adjust_s"] = timings.get("adjust_s", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        M_world = {mid: sol.M_world_marker[k] for k, mid in enumerate(marker_ids)}
        M_cw = {f: sol.M_cam_world[k] for k, f in enumerate(frame_ids)}
        verdicts = {mid: _check_marker(geo, mid, M_world, M_cw) for mid in marker_ids if mid not in anchor_pose}
        timings["checks_s"] = timings.get("checks_s", 0.0) + time.perf_counter() - t0
        bad = {mid: v for mid, v in verdicts.items() if v[0] != "ok"}
        if not bad:
            break
        # The worst first: one bad marker corrupts the cameras the others are checked against.
        worst = max(bad, key=lambda m: bad[m][2])
        excluded[worst] = (bad[worst][0], bad[worst][1])
        _logger.info("marker %d: %s (%s); solving again without it", worst, *excluded[worst])
    assert sol is not None
    # Report.
    R_fix = np.eye(4)
    if options.gravity_anchor is not None:
        R_fix = _gravity_frame(obs, geo, frame_ids, sol)
    marker_index = {mid: k for k, mid in enumerate(marker_ids)}
    r = sol.residuals_px
    om = problem.obs_marker
    for mid, rep in reports.items():
        if mid in excluded:
            rep.status, rep.detail = excluded[mid]
            continue
        if mid not in marker_index:
            continue
        k = marker_index[mid]
        rep.M_world_marker = R_fix @ sol.M_world_marker[k]
        sel = om == k
        rep.rms_px = float(np.sqrt(np.mean(np.sum(r[sel] ** 2, axis=-1)))) if sel.any() else math.nan
        # A marker whose corners fit worse than the map's average (a worse print, a harder view, another
        # family's corners) is as much less certain: its covariance takes its own residual variance.
        # (rms_px is a corner's 2-D error, sigma0 one coordinate's.)
        inflate = max(1.0, rep.rms_px**2 / max(2 * sol.sigma0_px**2, 1e-18)) if math.isfinite(rep.rms_px) else 1.0
        # Successive frames see a marker from nearly the same place, so their corner errors are alike,
        # not independent: the variance grows by the errors' integrated autocorrelation time.
        inflate *= _correlation_inflation(r[sel], problem.obs_frame[sel], [obs.frames[f] for f in frame_ids])
        C = sol.covariance[k] * inflate
        R3 = R_fix[:3, :3]
        rep.sigma_m = tuple(np.sqrt(np.maximum(np.diag(R3 @ C[3:, 3:] @ R3.T), 0.0)).tolist())  # type: ignore[assignment]
        rep.sigma_deg = tuple(np.degrees(np.sqrt(np.maximum(np.diag(R3 @ C[:3, :3] @ R3.T), 0.0))).tolist())  # type: ignore[assignment]
        rep.view_spread_deg = _view_spread(sol, problem, k)
        if mid in anchor_pose:
            rep.status = "anchor"
        elif rep.view_spread_deg < DEGENERATE_SPREAD_DEG:
            rep.status = "degenerate"
            rep.detail = (
                f"all views within {rep.view_spread_deg:.1f} deg of each other: depth and tilt weakly determined"
            )
    frame_rms = np.sqrt(np.mean(np.sum(r**2, axis=-1).reshape(len(r), 4), axis=1))
    per_frame = np.zeros(len(frame_ids))
    counts = np.zeros(len(frame_ids))
    np.add.at(per_frame, problem.obs_frame, frame_rms**2)
    np.add.at(counts, problem.obs_frame, 1)
    names = [f"{Path(obs.sources[obs.frames[f].source]).name}#{obs.frames[f].index}" for f in frame_ids]
    timings["total_s"] = time.perf_counter() - t_start + obs.detect_s
    return MapResult(
        reports, np.sqrt(per_frame / np.maximum(counts, 1)), names, sol, sol.sigma0_px, timings,
        dict(obs.unknown), obs.frames_read, len(frame_ids), len(problem.obs_frame),
    )  # fmt: skip


def _problem(
    geo: _Geometry,
    init: dict[int, NDArray[np.float64]],
    use: set[int],
    anchor_pose: dict[int, NDArray[np.float64]],
    options: MapOptions,
) -> tuple[ba.Problem, list[int], list[int]]:
    marker_ids = sorted(m for m in use if m in init)
    midx = {m: k for k, m in enumerate(marker_ids)}
    frame_ids, M_cw, sel_obs = [], [], []
    for f, dets in sorted(geo.by_frame.items()):
        dets = [i for i in dets if int(geo.mid[i]) in midx]
        if len(dets) < 2:
            continue
        M = geo.camera_pose(dets, init, None)
        if M is None:
            continue
        frame_ids.append(f)
        M_cw.append(M)
        sel_obs += dets
    sel = np.array(sel_obs, dtype=np.int64)
    fidx = {f: k for k, f in enumerate(frame_ids)}
    lenses = []
    for cal in geo.obs.lenses:
        # The lens model the adjustment projects with; other models are given undistorted corners.
        native = not cal.fisheye and cal.dist.size in ba.PLUMB_BOB_SIZES
        lenses.append(ba.Lens(cal.K, cal.dist if native else np.zeros(5)))
    corners = np.array([
        geo.corners[i] if not geo.obs.lenses[int(geo.lens_of[i])].fisheye
        and geo.obs.lenses[int(geo.lens_of[i])].dist.size in ba.PLUMB_BOB_SIZES else geo.und[i]
        for i in sel
    ])  # fmt: skip
    sigma_m = options.anchor_sigma_m if options.gravity_anchor is None else 0.0
    sigma_rad = math.radians(options.anchor_sigma_deg) if options.gravity_anchor is None else 0.0
    problem = ba.Problem(
        lenses=lenses,
        frame_lens=np.array([geo.obs.frames[f].lens for f in frame_ids], dtype=np.int64),
        sizes_m=np.array([geo.sizes[m] for m in marker_ids]),
        obs_frame=np.array([fidx[int(geo.frame[i])] for i in sel], dtype=np.int64),
        obs_marker=np.array([midx[int(geo.mid[i])] for i in sel], dtype=np.int64),
        corners_px=corners,
        M_world_marker=np.array([init[m] for m in marker_ids]),
        M_cam_world=np.array(M_cw),
        anchors=[ba.Anchor(midx[a], sigma_m, sigma_rad) for a in anchor_pose if a in midx],
    )
    return problem, frame_ids, marker_ids


def _correlation_inflation(
    r: NDArray[np.float64], frames: NDArray[np.int64], infos: list[FrameInfo], max_lag: int = MAX_LAG_FRAMES
) -> float:
    """The integrated autocorrelation time ``1 + 2 sum_k rho_k`` of one marker's corner residuals ``r``
    (n, 4, 2) along the frames of each input (``frames``: their adjusted-frame indices), summed over
    lags of 1, 2, ... frames while the correlation stays positive (at most ``max_lag``): how many
    times fewer independent errors the marker's sightings hold than their count."""
    v = r.reshape(len(r), -1)
    var = float(np.mean(np.sum(v * v, axis=1)))
    if var <= 0.0:
        return 1.0
    row = {(infos[f].source, infos[f].index): i for i, f in enumerate(frames)}
    tau = 1.0
    for lag in range(1, max_lag + 1):
        pairs = [(i, row[(s, k + lag)]) for (s, k), i in row.items() if (s, k + lag) in row]
        if len(pairs) < 5:
            break
        a, b = np.array(pairs).T
        rho = float(np.mean(np.sum(v[a] * v[b], axis=1))) / var
        if rho <= 0.0:
            break
        tau += 2.0 * rho
    return tau


def _view_spread(sol: ba.Solution, problem: ba.Problem, k: int) -> float:
    """The largest angle between two directions from which the marker was seen, degrees."""
    frames = np.unique(problem.obs_frame[problem.obs_marker == k])
    if len(frames) < 2:
        return 0.0
    centres = np.array([_inv(sol.M_cam_world[f])[:3, 3] for f in frames])
    d = centres - sol.M_world_marker[k][:3, 3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # The widest pair: the angle of each direction from the mean, twice the largest (cheap and close).
    mean = d.mean(axis=0)
    mean /= np.linalg.norm(mean)
    return float(np.degrees(np.arccos(np.clip(d @ mean, -1, 1)).max() + np.arccos(np.clip(d @ mean, -1, 1)).min()))


class _MarkerFit:
    """One marker's corners in many frames, the cameras held fixed (solved from the other markers)."""

    def __init__(self, geo: _Geometry, mid: int, cams: list[NDArray[np.float64]], dets: list[int]) -> None:
        self.X = ba.marker_corners(geo.sizes[mid])
        self.U = np.array([geo.und[i] for i in dets])
        self.fk = np.array([[geo.K(i)[0, 0], geo.K(i)[1, 1]] for i in dets])[:, None, :]
        self.ck = np.array([[geo.K(i)[0, 2], geo.K(i)[1, 2]] for i in dets])[:, None, :]
        self.Rc = np.array([c[:3, :3] for c in cams])
        self.tc = np.array([c[:3, 3] for c in cams])
        self.start = [_inv(c) @ geo.ippe[i] for c, i in zip(cams, dets, strict=True)]

    def fit(self, sel: NDArray[np.bool_], free_scale: bool = False) -> tuple[NDArray[np.float64], float, float, Any]:
        """(T_world_marker, scale, scale's sigma, per-frame RMS px of all frames) from the frames ``sel``."""
        M0 = _robust_pose_mean([m for m, k in zip(self.start, sel, strict=True) if k])
        idx = np.flatnonzero(sel)

        def project(x: NDArray[np.float64], rows: NDArray[np.int64]) -> NDArray[np.float64]:
            R = Rotation.from_rotvec(x[:3]).as_matrix() @ M0[:3, :3]
            Pw = (x[6] * self.X) @ R.T + M0[:3, 3] + x[3:6]
            Pc = np.einsum("nij,kj->nki", self.Rc[rows], Pw) + self.tc[rows][:, None, :]
            return Pc[..., :2] / np.maximum(Pc[..., 2:], 1e-3) * self.fk[rows] + self.ck[rows]

        def res(x: NDArray[np.float64]) -> NDArray[np.float64]:
            r = (project(x if free_scale else np.r_[x, 1.0], idx) - self.U[idx]).ravel()
            return r

        x0 = np.r_[np.zeros(6), 1.0] if free_scale else np.zeros(6)
        sol = least_squares(res, x0, loss="soft_l1", f_scale=1.0)
        x = sol.x if free_scale else np.r_[sol.x, 1.0]
        sigma_s = math.inf
        if free_scale:
            s2 = 2 * sol.cost / max(len(sol.fun) - 7, 1)
            with np.errstate(all="ignore"):
                try:
                    sigma_s = float(math.sqrt(max(np.linalg.inv(sol.jac.T @ sol.jac)[6, 6] * s2, 0.0)))
                except np.linalg.LinAlgError:
                    pass
        all_rows = np.arange(len(self.U))
        rms = np.sqrt(np.mean(np.sum((project(x, all_rows) - self.U) ** 2, axis=-1), axis=1))
        M = _pose(Rotation.from_rotvec(x[:3]).as_matrix() @ M0[:3, :3], M0[:3, 3] + x[3:6])
        return M, float(x[6]), sigma_s, rms


def _check_marker(
    geo: _Geometry, mid: int, M_world: dict[int, NDArray[np.float64]], M_cw: dict[int, NDArray[np.float64]]
) -> tuple[str, str, float]:
    """("ok" | "moved" | "duplicated" | "wrong_size", detail, strength) of one marker, checked against
    the cameras solved from the other markers of each frame (two or more of them where there are
    enough such frames, so that each camera is well determined)."""
    found: list[tuple[tuple[int, int], NDArray[np.float64], int, int]] = []
    for f, guess in M_cw.items():
        here = geo.by_frame[f]
        mine = [i for i in here if int(geo.mid[i]) == mid]
        rest = [i for i in here if int(geo.mid[i]) != mid and int(geo.mid[i]) in M_world]
        if not mine or not rest or geo.ippe[mine[0]] is None:
            continue
        M = geo.camera_pose(rest, M_world, guess)
        if M is None:
            continue
        info = geo.obs.frames[f]
        found.append(((info.source, info.capture_time_us), M, mine[0], len(rest)))
    if sum(1 for x in found if x[3] >= 2) >= MIN_CHECK_FRAMES:
        found = [x for x in found if x[3] >= 2]
    if len(found) < MIN_CHECK_FRAMES:
        return "ok", "", 0.0
    found.sort(key=lambda x: x[0])
    cams = [x[1] for x in found]
    dets = [x[2] for x in found]
    n = len(found)
    fit = _MarkerFit(geo, mid, cams, dets)
    everything = np.ones(n, dtype=bool)
    _, _, _, rms_all = fit.fit(everything)
    cost_all = float(np.sum(rms_all**2))
    # Candidate partitions: the split in time that separates the per-frame positions most, and the
    # two places the positions cluster at (2-medians); each group fitted on its own.
    P = np.array([m[:3, 3] for m in fit.start])
    spread = np.median(np.abs(P - np.median(P, axis=0)), axis=0) * 1.4826 + 1e-4
    best_k, best_z = 0, 0.0
    for k in range(MIN_GROUP, n - MIN_GROUP + 1):
        a, b = np.median(P[:k], axis=0), np.median(P[k:], axis=0)
        z = float(np.linalg.norm((a - b) / (spread * math.sqrt(1.0 / k + 1.0 / (n - k)))))
        if z > best_z:
            best_k, best_z = k, z
    candidates = []
    if best_k:
        candidates.append(("moved", np.arange(n) >= best_k))
    c0, c1 = P[np.argmin(P[:, 0])], P[np.argmax(P[:, 0])]
    lab = np.zeros(n, dtype=bool)
    for _ in range(10):
        lab = np.linalg.norm(P - c0, axis=1) > np.linalg.norm(P - c1, axis=1)
        if lab.all() or not lab.any():
            break
        c0, c1 = np.median(P[~lab], axis=0), np.median(P[lab], axis=0)
    if MIN_GROUP <= lab.sum() <= n - MIN_GROUP:
        candidates.append(("duplicated", lab))
    for kind, second in candidates:
        Ma, _, _, ra = fit.fit(~second)
        Mb, _, _, rb = fit.fit(second)
        cost_split = float(np.sum(ra[~second] ** 2) + np.sum(rb[second] ** 2))
        dist = float(np.linalg.norm(Ma[:3, 3] - Mb[:3, 3]))
        gain = cost_all / max(cost_split, 1e-9)
        # Two places, each fitting its frames far better than one place fits them all.
        if dist > MOVE_MIN_M and gain > SPLIT_GAIN and np.median(rms_all[second]) > MISFIT_PX:
            switches = int(np.sum(second[1:] != second[:-1]))
            if kind == "moved" or switches <= 2:
                k = int(np.argmax(second))
                when = f"recording {found[k][0][0] + 1}, {found[k][0][1] / 1e6:.1f} s"
                return "moved", f"moved by {dist * 100:.1f} cm (from {when} on)", gain
            if dist > DUPLICATE_MIN_M:
                return "duplicated", f"seen in two places {dist * 100:.1f} cm apart, alternately", gain
    # The size: all its corners fitted with a free scale.
    _, scale, sigma_s, rms_s = fit.fit(everything, free_scale=True)
    zs = abs(scale - 1.0) / max(sigma_s, 1e-9)
    gain = cost_all / max(float(np.sum(rms_s**2)), 1e-9)
    if abs(scale - 1.0) > SIZE_MIN_REL and zs > SIZE_Z and gain > SIZE_GAIN:
        size = geo.sizes[mid]
        return (
            "wrong_size",
            (
                f"its corners fit a marker of {size * scale * 1000:.1f} mm (+/- {size * sigma_s * 1000:.1f}),"
                f" not the world file's {size * 1000:.1f} mm"
            ),
            zs,
        )
    return "ok", "", 0.0


def _gravity_frame(obs: Observations, geo: _Geometry, frame_ids: list[int], sol: ba.Solution) -> NDArray[np.float64]:
    """T_world_anchor for the gravity anchor: origin at the marker, z up as the autopilot's attitude
    says, x the marker's x axis made level (its z axis when x is nearly vertical)."""
    ups = []
    for k, f in enumerate(frame_ids):
        info = obs.frames[f]
        mount = obs.mountings[info.source]
        if info.q_level_body_wxyz is None or mount is None:
            continue
        w, x, y, z = info.q_level_body_wxyz
        R_level_cam = Rotation.from_quat([x, y, z, w]).as_matrix() @ mount[:3, :3]
        up_cam = R_level_cam.T @ np.array([0.0, 0.0, 1.0])
        ups.append(_inv(sol.M_cam_world[k])[:3, :3] @ up_cam)  # in the anchor's frame
    if len(ups) < 3:
        raise MapError("--gravity-anchor needs the autopilot's attitude and the camera's mounting (a recording)")
    up = np.mean(ups, axis=0)
    up /= np.linalg.norm(up)
    x = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = x - (x @ up) * up
    x /= np.linalg.norm(x)
    R_anchor_world = np.column_stack([x, np.cross(up, x), up])
    return _pose(R_anchor_world.T, np.zeros(3))

"""From frames to a marker map: detect corners, initialise, bundle-adjust, check, report.

1. Every frame of every input (recordings, videos, image folders) is searched at full resolution for
   the world file's world markers; a frame keeps the markers it shows once (an id seen twice in one
   image is dropped there and counted).
2. Markers seen in fewer than ``min_frames`` frames with another marker are left out (too rarely);
   the rest fall into groups seen together: each group with an anchor is mapped (from its own
   anchors), the others are reported as unanchored.
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
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, WorldConfig
from atlas_onboard.mapping import ba
from atlas_onboard.mapping.checks import (
    _check_marker,
)
from atlas_onboard.mapping.geometry import (
    _components,
    _Geometry,
    _initialise,
    _inv,
    _pose,
)
from atlas_onboard.mapping.observations import (
    MapError,
    Observations,
)
from atlas_onboard.mapping.report import (
    MapResult,
    MarkerReport,
    _correlation_inflation,
    _view_spread,
)

_logger = logging.getLogger(__name__)

MIN_FRAMES = 5  # a marker seen with another in fewer frames is not mapped
DEGENERATE_SPREAD_DEG = 10.0  # views of a marker all within this angle of each other: a weak depth
MAX_CHECK_ROUNDS = 4


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
    # Each group of markers seen together is mapped from its own anchors; a group without one has no
    # place in the world (nothing ties it to the anchors) and is reported, not mapped.
    comps = _components(pairs, active)
    anchored = [c for c in comps if c & set(seen_anchors)]
    for c in comps:
        if c in anchored:
            continue
        group = "{" + ", ".join(map(str, sorted(c))) + "}"
        why = f"group {group} is never seen with an anchored marker: give one of them as --anchor, or fly between"
        for mid in c:
            reports[mid].status, reports[mid].detail = "unanchored", why
        active -= c
        _logger.info("markers %s: no anchor in their group, not mapped", group)
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

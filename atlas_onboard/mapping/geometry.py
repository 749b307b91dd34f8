"""The map's geometry: undistorted corners, single-marker poses, camera poses from mapped markers, and the
initial map grown from the anchors (step 3 of :mod:`atlas_onboard.mapping.build`)."""

from __future__ import annotations

import math
from collections import defaultdict

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.mapping import ba
from atlas_onboard.mapping.observations import Observations


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

"""The map's checks, each marker against the others: moved, duplicated id, wrong size (step 5 of
:mod:`atlas_onboard.mapping.build`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from atlas_onboard.mapping import ba
from atlas_onboard.mapping.geometry import _Geometry, _inv, _pose, _robust_pose_mean

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

"""Bundle adjustment of a marker map: every corner seen in every frame, one least-squares problem.

Unknowns: the pose of the camera at every frame (``T_cam_world``) and the pose of every marker that is
not a fixed anchor (``T_world_marker``). Residuals: the reprojection error of each corner, in pixels,
through the camera's lens model (pinhole with OpenCV's k1 k2 p1 p2 k3 [k4 k5 k6] distortion; other
models are given undistorted corners and no distortion). Anchors are fixed, or held near their
surveyed pose by a prior. Solved by ``scipy.optimize.least_squares`` with a robust loss (scale in
pixels) and the Jacobian's sparsity pattern (a corner depends on one camera and one marker only).

Each pose is a correction of an initial one: ``R = exp([d]x) R0`` and ``t = t0 + dt``, so a marker's
6-vector is ``[d (rad, world axes), dt (m, world)]``, and its 1-sigma uncertainty is the marker block
of ``s^2 (J^T J)^-1`` at the solution (``s^2`` the residual variance), taken by the Schur complement
of the cameras' block-diagonal part (never a dense inverse of the whole matrix).

Pure: numpy and scipy only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

PLUMB_BOB_SIZES = (0, 4, 5, 8)  # distortion vectors this module projects itself (rational with 8)


@dataclass(frozen=True)
class Lens:
    """One camera's intrinsics: K (3, 3) and OpenCV distortion (0, 4, 5 or 8 coefficients)."""

    K: NDArray[np.float64]
    dist: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))

    def coefficients(self) -> NDArray[np.float64]:
        """k1 k2 p1 p2 k3 k4 k5 k6 (8,), zero where the calibration has none."""
        d = np.zeros(8)
        raw = np.asarray(self.dist, dtype=float).ravel()
        if raw.size not in PLUMB_BOB_SIZES:
            raise ValueError(f"expected 0, 4, 5 or 8 distortion coefficients, got {raw.size}")
        d[: raw.size] = raw
        return d


def marker_corners(size_m: float) -> NDArray[np.float64]:
    """(4, 3) corners in the marker frame, OpenCV order (top-left, top-right, bottom-right, bottom-left)."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def project(lens_params: NDArray[np.float64], P_cam: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pixels (..., 2) of points ``P_cam`` (..., 3) in the optical frame; ``lens_params`` (..., 12):
    fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6, broadcast against the points."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = np.moveaxis(lens_params, -1, 0)
    z = P_cam[..., 2]
    x, y = P_cam[..., 0] / z, P_cam[..., 1] / z
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=-1)


@dataclass(frozen=True)
class Anchor:
    """A surveyed marker: fixed (sigmas 0) or held at its surveyed pose by a prior of these sigmas."""

    marker: int  # index into the problem's markers
    sigma_m: float = 0.0
    sigma_rad: float = 0.0

    @property
    def fixed(self) -> bool:
        return self.sigma_m <= 0.0 or self.sigma_rad <= 0.0


@dataclass
class Problem:
    """What the adjustment needs. Indices: F frames, M markers, N observations (a marker in a frame).

    Attributes:
        lenses: the cameras' models; ``frame_lens`` (F,) picks one per frame.
        sizes_m: (M,) black-square side of every marker, metres.
        obs_frame, obs_marker: (N,) the frame and marker of each observation.
        corners_px: (N, 4, 2) the detected corners (pixels, distorted, OpenCV order).
        M_world_marker: (M, 4, 4) initial marker poses (the anchors' surveyed ones).
        M_cam_world: (F, 4, 4) initial camera poses.
        anchors: the surveyed markers; at least one.
        prior_px: the pixel noise a prior's whitened residual is scaled to (so it weighs as corners do).
    """

    lenses: list[Lens]
    frame_lens: NDArray[np.int64]
    sizes_m: NDArray[np.float64]
    obs_frame: NDArray[np.int64]
    obs_marker: NDArray[np.int64]
    corners_px: NDArray[np.float64]
    M_world_marker: NDArray[np.float64]
    M_cam_world: NDArray[np.float64]
    anchors: list[Anchor]
    prior_px: float = 0.5


@dataclass
class Solution:
    """The adjusted map.

    Attributes:
        M_world_marker: (M, 4, 4) marker poses; M_cam_world: (F, 4, 4) camera poses.
        covariance: (M, 6, 6) of ``[rotation (rad, world axes), position (m, world)]``; zeros for a
            fixed anchor.
        residuals_px: (N, 4, 2) reprojection errors at the solution.
        sigma0_px: the residual standard deviation the covariance is scaled by.
        cost, nfev, status: from least_squares.
    """

    M_world_marker: NDArray[np.float64]
    M_cam_world: NDArray[np.float64]
    covariance: NDArray[np.float64]
    residuals_px: NDArray[np.float64]
    sigma0_px: float
    cost: float
    nfev: int
    status: int

    def position_sigma_m(self) -> NDArray[np.float64]:
        """(M, 3) 1-sigma of each marker's position along the world axes."""
        return np.sqrt(np.maximum(np.diagonal(self.covariance[:, 3:, 3:], axis1=1, axis2=2), 0.0))

    def rotation_sigma_rad(self) -> NDArray[np.float64]:
        """(M, 3) 1-sigma of each marker's rotation about the world axes."""
        return np.sqrt(np.maximum(np.diagonal(self.covariance[:, :3, :3], axis1=1, axis2=2), 0.0))


class _Layout:
    """Where each pose's 6 corrections sit in the unknown vector."""

    def __init__(self, problem: Problem) -> None:
        n_frames = len(problem.M_cam_world)
        n_markers = len(problem.M_world_marker)
        fixed = {a.marker for a in problem.anchors if a.fixed}
        self.free_markers = np.array([m for m in range(n_markers) if m not in fixed], dtype=np.int64)
        self.marker_col = np.full(n_markers, -1, dtype=np.int64)
        self.marker_col[self.free_markers] = 6 * n_frames + 6 * np.arange(len(self.free_markers))
        self.n_frames = n_frames
        self.n_params = 6 * n_frames + 6 * len(self.free_markers)


def _lens_table(problem: Problem) -> NDArray[np.float64]:
    rows = []
    for lens in problem.lenses:
        K = np.asarray(lens.K, dtype=float)
        rows.append(np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], lens.coefficients()]))
    return np.array(rows)


def _apply(
    R0: NDArray[np.float64], t0: NDArray[np.float64], x6: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    return Rotation.from_rotvec(x6[:, :3]).as_matrix() @ R0, t0 + x6[:, 3:]


def _hat(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """(..., 3, 3) cross-product matrices of vectors (..., 3)."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def _left_jacobian(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """(K, 3, 3) left Jacobians of SO(3) at rotation vectors a (K, 3): exp(a + e) = exp(Jl e) exp(a)."""
    theta = np.linalg.norm(a, axis=1)[:, None, None]
    A = _hat(a)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    c1 = np.where(small, 0.5, (1 - np.cos(th)) / th**2)
    c2 = np.where(small, 1.0 / 6.0, (th - np.sin(th)) / th**3)
    return np.eye(3) + c1 * A + c2 * (A @ A)


def _projection_jacobian(lens: NDArray[np.float64], P_c: NDArray[np.float64]) -> NDArray[np.float64]:
    """(..., 2, 3) derivative of :func:`project`'s pixels with respect to the point in the optical frame."""
    fx, fy, _, _, k1, k2, p1, p2, k3, k4, k5, k6 = np.moveaxis(lens, -1, 0)
    X, Y, Z = P_c[..., 0], P_c[..., 1], P_c[..., 2]
    x, y = X / Z, Y / Z
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    rad = num / den
    drad = (dnum * den - num * dden) / den**2  # d radial / d r2
    dxd_dx = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    dyd_dy = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    D = np.empty((*P_c.shape[:-1], 2, 3))
    # d(x, y)/dP = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
    D[..., 0, 0] = fx * dxd_dx / Z
    D[..., 0, 1] = fx * dxd_dy / Z
    D[..., 0, 2] = -fx * (dxd_dx * x + dxd_dy * y) / Z
    D[..., 1, 0] = fy * dyd_dx / Z
    D[..., 1, 1] = fy * dyd_dy / Z
    D[..., 1, 2] = -fy * (dyd_dx * x + dyd_dy * y) / Z
    return D


def solve(
    problem: Problem, loss: str = "soft_l1", f_scale_px: float = 1.0, max_nfev: int = 100, jacobian: str = "analytic"
) -> Solution:
    """Adjust the map; see the module docstring. ``f_scale_px``: the residual (pixels) beyond which
    the robust loss starts to discount a corner. ``jacobian``: ``analytic`` (the chain rule through
    the lens model) or ``numeric`` (finite differences over the sparsity pattern, ``jac_sparsity``)."""
    layout = _Layout(problem)
    F, M, N = layout.n_frames, len(problem.M_world_marker), len(problem.obs_frame)
    lens = _lens_table(problem)[problem.frame_lens[problem.obs_frame]][:, None, :]  # (N, 1, 12)
    X = np.stack([marker_corners(s) for s in problem.sizes_m])[problem.obs_marker]  # (N, 4, 3)
    R0_cw, t0_cw = problem.M_cam_world[:, :3, :3], problem.M_cam_world[:, :3, 3]
    R0_wm, t0_wm = problem.M_world_marker[:, :3, :3], problem.M_world_marker[:, :3, 3]
    of, om = problem.obs_frame, problem.obs_marker
    priors = [a for a in problem.anchors if not a.fixed]
    prior_w = np.array([[1 / a.sigma_rad] * 3 + [1 / a.sigma_m] * 3 for a in priors]).reshape(-1, 6)
    prior_idx = np.array([a.marker for a in priors], dtype=np.int64)

    def unpack(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        xm = np.zeros((M, 6))
        xm[layout.free_markers] = x[6 * F :].reshape(-1, 6)
        R_cw, t_cw = _apply(R0_cw, t0_cw, x[: 6 * F].reshape(F, 6))
        R_wm, t_wm = _apply(R0_wm, t0_wm, xm)
        return R_cw, t_cw, R_wm, t_wm, xm

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        R_cw, t_cw, R_wm, t_wm, xm = unpack(x)
        P_w = np.einsum("nij,nkj->nki", R_wm[om], X) + t_wm[om][:, None, :]
        P_c = np.einsum("nij,nkj->nki", R_cw[of], P_w) + t_cw[of][:, None, :]
        # A point behind the camera (only ever met far from the solution) projects far away.
        P_c[..., 2] = np.maximum(P_c[..., 2], 1e-3)
        r = (project(lens, P_c) - problem.corners_px).ravel()
        if len(prior_idx):
            r = np.concatenate([r, (xm[prior_idx] * prior_w).ravel() * problem.prior_px])
        return r

    sparsity = _sparsity(layout, of, om, prior_idx, N)
    free = layout.marker_col[om] >= 0
    # The Jacobian's non-zeros in the order _sparsity lists them: per observation 8 rows x 6 camera
    # columns, then (free markers) 8 rows x 6 marker columns, then the priors' diagonal.
    rows_c = np.repeat(np.arange(8 * N).reshape(N, 8, 1), 6, axis=2)
    cols_c = np.broadcast_to((6 * of)[:, None, None] + np.arange(6)[None, None, :], (N, 8, 6))
    rows_m = rows_c[free]
    cols_m = np.broadcast_to(layout.marker_col[om][free][:, None, None] + np.arange(6), (int(free.sum()), 8, 6))
    prior_rows = 8 * N + np.arange(6 * len(prior_idx))
    prior_cols = (layout.marker_col[prior_idx][:, None] + np.arange(6)).ravel() if len(prior_idx) else prior_rows
    jac_rows = np.concatenate([rows_c.ravel(), rows_m.ravel(), prior_rows])
    jac_cols = np.concatenate([cols_c.ravel(), cols_m.ravel(), prior_cols])
    shape = (8 * N + 6 * len(prior_idx), layout.n_params)

    def jac(x: NDArray[np.float64]) -> sp.csr_matrix:
        R_cw, t_cw, R_wm, t_wm, xm = unpack(x)
        Y = np.einsum("nij,nkj->nki", R_wm[om], X)  # marker corners rotated into the world, (N, 4, 3)
        P_w = Y + t_wm[om][:, None, :]
        RP = np.einsum("nij,nkj->nki", R_cw[of], P_w)
        P_c = RP + t_cw[of][:, None, :]
        P_c[..., 2] = np.maximum(P_c[..., 2], 1e-3)
        D = _projection_jacobian(lens, P_c)  # (N, 4, 2, 3)
        Jl_c = _left_jacobian(x[: 6 * F].reshape(F, 6)[:, :3])[of]  # (N, 3, 3)
        Jc = np.empty((N, 4, 2, 6))
        Jc[..., :3] = D @ (-_hat(RP) @ Jl_c[:, None])
        Jc[..., 3:] = D
        Jm = np.empty((N, 4, 2, 6))
        Jl_m = _left_jacobian(xm[:, :3])[om]
        DR = D @ R_cw[of][:, None]  # (N, 4, 2, 3)
        Jm[..., :3] = DR @ (-_hat(Y) @ Jl_m[:, None])
        Jm[..., 3:] = DR
        data = [Jc.reshape(N, 8, 6).ravel(), Jm[free].reshape(-1, 8, 6).ravel()]
        if len(prior_idx):
            data.append((prior_w * problem.prior_px).ravel())
        return sp.csr_matrix((np.concatenate(data), (jac_rows, jac_cols)), shape=shape)

    x0 = np.zeros(layout.n_params)
    analytic = jacobian == "analytic"
    # x_scale="jac" equalises the columns (radians and metres of cameras and markers) for lsmr.
    res = least_squares(
        residuals, x0, jac=jac if analytic else "2-point", jac_sparsity=None if analytic else sparsity, loss=loss,
        f_scale=f_scale_px, x_scale="jac", method="trf", tr_solver="lsmr",
        tr_options={"atol": 1e-8, "btol": 1e-8, "maxiter": 300}, max_nfev=max_nfev, xtol=1e-10, ftol=1e-9,
    )  # fmt: skip
    R_cw, t_cw, R_wm, t_wm, _ = unpack(res.x)
    M_cw = np.tile(np.eye(4), (F, 1, 1))
    M_cw[:, :3, :3], M_cw[:, :3, 3] = R_cw, t_cw
    M_wm = np.tile(np.eye(4), (M, 1, 1))
    M_wm[:, :3, :3], M_wm[:, :3, 3] = R_wm, t_wm
    dof = max(len(res.fun) - layout.n_params, 1)
    sigma0 = float(np.sqrt(2.0 * res.cost / dof))
    cov = np.zeros((M, 6, 6))
    cov[layout.free_markers] = marker_covariance(sp.csr_matrix(res.jac), F, len(layout.free_markers)) * sigma0**2
    cov[~np.isfinite(cov)] = np.inf
    r_px = res.fun[: 8 * N].reshape(N, 4, 2)
    return Solution(M_wm, M_cw, cov, r_px, sigma0, float(res.cost), int(res.nfev), int(res.status))


def _sparsity(
    layout: _Layout, of: NDArray[np.int64], om: NDArray[np.int64], prior_idx: NDArray[np.int64], N: int
) -> sp.csr_matrix:
    rows, cols = [], []
    r = np.arange(8 * N).reshape(N, 8)
    for k in range(6):
        rows.append(r.ravel())
        cols.append(np.repeat(6 * of + k, 8))
    free = layout.marker_col[om] >= 0
    for k in range(6):
        rows.append(r[free].ravel())
        cols.append(np.repeat(layout.marker_col[om][free] + k, 8))
    for i, m in enumerate(prior_idx):
        for k in range(6):
            rows.append(np.array([8 * N + 6 * i + k]))
            cols.append(np.array([layout.marker_col[m] + k]))
    n_rows = 8 * N + 6 * len(prior_idx)
    rr, cc = np.concatenate(rows), np.concatenate(cols)
    return sp.csr_matrix((np.ones(len(rr)), (rr, cc)), shape=(n_rows, layout.n_params))


def marker_covariance(J: sp.csr_matrix, n_frames: int, n_markers: int) -> NDArray[np.float64]:
    """(n_markers, 6, 6) blocks of (J^T J)^-1 for the marker columns, by the Schur complement of the
    cameras' block-diagonal part: S = H_mm - H_mc H_cc^-1 H_cm, the markers' covariance being S^-1."""
    H = (J.T @ J).tocsr()
    nc = 6 * n_frames
    blocks = np.empty((n_frames, 6, 6))
    Hcc_csr = H[:nc, :nc].tocsr()
    for k in range(6):
        for j in range(6):
            blocks[:, k, j] = np.asarray(Hcc_csr[np.arange(k, nc, 6), np.arange(j, nc, 6)]).ravel()
    inv = np.linalg.pinv(blocks, hermitian=True)
    rows = np.repeat(np.arange(nc).reshape(n_frames, 6), 6, axis=1).ravel()
    cols = np.tile(np.arange(nc).reshape(n_frames, 6), (1, 6)).ravel()
    Hcc_inv = sp.csr_matrix((inv.reshape(n_frames, 36).ravel(), (rows, cols)), shape=(nc, nc))
    Hcm = H[:nc, nc:]
    S = H[nc:, nc:].toarray() - (Hcm.T @ Hcc_inv @ Hcm).toarray()
    lam, V = np.linalg.eigh((S + S.T) / 2.0)
    # Directions the corners do not determine (a marker seen only where nothing else fixes the camera)
    # have no finite covariance: the markers they involve get an infinite one.
    weak = lam <= 1e-9 * max(float(lam.max(initial=0.0)), 1e-300)
    C = (V[:, ~weak] / lam[~weak]) @ V[:, ~weak].T
    idx = np.arange(6 * n_markers).reshape(n_markers, 6)
    out = C[idx[:, :, None], idx[:, None, :]]
    if weak.any():
        involved = np.abs(V[:, weak]).max(axis=1).reshape(n_markers, 6).max(axis=1) > 1e-6
        out[involved] = np.diag(np.full(6, np.inf))
    return out

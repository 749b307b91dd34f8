"""A small synthetic mapping problem with known truth: markers on a floor and a wall, a camera moving
over them, corners projected through a distorted lens with Gaussian pixel noise."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.mapping.ba import Anchor, Lens, Problem, marker_corners, project

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.08, 0.02, 0.0005, -0.0003, 0.0])


def pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


def truth_markers(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(M, 4, 4) marker poses and (M,) sizes: 9 on the floor, 3 on the wall at x = 2.2 m."""
    poses, sizes = [], []
    for i, (x, y) in enumerate([(gx, gy) for gx in (-1.0, 0.0, 1.0) for gy in (-0.8, 0.0, 0.8)]):
        R = Rotation.from_euler("z", rng.uniform(-20, 20), degrees=True).as_matrix()
        poses.append(pose(R, np.array([x, y, 0.0])))
        sizes.append(0.16 if i % 2 else 0.2)
    for y in (-0.6, 0.0, 0.6):
        # Facing -x: marker z (out of the face) along world -x, marker y up along world z.
        R = np.column_stack([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
        poses.append(pose(R, np.array([2.2, y, 1.0])))
        sizes.append(0.2)
    return np.array(poses), np.array(sizes)


def camera_poses(rng: np.random.Generator, n: int, M_wm: np.ndarray) -> np.ndarray:
    """(n, 4, 4) T_cam_world of a camera 1-2 m from a point between markers, looking at it."""
    out = []
    for _ in range(n):
        a, b = M_wm[rng.integers(len(M_wm), size=2), :3, 3]
        target = a + rng.uniform(0.0, 1.0) * (b - a) + rng.normal(0.0, 0.1, 3)
        normal = np.array([0.0, 0.0, 1.0]) if target[0] < 1.5 else np.array([-1.0, 0.0, 0.3])
        d = normal / np.linalg.norm(normal) + rng.normal(0.0, 0.35, 3)
        c = target + rng.uniform(1.2, 2.0) * d / np.linalg.norm(d)
        z = target - c
        z /= np.linalg.norm(z)
        x = np.cross(z, rng.normal(0.0, 1.0, 3))
        x /= np.linalg.norm(x)
        R_wc = np.column_stack([x, np.cross(z, x), z])
        out.append(np.linalg.inv(pose(R_wc, c)))
    return np.array(out)


def visible_corners(lens_row: np.ndarray, Mc: np.ndarray, Mm: np.ndarray, size: float) -> np.ndarray | None:
    """The marker's four corners in the image (px), or None when the camera would not see it whole: a
    corner nearer than 0.3 m, seen more than 70 deg off its face, or within 5 px of the border."""
    X = marker_corners(size) @ Mm[:3, :3].T + Mm[:3, 3]
    P = X @ Mc[:3, :3].T + Mc[:3, 3]
    if np.any(P[:, 2] < 0.3):
        return None
    normal_c = Mc[:3, :3] @ Mm[:3, 2]
    centre = P.mean(axis=0)
    if normal_c @ (-centre / np.linalg.norm(centre)) < np.cos(np.radians(70)):
        return None
    px = project(lens_row, P)
    if np.any(px < 5) or np.any(px[:, 0] > 634) or np.any(px[:, 1] > 474):
        return None
    return px


def make_problem(
    seed: int, n_frames: int = 40, noise_px: float = 0.3, init_error: float = 0.02
) -> tuple[Problem, np.ndarray, np.ndarray]:
    """The problem (initial poses perturbed from the truth), the true markers and cameras."""
    rng = np.random.default_rng(seed)
    M_wm, sizes = truth_markers(np.random.default_rng(0))
    M_cw = camera_poses(rng, n_frames, M_wm)
    lens_row = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], DIST, [0.0, 0.0, 0.0]])
    frames, markers, corners = [], [], []
    for f, Mc in enumerate(M_cw):
        for m, Mm in enumerate(M_wm):
            px = visible_corners(lens_row, Mc, Mm, sizes[m])
            if px is None:
                continue
            frames.append(f)
            markers.append(m)
            corners.append(px + rng.normal(0.0, noise_px, (4, 2)))
    M0_wm = np.array([_perturb(rng, M, init_error) for M in M_wm])
    M0_wm[0] = M_wm[0]
    M0_cw = np.array([_perturb(rng, M, init_error) for M in M_cw])
    problem = Problem(
        lenses=[Lens(K, DIST)], frame_lens=np.zeros(n_frames, dtype=np.int64), sizes_m=sizes,
        obs_frame=np.array(frames), obs_marker=np.array(markers), corners_px=np.array(corners),
        M_world_marker=M0_wm, M_cam_world=M0_cw, anchors=[Anchor(0)],
    )  # fmt: skip
    return problem, M_wm, M_cw


def _perturb(rng: np.random.Generator, M: np.ndarray, err: float) -> np.ndarray:
    R = Rotation.from_rotvec(rng.normal(0.0, err, 3)).as_matrix() @ M[:3, :3]
    return pose(R, M[:3, 3] + rng.normal(0.0, err, 3))


def make_observations(
    seed: int,
    n_frames: int = 120,
    noise_px: float = 0.3,
    moved: tuple[int, float] | None = None,
    true_size: tuple[int, float] | None = None,
    hidden: set[int] = frozenset(),
    attitude: bool = False,
):
    """Observations of the synthetic room as :func:`atlas_onboard.mapping.build.collect` gives them,
    and a world file listing its markers (ids 0..11, all world markers). ``moved``: (marker, metres)
    moved along world x after the first half of the frames; ``true_size``: (marker, size) printed at
    another size than the world file says; ``hidden``: markers that are never seen; ``attitude``: each
    frame carries the camera's attitude (the body is the camera) in a level frame turned by 30 deg."""
    from atlas_onboard.config import parse_world
    from atlas_onboard.detector.calibration import Calibration
    from atlas_onboard.mapping.observations import FrameInfo, Observations

    rng = np.random.default_rng(seed)
    M_wm, sizes = truth_markers(np.random.default_rng(0))
    M_cw = camera_poses(rng, n_frames, M_wm)
    lens_row = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], DIST, [0.0, 0.0, 0.0]])
    obs = Observations(lenses=[Calibration(640, 480, K, DIST)], sources=["synthetic"],
                       mountings=[np.eye(4) if attitude else None])  # fmt: skip
    R_level_world = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    obs.frames_read = n_frames
    for f, Mc in enumerate(M_cw):
        dets = []
        for m, Mm in enumerate(M_wm):
            if m in hidden:
                continue
            Mm = Mm.copy()
            size = sizes[m]
            if moved is not None and m == moved[0] and f >= n_frames // 2:
                Mm[0, 3] += moved[1]
            if true_size is not None and m == true_size[0]:
                size = true_size[1]
            px = visible_corners(lens_row, Mc, Mm, size)
            if px is None:
                continue
            dets.append((m, px + rng.normal(0.0, noise_px, (4, 2))))
        if not dets:
            continue
        q = None
        if attitude:
            x, y, z, w = Rotation.from_matrix(R_level_world @ Mc[:3, :3].T).as_quat()
            q = (w, x, y, z)
        obs.frames.append(FrameInfo(0, f, round(f * 1e6 / 15), 0, q))
        for m, c in dets:
            obs.obs_frame.append(len(obs.frames) - 1)
            obs.obs_marker_id.append(m)
            obs.corners_px.append(c)
    markers = []
    for m, Mm in enumerate(M_wm):
        x, y, z, w = Rotation.from_matrix(Mm[:3, :3]).as_quat()
        markers.append(
            {
                "id": m,
                "size_m": float(sizes[m]),
                "pose": {"pos": [float(v) for v in Mm[:3, 3]], "rot": {"w": w, "x": x, "y": y, "z": z}},
            }
        )
    world = parse_world({"entities": {"world": {"markers": markers}}})
    return obs, world, M_wm

"""The refinement's records against known answers: a pose's largest 1-sigma in position and rotation
along its worst direction, and an estimate's per-axis sigmas in the world's axes."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.refine.records import Estimate, WorldMarkerPose


def _cov(pos_sigmas, rot_sigmas_rad, R_pos: np.ndarray | None = None, R_rot: np.ndarray | None = None) -> np.ndarray:
    R_pos = np.eye(3) if R_pos is None else R_pos
    R_rot = np.eye(3) if R_rot is None else R_rot
    cov = np.zeros((6, 6))
    cov[:3, :3] = R_pos @ np.diag(np.square(pos_sigmas)) @ R_pos.T
    cov[3:, 3:] = R_rot @ np.diag(np.square(rot_sigmas_rad)) @ R_rot.T
    return cov


@settings(max_examples=50, deadline=None)
@given(
    pos=st.lists(st.floats(1e-4, 1.0), min_size=3, max_size=3),
    rot=st.lists(st.floats(1e-4, 0.5), min_size=3, max_size=3),
    seed=st.integers(0, 2**31),
)
def test_the_largest_sigma_is_along_the_worst_direction_whatever_the_axes(pos, rot, seed):
    rng = np.random.default_rng(seed)
    R1, R2 = Rotation.random(2, rng=rng).as_matrix()
    pose = WorldMarkerPose(3, np.zeros(3), np.eye(3), _cov(pos, rot, R1, R2))
    assert math.isclose(pose.max_sigma_m, max(pos), rel_tol=1e-9)
    assert math.isclose(pose.max_sigma_deg, math.degrees(max(rot)), rel_tol=1e-9)


def _estimate(R_world_marker: np.ndarray, cov: np.ndarray) -> Estimate:
    return Estimate(5, np.zeros(3), R_world_marker, cov, 10, 0, 4, 30.0, np.zeros(3), 0.0, 0.0)


def test_an_estimates_sigmas_are_along_the_world_axes():
    # Rotation sigmas about the marker's axes 1, 2, 3 deg; the marker turned 90 deg about world z:
    # its x axis is the world's y, its y axis the world's -x.
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    est = _estimate(R, _cov([0.01, 0.02, 0.03], np.radians([1.0, 2.0, 3.0])))
    np.testing.assert_allclose(est.sigma_m, [0.01, 0.02, 0.03], rtol=1e-12)
    np.testing.assert_allclose(est.sigma_deg, [2.0, 1.0, 3.0], rtol=1e-9)
    assert math.isclose(est.max_sigma_deg, 3.0, rel_tol=1e-9)

"""The leave-one-out placement's rotation vectors (placement.rotvecs_from_matrices) against scipy's, which
they replace there: any rotation, near the identity (the Taylor branch) and near a half turn."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.refine.placement import rotvecs_from_matrices

angle = st.one_of(st.floats(0.0, 2e-3), st.floats(0.0, np.pi - 1e-6), st.floats(np.pi - 1e-3, np.pi - 1e-9))
axis = st.tuples(*[st.floats(-1.0, 1.0) for _ in range(3)]).filter(lambda v: float(np.dot(v, v)) > 1e-6)


@settings(max_examples=300, deadline=None)
@given(angles=st.lists(angle, min_size=1, max_size=12), axes=st.lists(axis, min_size=12, max_size=12), turn=axis)
def test_rotvecs_are_scipys(angles: list[float], axes: list[tuple[float, float, float]], turn: tuple) -> None:
    """Products of rotations (as the residuals have them): scipy's rotation vectors to a few ulps."""
    a = np.array(axes[: len(angles)], dtype=float)
    rotvecs = a / np.linalg.norm(a, axis=1, keepdims=True) * np.array(angles)[:, None]
    R_ref = Rotation.from_rotvec(np.array(turn, dtype=float)).as_matrix()
    R = R_ref.T @ (Rotation.from_rotvec(rotvecs).as_matrix() @ R_ref)
    want = Rotation.from_matrix(R).as_rotvec()
    np.testing.assert_allclose(rotvecs_from_matrices(R), want, rtol=0.0, atol=1e-14)

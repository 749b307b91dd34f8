"""Ground-truth motions shared by the EKF's tests."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def oscillating(t):
    """Paper-test1's drone: a 0.6 m/s path plus 3 cm of oscillation at 1.2 Hz (1.7 m/s^2), tilting 10 deg."""
    w = 2 * np.pi * 1.2
    p = np.array([0.6 * t, 0.3 * np.sin(0.5 * t), 1.5])
    p = p + np.array([0.03, 0.03, 0.01]) * np.sin(w * t + np.array([0.0, 1.0, 2.0]))
    q = Rotation.from_rotvec(np.radians(10) * np.array([np.sin(w * t + 1.0), -np.sin(w * t), 0.3 * t]))
    return p, q

"""Shared test helpers: in-memory world files and exact observations from ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import WorldConfig, parse_world
from atlas_onboard.core.markerdata import MarkerData

PAPER_FUSION = {  # the paper's method, every key listed (the gate, the attitude's ageing): as the runs set it
    "method": "paper",
    "path": "bfs",
    "weighting": "sigma_min",
    "age_sigma_m_per_s": 0.0,
    "ema_alpha": 1.0,
    "outlier_gate_sigma": 0.0,
    "filter": "none",
}


def world_from(doc: dict[str, Any]) -> WorldConfig:
    return parse_world(doc)


def pose(p: list[float], rpy_deg: list[float] | None = None) -> RigidTransform:
    rot = Rotation.identity() if rpy_deg is None else Rotation.from_euler("ZYX", rpy_deg[::-1], degrees=True)
    return RigidTransform.from_components(np.asarray(p, dtype=float), rot)


def observe(
    world: WorldConfig,
    truth: dict[str, RigidTransform],
    sensor_id: int,
    marker_id: int,
    sigma_m: float = 0.01,
    capture_time_us: int = 0,
    T_noise: RigidTransform | None = None,
) -> MarkerData:
    """The exact MarkerData a perfect sensor would report, given every entity's true world pose."""
    s = world.sensors[sensor_id]
    m = world.markers[marker_id]
    T_world_sensor = truth[s.entity] * s.T_entity_sensor
    T_world_marker = truth[m.entity] * m.T_entity_marker
    T_sensor_marker = T_world_sensor.inv() * T_world_marker
    if T_noise is not None:
        T_sensor_marker = T_sensor_marker * T_noise
    p = T_sensor_marker.translation
    x, y, z, w = T_sensor_marker.rotation.as_quat()
    return MarkerData(
        sensor_id=sensor_id,
        marker_id=marker_id,
        sigma_m=sigma_m,
        p_sensor_marker_m=(float(p[0]), float(p[1]), float(p[2])),
        q_sensor_marker_wxyz=(float(w), float(x), float(y), float(z)),
        capture_time_us=capture_time_us,
    )


def assert_pose_close(
    p: np.ndarray, q_xyzw: np.ndarray, T_true: RigidTransform, pos_tol_m: float = 1e-9, ang_tol_rad: float = 1e-9
) -> None:
    err_p = float(np.linalg.norm(np.asarray(p) - T_true.translation))
    err_a = float((Rotation.from_quat(q_xyzw).inv() * T_true.rotation).magnitude())
    assert err_p <= pos_tol_m, f"position error {err_p} m > {pos_tol_m}"
    assert err_a <= ang_tol_rad, f"angle error {err_a} rad > {ang_tol_rad}"


DATA = Path(__file__).resolve().parent / "data"


def write_ubiquity_calibration(path: Path) -> Path:
    """The ROS camera_info calibration of the Ubiquity Robotics photos (tests/data/ubiquity), written to ``path``."""
    cams = yaml.safe_load((DATA / "ubiquity" / "cameras.yaml").read_text())["test_png_and_403"]
    path.write_text(
        yaml.safe_dump(
            {
                "image_width": 1280, "image_height": 960, "distortion_model": "plumb_bob",
                "camera_matrix": {"rows": 3, "cols": 3, "data": cams["K"]},
                "distortion_coefficients": {"rows": 1, "cols": 5, "data": cams["D"]},
            }
        )
    )  # fmt: skip
    return path

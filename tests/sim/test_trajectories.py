"""Trajectories' true motion: body rates and velocities against analytic derivatives and against the
poses they must integrate to; the vibration is added to the pose without tilting the vehicle."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.sim import scenarios
from atlas_onboard.sim import trajectories as tj

T = np.linspace(0.3, 29.7, 37)


def test_body_rates_of_a_pure_yaw_swing_are_the_analytic_yaw_rate():
    drone = tj.Quadrotor(tj.lissajous((0, 0, 1), (0, 0, 0), (0.1, 0.1, 0.1)), tj.slow_yaw(10.0, 40.0, 9.0))
    w = drone.body_rates(T)
    yaw_rate = math.radians(40.0) * 2 * math.pi / 9.0 * np.cos(2 * math.pi * T / 9.0)
    np.testing.assert_allclose(w[:, 2], yaw_rate, atol=1e-7)
    np.testing.assert_allclose(w[:, :2], 0.0, atol=1e-7)


def test_body_rates_turn_each_attitude_into_the_next():
    drone = scenarios.get("rolling").trajectories["drone"]
    dt = 1e-3
    _, q0 = drone.pose(T)
    _, q1 = drone.pose(T + dt)
    w = drone.body_rates(T + dt / 2)  # the mid-point rate turns R(t) into R(t + dt) to third order
    predicted = Rotation.from_quat(q0) * Rotation.from_rotvec(w * dt)
    assert (predicted.inv() * Rotation.from_quat(q1)).magnitude().max() < 1e-8
    assert np.abs(w).max() > 0.3  # it does turn (yaw swings, sway, vibration)


def test_vibration_moves_the_pose_with_its_analytic_velocity_and_tilts_nothing_else():
    vib = tj.Vibration(0.3, 0.003, 2.0, seed=4)
    still = tj.Quadrotor(tj.lissajous((0, 0, 1), (0, 0, 0), (0.1, 0.1, 0.1)), tj.constant_yaw(0.0))
    shaken = tj.Quadrotor(still.path, still.yaw, vibration=vib)
    dp, d_rp = vib.offsets(T)
    p0, _ = still.pose(T)
    p1, q1 = shaken.pose(T)
    np.testing.assert_allclose(p1 - p0, dp, atol=1e-12)
    rpy = Rotation.from_quat(q1).as_euler("ZYX")[:, ::-1]
    np.testing.assert_allclose(rpy[:, :2], d_rp, atol=1e-12)  # the 3 mm shake adds no thrust tilt
    assert np.abs(d_rp).max() == pytest.approx(math.radians(0.3), rel=0.05)
    phase = np.random.default_rng(4).uniform(0, 2 * np.pi, 5)[:3]
    v = 0.003 * 2 * math.pi * 2.0 * np.cos(2 * math.pi * 2.0 * T[:, None] + phase[None, :])
    np.testing.assert_allclose(shaken.velocity(T), v, atol=1e-6)

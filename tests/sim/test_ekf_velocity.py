"""The simulated autopilot's EKF velocity: the truth plus a wandering error of its stated spread, a drift
while no vision comes that the filter pulls back once it does, in the autopilot's own heading."""

import math

import numpy as np
import pytest

from atlas_onboard.sim.ekf_velocity import EkfVelocity, EkfVelocityNoise

TRUE = np.array([0.6, -0.3, 0.1])


def test_with_vision_the_error_has_the_stated_spread_and_no_drift():
    noise = EkfVelocityNoise()
    errors = []
    for seed in range(400):  # independent runs, each read for 2 s at 30 Hz with fresh vision
        ekf = EkfVelocity(noise, seed)
        for k in range(60):
            v = ekf.read(k / 30.0, TRUE, 0.03)
        errors.append(v - TRUE)
    spread = np.std(errors, axis=0)
    assert np.all(np.abs(spread / noise.sigma_m_s - 1.0) < 0.15)  # 400 samples: the std within ~7 % (2 sigma)
    assert np.all(np.abs(np.mean(errors, axis=0)) < 4 * noise.sigma_m_s / math.sqrt(400))


def test_without_vision_it_drifts_by_its_accelerometer_bias_and_recovers_with_vision():
    noise = EkfVelocityNoise(sigma_m_s=0.0, accel_bias_sigma=0.05)
    ekf = EkfVelocity(noise, 3)
    bias = ekf._accel_bias.copy()
    ekf.read(0.0, TRUE, 0.01)
    for k in range(1, 31):  # one second without vision
        v = ekf.read(k / 30.0, TRUE, 0.3 + k / 30.0)
    np.testing.assert_allclose(v - TRUE, bias * 1.0, atol=1e-12)
    for k in range(31, 31 + 60):  # two seconds with vision: four recovery times
        v = ekf.read(k / 30.0, TRUE, 0.01)
    assert np.abs(v - TRUE).max() < np.abs(bias).max() * math.exp(-3.9)


def test_ned_in_the_autopilots_heading():
    """A body flying north in the world whose autopilot reads every heading 30 deg further east (ATTITUDE's
    yaw offset): in the autopilot's frame it flies 30 deg east of north (NED: north cos 30, east sin 30)."""
    ekf = EkfVelocity(EkfVelocityNoise(sigma_m_s=0.0, accel_bias_sigma=0.0), 0)
    vn, ve, vd = ekf.read_ned(0.0, np.array([0.0, 1.0, 0.2]), 0.01, 30.0)
    assert (vn, ve, vd) == pytest.approx((math.cos(math.radians(30)), math.sin(math.radians(30)), -0.2))

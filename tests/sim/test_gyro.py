"""The simulated autopilot's gyros: white noise of the stated density, a bias of the stated size that
wanders slowly, both measured against the true rates they are added to."""

import math

import numpy as np
import pytest

from atlas_onboard.sim.gyro import Gyro, GyroNoise

HZ = 50.0


def _readings(noise: GyroNoise, seed: int, seconds: float):
    """Readings, true rates and the gyro's bias at each reading (N, 3) of a body swinging about all axes."""
    g = Gyro(noise, seed)
    t = np.arange(int(seconds * HZ)) / HZ
    truth = np.stack([0.8 * np.sin(2 * np.pi * 0.3 * t), 0.3 * np.cos(2 * np.pi * 2.0 * t), 0.5 + 0 * t], axis=1)
    readings, biases = np.empty_like(truth), np.empty_like(truth)
    for i in range(len(t)):
        readings[i] = g.read(float(t[i]), truth[i], HZ)
        biases[i] = g.bias
    return readings, truth, biases


def test_white_noise_has_the_stated_density_and_is_uncorrelated():
    noise = GyroNoise()
    readings, truth, biases = _readings(noise, seed=3, seconds=600.0)
    white = readings - truth - biases
    sigma = noise.density * math.sqrt(HZ)
    n = len(white)
    # The sample standard deviation of n normal draws is within 4 / sqrt(2 n) of sigma (relative).
    assert np.all(np.abs(white.std(axis=0) / sigma - 1.0) < 4.0 / math.sqrt(2 * n))
    assert np.all(np.abs(white.mean(axis=0)) < 4.0 * sigma / math.sqrt(n))
    lag1 = [np.corrcoef(white[:-1, k], white[1:, k])[0, 1] for k in range(3)]
    assert np.all(np.abs(lag1) < 4.0 / math.sqrt(n))


def test_the_bias_is_what_the_readings_average_to_and_wanders_slowly():
    noise = GyroNoise()
    readings, truth, biases = _readings(noise, seed=5, seconds=120.0)
    error = readings - truth
    per = int(10 * HZ)  # 10 s windows: the bias shows as the mean error
    sigma = noise.density * math.sqrt(HZ)
    for k in range(0, len(error), per):
        window = error[k : k + per]
        assert np.all(np.abs(window.mean(axis=0) - biases[k : k + per].mean(axis=0)) < 4.0 * sigma / math.sqrt(per))
    # Over two minutes (well under its correlation time) the bias moves by a fraction of its size.
    drift = np.abs(biases[-1] - biases[0])
    expected = noise.bias_sigma * math.sqrt(2.0 * (1.0 - math.exp(-120.0 / noise.bias_tau_s)))
    assert np.all(drift < 4.0 * expected)
    assert np.any(drift > 0.0)


def test_the_bias_has_the_stated_size_across_gyros():
    noise = GyroNoise()
    first = np.array([Gyro(noise, seed).bias for seed in range(400)])  # 1200 draws
    assert first.std() == pytest.approx(noise.bias_sigma, rel=4.0 / math.sqrt(2 * first.size))
    assert abs(first.mean()) < 4.0 * noise.bias_sigma / math.sqrt(first.size)

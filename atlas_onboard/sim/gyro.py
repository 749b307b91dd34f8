"""The simulated autopilot's angular rates: what its gyros report of a body's true rates.

A MEMS gyro's reading is the true rate plus white noise (its angular random walk, a density in
rad/s/sqrt(Hz)) and a bias that wanders slowly (a first-order Gauss-Markov process: it keeps about the
same size, turning over in ``bias_tau_s``). Samples are taken at a stream's rate, each the average
of the rate over the interval since the last, so the white noise's standard deviation per sample is
the density times the square root of the rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class GyroNoise:
    """A gyro's errors, per axis: white noise density (rad/s/sqrt(Hz)), the bias's standard deviation
    (rad/s) and its correlation time (s). The defaults are a flight controller's MEMS gyro (an
    ICM-42688-class part after the autopilot's filtering)."""

    density: float = 0.003
    bias_sigma: float = 0.003
    bias_tau_s: float = 300.0


class Gyro:
    """Readings of one gyro triad in time order (``read``), from its own seeded random stream."""

    def __init__(self, noise: GyroNoise, seed: int) -> None:
        self.noise = noise
        self._rng = np.random.default_rng(seed)
        self.bias = self._rng.normal(0.0, noise.bias_sigma, 3)
        self._last_s: float | None = None

    def read(self, t_s: float, true_rate: NDArray[np.float64], rate_hz: float) -> NDArray[np.float64]:
        """The reading (3,) rad/s at ``t_s`` of a body turning at ``true_rate`` (3,) rad/s, sampled at
        ``rate_hz``: the bias walks over the time since the previous reading first."""
        n = self.noise
        if self._last_s is not None and n.bias_tau_s > 0:
            a = math.exp(-max(t_s - self._last_s, 0.0) / n.bias_tau_s)
            self.bias = a * self.bias + n.bias_sigma * math.sqrt(1.0 - a * a) * self._rng.normal(0.0, 1.0, 3)
        self._last_s = t_s
        white = n.density * math.sqrt(max(rate_hz, 0.0)) * self._rng.normal(0.0, 1.0, 3)
        return np.asarray(true_rate, dtype=float) + self.bias + white

    def read_frd(
        self, t_s: float, true_rate_flu: NDArray[np.float64] | None, rate_hz: float
    ) -> tuple[float, float, float]:
        """:meth:`read` of a body rate about FLU (None: none known, zeros) in the body FRD axes, ATTITUDE's."""
        if true_rate_flu is None:
            return (0.0, 0.0, 0.0)
        x, y, z = self.read(t_s, np.asarray(true_rate_flu, dtype=float), rate_hz)
        return (float(x), float(-y), float(-z))  # FLU -> FRD

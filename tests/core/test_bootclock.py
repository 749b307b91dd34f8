"""The autopilot's boot time mapped to the wall clock, through a drifting clock and a jittery link."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.core.attitude import AttitudeHistory
from atlas_onboard.core.bootclock import BootClock


def test_boot_clock_converges_on_the_smallest_lag_and_restarts_after_a_reboot():
    c = BootClock()
    assert c.wall_us(2_000_000, 7_000_000 + 9_000) == 7_000_000 + 9_000  # first: arrival
    assert c.wall_us(2_001_000, 7_001_000 + 3_000) == 7_001_000 + 3_000  # a smaller lag wins
    assert c.wall_us(2_002_000, 7_002_000 + 20_000) == 7_002_000 + 3_000  # a late arrival is not believed
    assert c.wall_us(0, 9_000_000) == 9_000_000  # boot time went back: a reboot


def _drifting_link(ppm: float, hours: float, hz: float, floor_us: int, seed: int):
    """A stream of (true wall time us, time_boot_ms in us, arrival us) from an autopilot whose clock runs
    ``ppm`` parts per million fast (negative: slow), over a link with a delay of ``floor_us`` plus an
    exponential part (mean 2 ms) and, one packet in a hundred, a 50 ms spike."""
    rng = np.random.default_rng(seed)
    n = int(hours * 3600 * hz)
    t_wall_us = 1_700_000_000_000_000 + np.round(np.arange(n) / hz * 1e6).astype(np.int64)
    boot_us = ((np.arange(n) / hz + 12.3) * (1.0 + ppm * 1e-6) * 1e3).astype(np.int64) * 1000  # whole ms
    delay_us = floor_us + rng.exponential(2_000.0, n) + 50_000.0 * (rng.random(n) < 0.01)
    return t_wall_us, boot_us, t_wall_us + delay_us.astype(np.int64)


@pytest.mark.parametrize(
    ("ppm", "hours"), [(-20_000, 0.25), (-1_000, 0.25), (-50, 1.0), (50, 1.0), (1_000, 0.25), (20_000, 0.25)]
)
def test_boot_clock_follows_a_drifting_autopilot_clock(ppm, hours):
    # Mapped stamps are late by the link's delay floor, less up to the 1 ms that time_boot_ms truncates,
    # plus the envelope's own error (a fraction of a millisecond here): within floor +- 2 ms after the
    # first 10 s (while the samples span under a second the rate is unknown: up to 20 ms behind at 2 %).
    floor_us, hz = 3_000, 12.5  # samples 80 ms apart: within the history's gap
    t_wall, boot, arrival = _drifting_link(ppm, hours, hz, floor_us, seed=abs(ppm) % 97 + (ppm > 0))
    clock, history = BootClock(), AttitudeHistory()
    rate = 0.2  # rad/s about x: the attitude at a time says when it is
    errors = np.empty(len(t_wall))
    unavailable, worst_angle = 0, 0.0
    for i in range(len(t_wall)):
        mapped = clock.wall_us(int(boot[i]), int(arrival[i]))
        errors[i] = mapped - t_wall[i]
        history.add(mapped, Rotation.from_rotvec([rate * (t_wall[i] - t_wall[0]) * 1e-6, 0.0, 0.0]))
        if i >= 10 * hz and i % 4 == 0:  # a capture 40 ms ago, looked up when this sample has arrived
            capture = int(t_wall[i]) - 40_000
            R = history.attitude_at(capture)
            if R is None:
                unavailable += 1
                continue
            truth = Rotation.from_rotvec([rate * (capture - t_wall[0]) * 1e-6, 0.0, 0.0])
            worst_angle = max(worst_angle, (R.inv() * truth).magnitude())
    settled = errors[int(10 * hz) :]
    assert np.all(np.abs(errors[: int(10 * hz)] - floor_us) <= 25_000)
    assert settled.min() >= floor_us - 2_000 and settled.max() <= floor_us + 2_000
    assert unavailable == 0
    assert worst_angle <= rate * (floor_us + 2_000) * 1e-6 + 1e-9  # the stamp's error times the rate

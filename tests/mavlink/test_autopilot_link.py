"""The autopilot's body rates from ATTITUDE into the node's rate history (FRD -> FLU), for the cameras."""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np

from atlas_onboard.config import NodeConfig
from atlas_onboard.mavlink.autopilot_link import AutopilotLink

WALL_S = 1_700_000_000.0


def _attitude(boot_ms: int, p: float, q: float, r: float) -> SimpleNamespace:
    return SimpleNamespace(
        get_type=lambda: "ATTITUDE", time_boot_ms=boot_ms, roll=0.1, pitch=-0.05, yaw=1.0,
        rollspeed=p, pitchspeed=q, yawspeed=r,
    )  # fmt: skip


def test_attitude_rates_reach_the_cameras_in_body_flu() -> None:
    """A roll right (FRD +p), pitch up (FRD +q) and yaw right (FRD +r) read as FLU (+p, -q, -r), at the
    sample's mapped time, with a covariance that grows away from the samples; none when the sender left
    the rates at zero."""
    link = AutopilotLink(NodeConfig(entity="d1", system_id=1), 191, wall_clock=lambda: WALL_S)
    now = time.monotonic_ns()
    for k in range(5):
        link._on_attitude(_attitude(1000 + 20 * k, 0.3, 0.2, -0.4), now)
    t_last = link.attitude.latest_us()
    assert t_last is not None
    rate = link.rate_at(t_last - 10_000)
    assert rate is not None
    np.testing.assert_allclose(rate.omega_flu, [0.3, -0.2, 0.4])
    at_sample = link.rate_at(t_last)
    assert at_sample is not None and np.all(np.diag(rate.cov) > np.diag(at_sample.cov))
    assert link.rate_at(t_last + 60_000) is None  # the stream stopped
    still = AutopilotLink(NodeConfig(entity="d1", system_id=1), 191, wall_clock=lambda: WALL_S)
    still._on_attitude(_attitude(1000, 0.0, 0.0, 0.0), now)
    assert still.attitude.latest_us() is not None and still.rate_at(still.attitude.latest_us()) is None
    assert math.isfinite(float(np.trace(rate.cov)))
